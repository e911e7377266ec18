from glob import glob

from setuptools import find_packages, setup

PACKAGE = "wheelgrid_bringup"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/wheelgrid_bringup"]),
        ("share/wheelgrid_bringup", ["package.xml"]),
        ("share/" + PACKAGE, glob("config/*.yaml")),
        ("share/" + PACKAGE + "/launch", glob("launch/*.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="wheelgrid developers",
    maintainer_email="dev@wheelgrid.invalid",
    description="The wheelgrid command, parameter files and launch description for the whole chain.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": ["wheelgrid = wheelgrid_bringup.cli:main"],
    },
)
