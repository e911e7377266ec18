from setuptools import find_packages, setup

PACKAGE = "wheelgrid_sim"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/wheelgrid_sim"]),
        ("share/wheelgrid_sim", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="wheelgrid developers",
    maintainer_email="dev@wheelgrid.invalid",
    description="Synthetic iPhone-LiDAR room simulator with exact ground truth, written as rosbag2 bags.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [],
    },
)
