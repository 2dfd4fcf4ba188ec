from glob import glob

from setuptools import find_packages, setup

package_name = "bac_bringup"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/profiles", sorted(glob("profiles/*.yaml"))),
        ("share/" + package_name + "/params", sorted(glob("params/*.yaml"))),
        # `bac` on PATH once the install space is sourced (colcon adds <prefix>/bin); runs lib/bac_bringup/bac
        ("bin", ["bin/bac"]),
    ],
    package_data={package_name: ["py.typed"]},
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    zip_safe=True,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "Graph launcher and command-line entry points of bac: profiles (sim, car, replay), process "
        "supervision and network isolation."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "bac = bac_bringup.cli:main",
            "trial_announcer = bac_bringup.smoke_node:announcer_main",
            "trial_listener = bac_bringup.smoke_node:listener_main",
        ],
    },
)
