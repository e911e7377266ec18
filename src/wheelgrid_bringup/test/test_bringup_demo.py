"""The demo names the truth's room cells in whatever grid the chain published."""

import json
import math
import os

import numpy as np
import pytest

from wheelgrid_bringup.demo import heading_yaw, room_cells_in_grid
from wheelgrid_common.map_io import Grid, write_map


def _truth(tmp_path, map_from_room):
    write_map(tmp_path / "expected_grid.yaml", Grid(np.zeros((8, 8), np.int8), 1.2))
    return {"expected_grid": "expected_grid.yaml", "map_from_room": map_from_room.tolist()}


def test_aligned_grid_keeps_the_cells_and_heading(tmp_path):
    m = np.eye(4)
    m[:2, 3] = [-0.6, -6.6]  # map origin below the first pose, at room (0.6, 6.6)
    grid = Grid(np.zeros((8, 8), np.int8), 1.2, (-0.6, -6.6, 0.0))
    assert room_cells_in_grid(tmp_path, _truth(tmp_path, m), grid, (2, 0), (6, 5), "down") == (
        (2, 0),
        (6, 5),
        "down",
    )


def test_a_grid_turned_by_90_degrees_gets_other_labels_for_the_same_places(tmp_path):
    m = np.eye(4)
    m[:2, 3] = [-0.6, -6.6]
    # the same room, but the grid's axes turned +90 deg: its origin is the room's south-east corner
    grid = Grid(np.zeros((8, 8), np.int8), 1.2, (9.0, -6.6, math.pi / 2))
    start, goal, heading = room_cells_in_grid(
        tmp_path, _truth(tmp_path, m), grid, (2, 0), (6, 5), "down"
    )
    room = Grid(np.zeros((8, 8), np.int8), 1.2)
    for room_cell, cell in (((2, 0), start), ((6, 5), goal)):
        want = room.cell_center(*room_cell) + np.array([-0.6, -6.6])
        np.testing.assert_allclose(grid.cell_center(*cell), want, atol=1e-9)
    # "down" in the room is -y in the map; find it among the turned grid's directions
    assert abs(math.remainder(heading_yaw(grid, heading) + math.pi / 2, math.tau)) < 1e-9


@pytest.mark.ros
def test_the_status_line_shows_the_phone_bridge_and_leaves_out_a_drive_not_started():
    """`wheelgrid launch --iphone --no-drive` showed 'map 153/779 frames' with no word of the
    942 frames the bridge published, and 'drive - (0 cmds)' for a drive it never started."""
    from wheelgrid_bringup.chain import Monitor
    from wheelgrid_common.testing import rclpy_context

    with rclpy_context() as ctx:
        monitor = Monitor(ctx, "status_line_test")
        try:
            with monitor.state.lock:
                monitor.state.bridge = {"clients": "1", "frames_published": "942"}
                monitor.state.mapper = {"frames_used": "153", "frames_received": "779"}
            line = monitor.status_line(drive=False)
            assert line.startswith("phone 1 client(s), 942 frames published | map 153/779"), line
            assert "drive" not in line
            assert "drive - (0 cmds)" in monitor.status_line()
        finally:
            monitor.close()


def test_a_silent_mapper_is_said_on_the_status_line():
    """A mapper frozen mid-replay left "map 28/28" on the line for as long, read as mapping (a
    review): three of its status periods (5 s at least) without a status, and the line says
    for how long it has been silent."""
    from wheelgrid_bringup.chain import mapper_silence

    status = {"frames_used": "28", "status_period_s": "2.0"}
    assert mapper_silence(status, 100.0, now=105.9) == 0.0
    assert mapper_silence(status, 100.0, now=112.0) == pytest.approx(12.0)
    slow = {**status, "status_period_s": "10.0"}  # a mapper set to report every 10 s
    assert mapper_silence(slow, 100.0, now=125.0) == 0.0
    assert mapper_silence(slow, 100.0, now=131.0) == pytest.approx(31.0)
    assert mapper_silence({}, 0.0, now=500.0) == 0.0  # none yet: nothing said


