from setuptools import find_packages, setup

package_name = "bac_agent"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    package_data={package_name: ["py.typed"]},
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "Algorithm 1 of bac: run segmentation (cut and align), KPI scoring, the Bayesian- "
        "optimization engine and agent node with its campaign journal, the simulation-phase "
        "parameter reduction, rescoring and reports."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "run_segmenter = bac_agent.segmenter_node:main",
            "kpi_scorer = bac_agent.scorer_node:main",
            "bo_agent = bac_agent.agent_node:main",
        ],
    },
)
