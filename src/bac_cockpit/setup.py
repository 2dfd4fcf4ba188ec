from setuptools import find_packages, setup

package_name = "bac_cockpit"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
    ],
    # the page: its HTML, script, style and the vendored plotly.js (MIT, static/vendor/LICENSE-plotly.js.txt)
    package_data={package_name: ["py.typed", "static/*.html", "static/*.js", "static/*.css", "static/vendor/*"]},
    install_requires=["setuptools"],
    zip_safe=False,
    maintainer="bac developers",
    maintainer_email="bac@example.org",
    description=(
        "The calibration cockpit of bac: a live page of the campaign for the engineer and the driver, the same "
        "page for a campaign folder, and a terminal view."
    ),
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    entry_points={
        "console_scripts": [
            "cockpit = bac_cockpit.cockpit_node:main",
        ],
    },
)
