from glob import glob

from setuptools import find_packages, setup

package_name = "bac_common"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/calibrations", sorted(glob("calibrations/*.yaml"))),
    ],
    package_data={package_name: ["py.typed"]},
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    zip_safe=True,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "Pure-Python foundations shared by the bac packages: calibration definitions (parameter "
        "spaces, meta-parameters), progress metrics and common errors."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [],
        # the markers of the packages' unit tests, for pytest wherever they run (bac_common.pytest_markers)
        "pytest11": ["bac_markers = bac_common.pytest_markers"],
    },
)