def test_demo_never_deletes_a_folder_that_is_not_its_own(tmp_path, capsys):
    """`wheelgrid demo --out DIR` emptied DIR with shutil.rmtree whatever it held: `--out .`
    in the checkout, `--out ~` or `--out /tmp/s` beside the bag it replays were wiped without a
    word. Only a folder a demo made (its marker or summary.json) is replaced; anything else is
    refused with exit 2 before the chain starts, and nothing in it is touched."""
    from wheelgrid_bringup.demo import DEMO_MARKER, main, prepare_out

    mine = tmp_path / "precious"
    mine.mkdir()
    (mine / "thesis.txt").write_text("five years")
    bag = tmp_path / "no_bag_needed"  # refused before the bag is even opened
    assert main(["--out", str(mine), "--bag", str(bag)]) == 2
    err = capsys.readouterr().err
    assert "not a wheelgrid demo output folder" in err and str(mine) in err, err
    assert (mine / "thesis.txt").read_text() == "five years"
    assert prepare_out(tmp_path) is not None  # the folder above it: refused too
    assert (mine / "thesis.txt").exists()

    fresh = tmp_path / "fresh"  # a new folder, or an empty one, is made ready and marked
    assert prepare_out(fresh) is None
    assert (fresh / "logs").is_dir() and (fresh / DEMO_MARKER).exists()
    (fresh / "map.ply").write_text("an earlier run's")
    assert prepare_out(fresh) is None  # a demo's own folder is replaced, as before
    assert not (fresh / "map.ply").exists() and (fresh / DEMO_MARKER).exists()

    older = tmp_path / "older_demo"  # an out/ from before the marker: it has summary.json
    (older / "logs").mkdir(parents=True)
    (older / "summary.json").write_text("{}")
    assert prepare_out(older) is None and not (older / "summary.json").exists()

    empty = tmp_path / "empty"
    empty.mkdir()
    assert prepare_out(empty) is None

    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    assert "not a folder" in (prepare_out(a_file) or "")
    assert a_file.read_text() == "x"


def test_the_summary_names_the_out_folder_given_and_a_map_saved_on_exit(tmp_path, capsys):
    """It printed out/map.ply, out/grid.png ... whatever --out was, and "map not saved" after
    an early stop although the mapper had saved its map in on_exit/."""
    from wheelgrid_bringup.demo import print_summary
    from wheelgrid_common.fileio import write_ply

    out = tmp_path / "run1"
    (out / "on_exit").mkdir(parents=True)
    write_ply(out / "on_exit" / "map.ply", np.zeros((7, 3)))
    (out / "grid.png").write_bytes(b"")  # (a file not written is named as such)
    summary = {"map_points_saved": None, "map_saved_on_exit": str(out / "on_exit" / "map.ply"),
               "map_points_saved_on_exit": 7, "error": "interrupted"}  # fmt: skip
    print_summary(summary, out, 130)
    text = capsys.readouterr().out
    assert "the mapper saved 7 points on exit in " + str(out / "on_exit" / "map.ply") in text
    assert "out/" not in text.replace(str(out), "") and f"{out / 'grid.png'}" in text, text
    (out / "map.ply").write_bytes(b"")
    print_summary({"map_points_saved": 1234}, out, 0)
    assert f"1,234 points in {out / 'map.ply'}" in capsys.readouterr().out


def test_demo_arguments_say_what_they_expect_and_the_summary_names_only_files_written(
    tmp_path, capsys
):
    """`--start 2` said "invalid parse_cell value"; `--timeout nan` or `-5` ran (and the replay
    was never bounded by it); a failed run listed grid.png, route.png and commands.csv,
    which it never wrote."""
    import pytest

    from wheelgrid_bringup.demo import build_parser, paper_line, shown

    for argv, says in (
        (["--start", "2"], "expected a cell R,C such as 2,0"),
        (["--goal=-1,3"], "a cell's row and column count from 0"),
        (["--timeout", "nan"], "must be a number of seconds > 0"),
        (["--timeout", "-5"], "must be a number of seconds > 0"),
    ):
        with pytest.raises(SystemExit) as info:
            build_parser().parse_args(argv)
        assert info.value.code == 2 and says in capsys.readouterr().err, argv
    assert shown(tmp_path, "route.png") == "no route.png written"
    (tmp_path / "route.png").write_bytes(b"")
    assert shown(tmp_path, "route.png") == str(tmp_path / "route.png")
    assert paper_line({}) is None
    from wheelgrid_bringup.demo import shared_domain_warning

    mixed = {"frames": 210, "mapper": {"frames_used": "243", "frames_failed": "27"}}
    assert "another demo or chain shares this ROS domain" in shared_domain_warning(mixed)
    alone = {"frames": 210, "mapper": {"frames_used": "210", "frames_failed": "0"}}
    assert shared_domain_warning(alone) == "" and shared_domain_warning({}) == ""
    line = paper_line({"paper": {"grid_cells_as_expected": 63, "grid_cells": 64}})
    assert line == "  paper     grid 63/64 cells as expected"
    assert paper_line({"paper": {"error": "cannot compare"}}) == "  paper     cannot compare"


