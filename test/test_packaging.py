"""Each ament_python package's package.xml as colcon and rosdep read it where a full ROS 2 is
installed: valid, and naming every ROS or rosdep package its code imports.

Nothing here checks this otherwise: the pip-wheel ROS of this machine runs the code whatever
package.xml says. A review found wheelgrid_common's manifest not XML at all (an unescaped
``<->`` in its description: colcon took it for a plain Python package, so ``ament_index``
never listed it) and eleven imports no manifest declared."""

from __future__ import annotations

import ast
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = sorted(p.parent for p in (ROOT / "src").glob("*/package.xml"))

#: Python modules that are not ROS packages, by their rosdep keys (rosdep's python.yaml).
ROSDEP_KEYS = {
    "numpy": "python3-numpy",
    "yaml": "python3-yaml",
    "PIL": "python3-pil",
    "serial": "python3-serial",
    "pytest": "python3-pytest",
    "hypothesis": "python3-hypothesis",
}
#: From PyPI only (requirements.lock), with no rosdep key: each manifest says so in a comment
#: (lz4 comes with rosbags, which reads the same MCAP chunks with it).
PYPI_ONLY = {"open3d", "kiss_icp", "rosbags", "lz4", "catkin_pkg"}
#: ROS packages whose names do not say so.
ROS_NAMED = {"rclpy", "launch", "launch_ros", "ament_index_python", "rosidl_runtime_py"}
#: The tests' shared harness, installed with wheelgrid_common so that every package's tests
#: reach it: test code, its imports test_depends.
HARNESS = "testing.py"


def manifest(pkg: Path) -> tuple[set[str], set[str]]:
    """(exec_depend, test_depend) as catkin_pkg parses them: colcon's and rosdep's parser."""
    from catkin_pkg.package import parse_package

    parsed = parse_package(str(pkg))  # raises on a manifest that is not valid
    return {d.name for d in parsed.exec_depends}, {d.name for d in parsed.test_depends}


def optional(node: ast.AST, parents: dict[ast.AST, ast.AST]) -> bool:
    """An import inside ``try: ... except ImportError`` (or ModuleNotFoundError, or Exception):
    the code runs without it (tf2_msgs probed: ``/tf`` only where it is installed)."""
    while node in parents:
        node = parents[node]
        if isinstance(node, ast.Try):
            for handler in node.handlers:
                names = ast.unparse(handler.type) if handler.type is not None else ""
                if any(n in names for n in ("ImportError", "ModuleNotFoundError", "Exception")):
                    return True
    return False


def imported(files: list[Path]) -> dict[str, str]:
    """Top-level names of the modules ``files`` import for sure -> a file that imports it."""
    found: dict[str, str] = {}
    for path in files:
        tree = ast.parse(path.read_text(), str(path))
        parents = {child: node for node in ast.walk(tree) for child in ast.iter_child_nodes(node)}
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            if optional(node, parents):
                continue
            for name in names:
                found.setdefault(name.split(".")[0], str(path.relative_to(ROOT)))
    return found


def needed(modules: dict[str, str], own: str) -> dict[str, str]:
    """The dependency each import needs declared (ROS package or rosdep key) -> where."""
    out: dict[str, str] = {}
    for name, where in modules.items():
        if name in sys.stdlib_module_names or name in PYPI_ONLY or name == own:
            continue
        if name in ROSDEP_KEYS:
            out[ROSDEP_KEYS[name]] = where
        elif (
            name in ROS_NAMED
            or name.startswith("wheelgrid_")
            or name.endswith(("_msgs", "_srvs", "_interfaces"))
        ):
            out[name] = where
        else:
            raise AssertionError(
                f"{where} imports {name}: say in this test whether it is a ROS package, a "
                "rosdep key or PyPI-only"
            )
    return out


def dependents(name: str) -> set[str]:
    """The packages that depend on ``name``, directly or not: a test of ``name`` may import
    them (the harness starts the whole chain through wheelgrid_bringup) but cannot declare
    them, which would be a cycle."""
    run = {p.name: manifest(p)[0] for p in PACKAGES}
    found: set[str] = set()
    more = {name}
    while more:
        more = {p for p, deps in run.items() if deps & more} - found
        found |= more
    return found


@pytest.mark.parametrize("pkg", PACKAGES, ids=[p.name for p in PACKAGES])
def test_every_import_is_a_declared_dependency(pkg: Path) -> None:
    pytest.importorskip("catkin_pkg", reason="catkin_pkg (colcon's manifest parser) missing")
    run, test = manifest(pkg)
    code = sorted((pkg / pkg.name).rglob("*.py")) + sorted((pkg / "launch").glob("*.py"))
    harness = [f for f in code if f.name == HARNESS]
    code = [f for f in code if f.name != HARNESS]
    missing = {
        dep: where for dep, where in needed(imported(code), pkg.name).items() if dep not in run
    }
    assert not missing, f"{pkg.name}: exec_depend missing for {missing}"
    tests = sorted((pkg / "test").glob("*.py")) + harness
    missing = {
        dep: where
        for dep, where in needed(imported(tests), pkg.name).items()
        if dep not in run | test | dependents(pkg.name)
    }
    assert not missing, f"{pkg.name}: test_depend missing for {missing}"


def test_colcon_finds_the_six_ament_python_packages_and_nothing_else() -> None:
    """colcon searches the whole workspace from where it runs (the repository root, where
    colcon.meta is): it found vendor/tf2_msgs, failed the build on its rosidl generators and,
    on a full ROS 2, would have laid a tf2_msgs holding TFMessage alone over the real one
    (scripts/setup.sh builds it with CMake, only where no tf2_msgs is installed). And it took
    wheelgrid_common, its manifest not XML, for a plain Python package (a review)."""
    colcon = shutil.which("colcon")
    if colcon is None:
        pytest.skip("colcon is not installed")
    out = subprocess.run(
        [colcon, "--log-base", os.devnull, "list"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    ).stdout
    found = sorted(tuple(line.split("\t")) for line in out.splitlines())
    assert found == [(p.name, str(p.relative_to(ROOT)), "(ros.ament_python)") for p in PACKAGES]
