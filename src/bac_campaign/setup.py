from setuptools import find_packages, setup

package_name = "bac_campaign"

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
        "Campaign tools of bac: the campaign recorder and bag player nodes, offline rescoring, replay, "
        "reports, simulated runs to bags."
    ),
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},  # colcon test runs pytest (tests_require is gone from setuptools)
    entry_points={
        "console_scripts": [
            "campaign_recorder = bac_campaign.recorder_node:main",
            "bag_player = bac_campaign.replay:main",
        ],
    },
)
