from setuptools import find_packages, setup

PACKAGE = "wheelgrid_nav"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test"]),
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/wheelgrid_nav"]),
        ("share/wheelgrid_nav", ["package.xml"]),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="wheelgrid developers",
    maintainer_email="dev@wheelgrid.invalid",
    description="The safe 2D grid map (wheelchair-sized cells) and the Q-learning planner.",
    license="Apache-2.0",
    extras_require={"test": ["pytest"]},
    entry_points={
        "console_scripts": [
            "grid = wheelgrid_nav.grid_node:main",
            "planner = wheelgrid_nav.planner_node:main",
        ],
    },
)
