from setuptools import find_packages, setup

package_name = "bac_measure"

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
        "The measurement chain of bac: cut and align of each run (segmentation), the comfort KPI, bag reading "
        "and writing, the run_segmenter and kpi_scorer nodes."
    ),
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    entry_points={
        "console_scripts": [
            "run_segmenter = bac_measure.segmenter_node:main",
            "kpi_scorer = bac_measure.scorer_node:main",
        ],
    },
)
