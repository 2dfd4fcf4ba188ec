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
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    zip_safe=True,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "The Bayesian-optimization agent of bac (paper algorithm 1): the ask/tell engine, the campaign state "
        "machine and its journal, the bo_agent node."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "bo_agent = bac_agent.agent_node:main",
        ],
    },
)
