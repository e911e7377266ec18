from setuptools import find_packages, setup

PACKAGE = "wheelgrid_drive"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/wheelgrid_drive"]),
        ("share/wheelgrid_drive", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="wheelgrid developers",
    maintainer_email="dev@wheelgrid.invalid",
    description="Table II action conversion, the serial motor-controller protocol and link, the drive node and a simulated controller.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "drive = wheelgrid_drive.drive_node:main",
            "wheelgrid-motor-sim = wheelgrid_drive.motor_sim:main",
        ],
    },
)
