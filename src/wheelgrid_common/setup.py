from setuptools import find_packages, setup

PACKAGE = "wheelgrid_common"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    package_data={PACKAGE: ["fastdds_loopback.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/wheelgrid_common"]),
        ("share/wheelgrid_common", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="wheelgrid developers",
    maintainer_email="dev@wheelgrid.invalid",
    description="Shared, ROS-light helpers: PointCloud2 <-> numpy, QoS profiles, ROS environment, file formats (PLY, TUM, map_server).",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [],
    },
)
