from setuptools import find_packages, setup

package_name = "bac_sim"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    package_data={package_name: ["py.typed", "data/*.json", "data/*.yaml"]},
    install_requires=["setuptools"],
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    zip_safe=True,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "Simulated vehicle for bac: a vectorized full-car model with semi-active dampers, roads, "
        "the controllers under calibration, IMU and driver models, the simulated ECU on CAN and the "
        "vehicle_sim node."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "vehicle_sim = bac_sim.vehicle_sim_node:main",
        ],
    },
)
