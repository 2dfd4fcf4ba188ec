from glob import glob

from setuptools import find_packages, setup

package_name = "bac_ecu_bridge"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/dbc", sorted(glob("bac_ecu_bridge/dbc/*.dbc"))),
    ],
    package_data={package_name: ["py.typed", "dbc/*.dbc"]},
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    zip_safe=True,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "The ECU bridge of bac: the CAN calibration protocol (DBC), a bounded apply/acknowledge "
        "transaction and the ecu_bridge node."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "ecu_bridge = bac_ecu_bridge.bridge_node:main",
        ],
    },
)
