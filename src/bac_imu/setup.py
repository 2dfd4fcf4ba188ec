from setuptools import find_packages, setup

package_name = "bac_imu"

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
        "IMU ingestion for bac: mounting rotation, bias and gravity removal, resampling and stream- health diagnostics."
    ),
    license="Apache-2.0",
    entry_points={
        "console_scripts": [
            "imu_ingest = bac_imu.ingest_node:main",
        ],
    },
)
