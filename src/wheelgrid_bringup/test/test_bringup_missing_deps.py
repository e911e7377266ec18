"""A pip dependency not installed (on a full ROS 2 rosdep brings no kiss-icp, open3d or
rosbags) is one line naming its pip package, exit 2, from each command that needs it: not a
traceback, and not an error that blames the user's file (a review: bag-recover called an
intact bag "damaged before the cut", `wheelgrid grid` a PCD "not readable", and `wheelgrid
drive` a port it "cannot open")."""

from __future__ import annotations

from pathlib import Path

import pytest

from wheelgrid_bringup import cli
from wheelgrid_common.testing import not_installed, shared_data

BUNDLED = Path(__file__).resolve().parents[3] / "bags" / "paper_room"
# a real PCL scan: binary_compressed, the PCD kind read through open3d
PCD = shared_data("pcl-room-scans", Path(__file__).resolve().parents[3]) / "room_scan1.pcd"


@pytest.mark.parametrize(
    ("module", "pip", "argv"),
    [
        # kiss-icp: a traceback from deep in the registration, exit 1 (a review); the mapper
        # node's start says the same line (test_mapping_node_exit.py)
        ("kiss_icp", "kiss-icp", ["map", "{bag}", "--out", "{tmp}/m", "--max-frames", "3"]),
        ("serial", "pyserial", ["drive", "{tmp}/plan.json", "--port", "/dev/null"]),
        ("rosbags", "rosbags", ["bag-recover", "{bag}", "--out", "{tmp}/rec"]),
        ("rosbags", "rosbags", ["simulate", "--seed", "3", "--frames", "2", "--out", "{tmp}/s"]),
        ("open3d", "open3d", ["grid", "{pcd}", "--level", "--out", "{tmp}/g"]),
    ],
)
def test_a_missing_dependency_is_named_not_blamed_on_the_input(
    module: str, pip: str, argv: list[str], tmp_path: Path, monkeypatch, capsys
) -> None:
    if "{bag}" in argv and not (BUNDLED / "scan" / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")
    if "{pcd}" in argv and not PCD.is_file():
        pytest.skip(f"{PCD}: the real PCL scans are not present")
    args = [a.format(tmp=tmp_path, bag=BUNDLED / "scan", pcd=PCD) for a in argv]
    not_installed(monkeypatch, module)
    assert cli.main(args) == 2
    err = capsys.readouterr().err
    assert f"wheelgrid {argv[0]}: the Python package {pip} is not installed" in err, err
    assert "Traceback" not in err and "damaged" not in err and "cannot open" not in err
