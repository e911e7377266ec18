from setuptools import find_packages, setup

PACKAGE = "wheelgrid_mapping"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/wheelgrid_mapping"]),
        ("share/wheelgrid_mapping", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="wheelgrid developers",
    maintainer_email="dev@wheelgrid.invalid",
    description="Filters and registers iPhone-LiDAR PointCloud2 frames (KISS-ICP) into a levelled 3D map; the iPhone bridge.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "mapper = wheelgrid_mapping.mapper_node:main",
            "depth_to_cloud = wheelgrid_mapping.depth_to_cloud_node:main",
            "iphone_bridge = wheelgrid_mapping.iphone_bridge_node:main",
        ],
    },
)