def test_a_demo_takes_a_domain_no_other_demo_holds_and_refuses_when_all_are_held(
    tmp_path, monkeypatch, capsys
):
    """Two demos run at once shared domain 217 and each mapped the other's frames (the summary
    could only warn afterwards). Each now takes a domain no other demo on the machine holds,
    in an order that starts from the checkout's domain and never is the checkout's."""
    from wheelgrid_bringup import demo
    from wheelgrid_common import ros_env

    order = demo.demo_domains("17")
    assert sorted(order) == list(demo.DEMO_DOMAINS) and order[0] == demo.DEMO_DOMAINS[17]
    assert 220 not in demo.demo_domains("220")  # never the inherited domain
    monkeypatch.setattr(ros_env, "DOMAIN_LOCK_DIR", tmp_path)
    held = [ros_env.claim_domain([d]) for d in demo.DEMO_DOMAINS]  # every one, as 18 demos
    try:
        assert all(h is not None and h[1] >= 0 for h in held)
        from wheelgrid_sim.cli import main as simulate  # a real bag: refused after opening it

        sim = tmp_path / "sim"
        assert simulate(["--seed", "7", "--frames", "2", "--out", str(sim)]) == 0
        capsys.readouterr()
        assert demo.main(["--bag", str(sim), "--out", str(tmp_path / "out")]) == 2
        err = capsys.readouterr().err
        assert "every demo domain (215-232) is held by another demo" in err, err
    finally:
        for h in held:
            if h is not None:
                os.close(h[1])


def test_a_start_or_goal_outside_the_simulated_room_is_refused_before_the_replay(tmp_path, capsys):
    """`--goal 9,9` on the paper room (8 x 8) replayed the whole bag, 2-3 minutes, and only
    then said the goal was not free."""
    import shutil

    from wheelgrid_bringup import demo

    sim = tmp_path / "sim"  # truth.json and its expected grid, but no bag: refused before it
    sim.mkdir()
    bundled = demo.repo_root() / "bags" / "paper_room"
    for name in ("truth.json", "expected_grid.yaml", "expected_grid.pgm"):
        shutil.copy(bundled / name, sim / name)
    truth = json.loads((sim / "truth.json").read_text())
    assert demo.cells_outside_room(sim, truth, {"start": (2, 0), "goal": (7, 7)}) is None
    assert demo.cells_outside_room(sim, truth, {"start": None, "goal": None}) is None
    why = demo.cells_outside_room(sim, truth, {"start": None, "goal": (9, 9)})
    assert why is not None and "--goal 9,9 lies outside the simulated room's 8 x 8 grid" in why
    assert demo.cells_outside_room(tmp_path, {}, {"goal": (99, 0)}) is None  # no truth: live
    # refused before the bag is opened (there is none here) and before --out is made
    assert demo.main(["--bag", str(sim), "--goal", "8,0", "--out", str(tmp_path / "o")]) == 2
    assert "--goal 8,0 lies outside" in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("text", ["{bad", "[1, 2]"])
def test_a_truth_json_that_is_not_one_is_one_line_and_exit_2(tmp_path, capsys, text):
    """A truth.json of `{bad` or `[1, 2]` beside a bag ended the demo in a traceback, exit 1
    (a review)."""
    from wheelgrid_bringup import demo

    sim = tmp_path / "sim"
    (sim / "scan").mkdir(parents=True)
    (sim / "truth.json").write_text(text)
    assert demo.main(["--bag", str(sim), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "truth.json" in err and "Traceback" not in err, err


def test_a_bag_without_truth_needs_its_start_and_goal_cells(tmp_path, capsys):
    """A rosbag2 folder without truth.json (an imported capture) was driven from the paper
    room's cells, (2, 0) to (6, 5), whatever the room (a review). It is refused, before
    anything starts, until --start and --goal say where."""
    from wheelgrid_bringup import demo

    bag = demo.repo_root() / "bags" / "paper_room" / "scan"  # the rosbag2 folder alone
    if not (bag / "metadata.yaml").exists():
        pytest.skip("bags/paper_room: not present")
    assert demo.main(["--bag", str(bag), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "no truth.json" in err and "--start R,C and --goal R,C" in err, err
    assert demo.main(["--bag", str(bag), "--start", "1,1", "--out", str(tmp_path / "o")]) == 2
    assert not (tmp_path / "o").exists()
