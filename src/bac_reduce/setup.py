from setuptools import find_packages, setup

package_name = "bac_reduce"

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
        "The simulation phase of bac (paper sec. III-D): M BO campaigns on the simulator, sensitivity, "
        "significance and similarity of the parameters, the meta-parameter file."
    ),
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    entry_points={
        "console_scripts": [],
    },
)
