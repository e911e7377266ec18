"""`wheelgrid drive PLAN.json --port DEV` against the simulated controller on a pty."""

import csv
import itertools
import json
import math

import numpy as np
import pytest

from wheelgrid_common.map_io import Grid, write_map
from wheelgrid_drive import protocol as proto
from wheelgrid_drive.cli import main

CELLS = [[2, 0], [2, 1], [2, 2], [2, 3], [2, 4], [2, 5], [3, 5], [4, 5], [5, 5], [6, 5]]
MOVES = ["right"] * 5 + ["down"] * 4


def grid_of(rows, cols, res=1.2):
    """A plan's record of its grid (`wheelgrid plan --json`'s): rows x cols cells of ``res``
    with row 0 along y = 0, toward -y, the cells the plans here were written for."""
    return {"rows": rows, "cols": cols, "resolution": res, "origin": [0.0, -rows * res, 0.0]}


def table_ii_plan(with_actions=True, grid=None):
    plan = {"cells": CELLS, "moves": MOVES} | ({"grid": grid} if grid else {})
    if with_actions:
        heading = "down"
        acts = []
        for (a, b), m in zip(itertools.pairwise(CELLS), MOVES, strict=True):
            action = (
                "Forward"
                if m == heading
                else ("Left-Forward" if heading == "down" else "Right-Forward")
            )
            acts.append(
                {
                    "from": a,
                    "to": b,
                    "heading": heading,
                    "move": m,
                    "new_heading": m,
                    "action": action,
                }
            )
            heading = m
        plan["actions"] = acts
    return plan


def write(tmp_path, doc, name="plan.json"):
    path = tmp_path / name
    path.write_text(json.dumps(doc))
    return str(path)


def sim_moves(sim):
    return [e.detail for e in sim.events if e.what == "move"]


def test_drive_executes_the_table_ii_plan(make_sim, tmp_path, capsys):
    sim = make_sim()
    free = Grid(np.zeros((8, 8), np.int8), 1.2)
    grid = write_map(tmp_path / "grid.yaml", free)
    rc = main(
        [
            write(tmp_path, table_ii_plan()),
            "--port",
            sim.slave_path,
            "--grid",
            str(grid),
            "--set-pose",
            "--jsonl",
        ]
    )
    out = capsys.readouterr().out
    assert rc == 0, out
    recs = [json.loads(line) for line in out.splitlines() if line.startswith("{")]
    assert [r["action"] for r in recs] == ["LEFT_FORWARD"] + ["FORWARD"] * 4 + ["RIGHT_FORWARD"] + [
        "FORWARD"
    ] * 3
    assert all(r["ack"] == "ACK" for r in recs)
    assert sim_moves(sim) == [r["action"] for r in recs]
    # The chair ends on the centre of the goal cell (6, 5) of the grid.
    x, y = free.cell_center(6, 5)
    st = sim.status()
    assert (st.x, st.y) == pytest.approx((x, y), abs=0.01)


def test_speed_is_capped_and_heading_flag_works(make_sim, tmp_path, capsys):
    sim = make_sim()
    rc = main(
        [
            write(tmp_path, table_ii_plan(False)),
            "--port",
            sim.slave_path,
            "--heading",
            "down",
            "--speed",
            "9",
            "--cell-size",
            "1.0",
            "--no-pose-check",  # the plan names no grid: where its cells lie is not known
        ]
    )
    captured = capsys.readouterr()
    assert rc == 0 and "capped" in captured.err
    assert sim_moves(sim)[0] == "LEFT_FORWARD"
    assert sim.speed * 1000 == pytest.approx(proto.MAX_SPEED_MM_S)


def test_a_route_through_an_occupied_or_unknown_cell_is_refused_before_any_move(
    make_sim, tmp_path, capsys
):
    """The --grid is a file: a route that enters a cell it does not call free is refused
    before the first frame (exit 2). It used to drive the chair up to that cell and stop it
    there, mid-route (exit 1)."""
    for value in (100, -1):
        sim = make_sim()
        data = np.zeros((8, 8), np.int8)
        data[2, 3] = value  # the third step's destination
        grid = write_map(tmp_path / f"grid{value}.yaml", Grid(data, 1.2))
        rc = main([write(tmp_path, table_ii_plan()), "--port", sim.slave_path, "--grid", str(grid)])
        err = capsys.readouterr().err
        assert rc == 2
        assert "step 3/9" in err and "(2, 3)" in err
        assert ("occupied" if value == 100 else "unknown") in err and "nothing was sent" in err
        assert sim_moves(sim) == []
        assert sim.state == proto.State.IDLE
        # --dry-run reads the same route on the same grid: refused as well
        rc = main([write(tmp_path, table_ii_plan()), "--dry-run", "--grid", str(grid)])
        assert rc == 2 and "(2, 3)" in capsys.readouterr().err


def test_the_runner_still_stops_at_a_step_whose_cell_is_not_free(make_sim, make_link):
    """The step-by-step check stays (the drive node's grid changes under a move): the chair is
    stopped before the move into the refused cell, never after it."""
    from wheelgrid_drive.cli import load_plan
    from wheelgrid_drive.runner import grid_cell_check, run_steps

    sim = make_sim()
    link = make_link(sim.slave_path)
    steps, _ = load_plan(table_ii_plan())
    data = np.zeros((8, 8), np.int8)
    data[2, 3] = 100
    grid = Grid(data, 1.2)
    result = run_steps(
        link, steps, distance_m=1.2, speed_kmh=3.0, cell_check=grid_cell_check(lambda: grid)
    )
    assert not result.ok and result.done == 2 and "(2, 3)" in result.error
    assert sim_moves(sim) == ["LEFT_FORWARD", "FORWARD"]  # never the move into (2, 3)
    assert sim.state == proto.State.IDLE


@pytest.mark.parametrize(
    ("doc", "extra", "message"),
    [
        ({"cells": [[0, 0], [1, 1]]}, ["--heading", "up"], "4-neighbours"),
        ({"cells": CELLS, "moves": ["up"] * 9}, ["--heading", "down"], "disagree"),
        ({"cells": CELLS}, [], "heading"),
        (table_ii_plan(), ["--heading", "up"], "disagrees"),
        (
            {
                **table_ii_plan(),
                "actions": [{**a, "action": "FORWARD"} for a in table_ii_plan()["actions"]],
            },
            [],
            "Table II",
        ),
        ([1, 2], [], "JSON object"),
        # what `wheelgrid plan --json` writes for an unreachable goal ("no 'cells' list")
        (
            {"cells": [], "moves": [], "reason": "goal unreachable"},
            [],
            "the plan is empty: the planner found no route (goal unreachable)",
        ),
        # int() used to truncate these to cells, or to raise from inside load_plan
        ({"cells": [[2.9, 0.7], [3.9, 0.2]]}, ["--heading", "down"], "of integers"),
        ({"cells": [[True, 0], [1, 0]]}, ["--heading", "down"], "of integers"),
        ({"cells": [["2", 0], [3, 0]]}, ["--heading", "down"], "of integers"),
        ({"cells": [[1e400, 0], [1, 0]]}, ["--heading", "down"], "of integers"),
        ({"cells": [{"a": 1, "b": 2}, [1, 0]]}, ["--heading", "down"], "of integers"),
        (
            {"cells": [[2, 0], [3, 0], [4, 0]], "actions": [{"heading": "down"}, 5]},
            [],
            "list of objects",
        ),
    ],
)
def test_bad_plans_exit_2_without_moving(make_sim, tmp_path, capsys, doc, extra, message):
    sim = make_sim()
    rc = main([write(tmp_path, doc), "--port", sim.slave_path, *extra])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not any(e.what == "rx" for e in sim.events)


def test_a_plan_nested_too_deep_is_bad_input(tmp_path, capsys):
    plan = tmp_path / "deep.json"
    plan.write_text("[" * 100_000)
    assert main([str(plan), "--dry-run"]) == 2
    assert "RecursionError" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("extra", "message"),
    [
        (["--cell-size", "0"], "outside [0.001, 2]"),  # `or 1.2` made it 1.2 m silently
        (["--cell-size", "0.0004"], "outside [0.001, 2]"),  # 0 mm: refused only when sent
        (["--cell-size", "nan"], "outside [0.001, 2]"),
        (["--cell-size", "0.6"], "smaller than the chair (1 m)"),  # a gap it does not fit
        (["--speed", "0.001"], "--speed must be >= 0.1 km/h"),  # never ends in its timeout
        (["--speed", "nan"], "--speed must be >= 0.1 km/h"),
        (["--reply-timeout", "0"], "--reply-timeout must be in (0, 10] s"),
        (["--reply-timeout", "1e12"], "--reply-timeout must be in (0, 10] s"),  # OverflowError
        (["--reply-timeout", "nan"], "--reply-timeout must be in (0, 10] s"),
        (["--retries", "-1"], "--retries must be in 0..20"),  # no frame, STOP included, sent
        (["--baud", "0"], "--baud must be > 0"),  # baud 0 hangs up a real line
        (["--baud", "99999999999"], "--baud must be <= 12000000"),  # exit 1, the OS's words
    ],
)
def test_bad_settings_exit_2_before_any_frame(make_sim, tmp_path, capsys, extra, message):
    sim = make_sim()
    rc = main([write(tmp_path, table_ii_plan()), "--port", sim.slave_path, *extra])
    assert rc == 2
    assert message in capsys.readouterr().err
    assert not any(e.what == "rx" for e in sim.events)


def test_set_pose_beyond_what_the_controller_holds_is_bad_input(make_sim, tmp_path, capsys):
    sim = make_sim()
    # 3600 km east: int32 mm overflowed
    doc = {"cells": [[0, 3_000_000], [0, 3_000_001]], "grid": grid_of(1, 3_000_002)}
    argv = [write(tmp_path, doc), "--port", sim.slave_path, "--heading", "right", "--set-pose"]
    assert main(argv) == 2
    assert "--set-pose: the start cell's pose" in capsys.readouterr().err
    assert not any(e.what == "rx" for e in sim.events)


def test_missing_port_is_a_failure(tmp_path, capsys):
    plan = table_ii_plan(grid=grid_of(8, 8))
    rc = main([write(tmp_path, plan), "--port", str(tmp_path / "ttyNONE")])
    err = capsys.readouterr().err
    assert rc == 1 and "cannot open" in err
    # the OS's reason once, not pyserial's wrapper repeating errno and path
    assert "No such file or directory" in err and "Errno" not in err, err
    assert err.count("ttyNONE") == 1, err


def test_silent_controller_exits_1_and_stops(make_sim, tmp_path, capsys):
    sim = make_sim(time_scale=1.0)
    sim.drop_rx_next = 10**6  # the controller hears nothing any more: every request times out
    plan = table_ii_plan(grid=grid_of(8, 8))
    rc = main([write(tmp_path, plan), "--port", sim.slave_path, "--retries", "1"])
    assert rc == 1
    # STOP was sent, but a silent controller cannot confirm it: "chair stopped" would be a
    # claim nobody checked, so the user is told to check the chair
    err = capsys.readouterr().err
    assert "STOP NOT CONFIRMED" in err and "chair stopped" not in err, err


def test_planner_spelling_of_actions_is_accepted():
    from wheelgrid_drive.cli import load_plan

    plan = table_ii_plan()
    for a in plan["actions"]:
        a["action"] = a["action"].lower()  # wheelgrid_nav writes "left-forward"
    steps, cells = load_plan(plan)
    assert cells[0] == (2, 0) and steps[0].action == "LEFT_FORWARD" and steps[0].heading == "down"


def test_a_plan_from_the_chairs_own_unknown_cell_is_driven_and_an_occupied_start_refused(
    make_sim, tmp_path, capsys
):
    """``wheelgrid plan`` plans from the chair's own cell where the grid has it unknown (a
    sensor on the chair never sees the floor under it; ``allow_unknown_start``), and the drive
    node drives such plans; ``wheelgrid drive --grid`` refused them ("start cell (2, 0) is
    unknown"), so the planner's own output could not be driven from the command line. An
    occupied start is still refused, and every cell moved into must be free."""
    data = np.zeros((8, 8), np.int8)
    data[2, 0] = -1  # the start
    sim = make_sim()
    grid = write_map(tmp_path / "own_unknown.yaml", Grid(data, 1.2))
    argv = [write(tmp_path, table_ii_plan()), "--port", sim.slave_path, "--grid", str(grid)]
    rc = main([*argv, "--set-pose"])
    assert rc == 0, capsys.readouterr().err
    assert len(sim_moves(sim)) == 9
    data[2, 0] = 100
    grid = write_map(tmp_path / "own_occupied.yaml", Grid(data, 1.2))
    rc = main([write(tmp_path, table_ii_plan()), "--dry-run", "--grid", str(grid)])
    assert rc == 2 and "start cell (2, 0) is occupied" in capsys.readouterr().err


def _corridor(tmp_path):
    """A free corridor along row 3 between occupied rows, the start cell below it, and a plan
    along it: ``(grid, grid.yaml, plan.json)``."""
    data = np.full((7, 9), 100, np.int8)
    data[3, :] = 0
    data[4, 0] = 0
    grid = Grid(data, 1.2)
    cells = [[4, 0]] + [[3, c] for c in range(9)]
    return grid, write_map(tmp_path / "grid.yaml", grid), write(tmp_path, {"cells": cells})


def test_a_chair_drifting_off_its_route_is_stopped_before_it_leaves_the_free_cells(
    make_sim, tmp_path, capsys
):
    """Each step drives one cell's length from where the chair really stands. The command
    checked only the plan's cells: with a real chair's turn error (the simulator's 3 deg) it
    drove the whole free corridor's plan, exit 0, through three occupied cells beside it. It
    now reads the controller's pose before each step, as the drive node does, and stops."""
    grid, grid_yaml, plan = _corridor(tmp_path)
    log = tmp_path / "pose.csv"
    sim = make_sim(noise_deg=3.0, seed=0, pose_log=str(log))
    argv = [plan, "--port", sim.slave_path, "--grid", str(grid_yaml), "--set-pose"]
    rc = main([*argv, "--heading", "right"])
    err = capsys.readouterr().err
    assert rc == 1 and "refused" in err and "more than 0.25 cell" in err, err
    assert "chair stopped" in err
    sim.stop()
    rows = list(csv.DictReader(log.open()))[1:]  # the first: the power-on pose, before --set-pose
    assert rows
    for row in rows:
        r, c = grid.cell_of(float(row["x"]), float(row["y"]))
        assert grid.inside(r, c) and grid.data[r, c] == 0, row


def test_a_last_move_that_ends_outside_the_goal_cell_fails_and_stops(make_sim, tmp_path, capsys):
    """No next step reads where the last one ended: a last move reported done 0.6 m past its
    cell, into an occupied one, was "1/1 steps done", exit 0 (a review; the drive node
    checks it, "plan ended short of its goal"). The command now reads the controller's pose
    after the last step too."""
    data = np.zeros((4, 4), np.int8)
    data[2, 3] = 100  # just past the goal (2, 2)
    grid_yaml = write_map(tmp_path / "grid.yaml", Grid(data, 1.2))
    plan = tmp_path / "plan.json"
    plan.write_text(json.dumps({"cells": [[2, 1], [2, 2]], "moves": ["right"],
                                "actions": [{"heading": "right"}]}))  # fmt: skip
    sim = make_sim(noise_m=0.5, seed=1)  # this seed's move ends 0.64 m long
    rc = main([str(plan), "--port", sim.slave_path, "--grid", str(grid_yaml), "--set-pose"])
    err = capsys.readouterr().err
    st = sim.status()
    assert Grid(data, 1.2).cell_of(st.x, st.y) != (2, 2), "the seed no longer ends off its cell"
    assert rc == 1 and "the plan ended short of its goal" in err and "cell (2, 2)" in err, err
    assert "chair stopped" in err and sim.state == proto.State.IDLE


def test_a_controller_elsewhere_than_the_plans_start_is_refused_before_any_move(
    make_sim, tmp_path, capsys
):
    """Without --set-pose the command took the chair to stand on the plan's first cell and
    never read where the controller said it was: from a cell the grid calls occupied it drove
    the plan's moves through occupied cells, exit 0. ``--no-pose-check`` is the opt-out for a
    controller whose pose is not in the plan's frame."""
    grid, grid_yaml, plan = _corridor(tmp_path)
    x, y = grid.cell_center(6, 0)  # occupied, two cells below the start
    sim = make_sim(pose=(float(x), float(y), 0.0))
    rc = main([plan, "--port", sim.slave_path, "--grid", str(grid_yaml), "--heading", "up"])
    err = capsys.readouterr().err
    # told to drive there or plan again: it named --set-pose and --no-pose-check, and a
    # review that followed it drove a chair 7.7 m off its start past the grid's edge, exit 0
    assert rc == 1 and "step 1/9" in err and "plan again from where it stands" in err, err
    assert "--set-pose" not in err and "--no-pose-check" not in err, err
    assert sim_moves(sim) == []
    rc = main(
        [plan, "--port", sim.slave_path, "--cell-size", "1.2", "--heading", "up", "--no-pose-check"]
    )
    assert rc == 0 and len(sim_moves(sim)) == 9, capsys.readouterr().err


def test_a_plan_from_another_grid_or_not_verified_is_refused_and_a_wrong_heading_not_hinted_away(
    make_sim, tmp_path, capsys
):
    """A plan holds cell indices only: one made on 1.2 m cells drove 9/9 steps of 0.6 m on a
    0.6 m grid, exit 0, and one whose planner refused its route (reason, converged) was driven
    as well. `wheelgrid plan --json` now names its grid, and the drive compares it. A chair on
    its start cell but facing another way was told to use --set-pose, which would give the
    controller a heading the chair does not have."""
    from wheelgrid_nav.cli_plan import main as plan_main

    free = Grid(np.zeros((8, 8), np.int8), 1.2, origin=(0.0, -9.6, 0.0))
    grid_a = write_map(tmp_path / "a.yaml", free)
    grid_b = write_map(tmp_path / "b.yaml", Grid(free.data, 1.0, origin=free.origin))
    argv = [str(grid_a), "--start", "2,0", "--goal", "6,5", "--heading", "down", "--json"]
    assert plan_main(argv) == 0
    planned = json.loads(capsys.readouterr().out)
    assert planned["grid"]["resolution"] == 1.2 and planned["grid"]["rows"] == 8
    plan = write(tmp_path, planned)
    sim = make_sim()
    assert main([plan, "--port", sim.slave_path, "--grid", str(grid_b), "--set-pose"]) == 2
    assert "the plan was made on another grid than" in capsys.readouterr().err
    moved = {**planned, "grid": {**planned["grid"], "origin": [1.2, -9.6, 0.0]}}
    assert (
        main([write(tmp_path, moved, "m.json"), "--port", sim.slave_path, "--grid", str(grid_a)])
        == 2
    )
    assert "origin" in capsys.readouterr().err
    changed = free.data.copy()
    changed[7, 7] = 100  # off the route: the same geometry, other cells
    grid_c = write_map(tmp_path / "c.yaml", Grid(changed, 1.2, origin=free.origin))
    assert main([plan, "--dry-run", "--grid", str(grid_c)]) == 0
    assert "changed since the plan was made" in capsys.readouterr().err
    refused = {**planned, "reason": "verification failed: x", "converged": False}
    assert main([write(tmp_path, refused, "r.json"), "--port", sim.slave_path, "--dry-run"]) == 2
    assert "not a verified route (reason 'verification failed: x'" in capsys.readouterr().err
    assert sim_moves(sim) == []
    # without --grid: said, and the plan's own cell size (not 1.2 m by default)
    assert main([plan, "--dry-run"]) == 0
    captured = capsys.readouterr()
    assert "no --grid: nothing checks" in captured.err and "1.2 m per cell" in captured.out
    assert (
        main(
            [
                write(
                    tmp_path, {**planned, "grid": {**planned["grid"], "resolution": 1.1}}, "n.json"
                ),
                "--dry-run",
            ]
        )
        == 0
    )
    assert "1.1 m per cell" in capsys.readouterr().out
    # on its start cell, facing left where the plan starts facing down
    x, y = free.cell_center(2, 0)
    facing_left = make_sim(pose=(float(x), float(y), math.pi))
    assert main([plan, "--port", facing_left.slave_path, "--grid", str(grid_a)]) == 1
    err = capsys.readouterr().err
    assert "does not face the plan's start heading" in err and "--set-pose tells" not in err, err
    assert sim_moves(facing_left) == []


@pytest.mark.parametrize(
    ("sig", "code", "says", "ignored"),
    [
        ("SIGTERM", 143, "terminated (SIGTERM); chair stopped", False),
        # a closed terminal or ssh session: the command died at once, no STOP, 0.4 m on
        ("SIGHUP", 129, "terminated (SIGHUP); chair stopped", False),
        # started in the background by a script (`&`), SIGINT comes ignored: it drove on
        ("SIGINT", 130, "interrupted; chair stopped", True),
    ],
)
def test_a_signal_mid_move_stops_the_chair_as_ctrl_c_does(
    make_sim, tmp_path, sig, code, says, ignored
):
    """`wheelgrid drive` killed with SIGTERM (a launcher, systemd, `timeout`) or SIGHUP
    mid-move sent no STOP: the chair drove on until the controller's own watchdog stopped it,
    half a second later. It now stops the chair and says whether the controller heard it, as
    Ctrl-C does, and Ctrl-C works however the command was started."""
    import signal
    import subprocess

    from wheelgrid_common.services import poll_until
    from wheelgrid_common.testing import managed_process, python_module

    sim = make_sim(time_scale=1.0)  # real time: a 1.2 m cell takes 1.4 s
    plan = write(tmp_path, {"cells": [[0, 0], [0, 1], [0, 2]], "grid": grid_of(1, 3)})
    argv = python_module("wheelgrid_drive.cli", plan, "--port", sim.slave_path)
    argv += ["--heading", "right", "--set-pose", "--cell-size", "1.2", "--jsonl"]
    kw = {"preexec_fn": lambda: signal.signal(signal.SIGINT, signal.SIG_IGN)} if ignored else {}
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    with managed_process(argv, **pipes, **kw) as proc:
        assert poll_until(lambda: sim.result == proto.Result.RUNNING, 20.0, 0.01)
        proc.send_signal(getattr(signal, sig))
        out, err = proc.communicate(timeout=20.0)
    assert proc.returncode == code, err
    assert says in err, err
    assert sim.result == proto.Result.STOPPED  # not WATCHDOG: the host stopped it
    # the step under way has its record too (there was none), with where the chair stood
    (rec,) = [json.loads(ln) for ln in out.splitlines()]  # --jsonl: JSON lines alone
    assert rec["ack"] == "INTERRUPTED" and says in rec["reason"] and len(rec["pose"]) == 2
    assert rec["from"] == [0, 0] and rec["to"] == [0, 1], rec


def test_a_plan_without_moves_takes_the_heading_wheelgrid_plan_wrote(make_sim, tmp_path, capsys):
    """`wheelgrid plan --heading down` from a cell to itself writes "heading" and no actions:
    the drive refused it ("start heading unknown"), exit 2. It is 0 steps, the chair unmoved."""
    sim = make_sim()
    doc = {"cells": [[2, 2]], "moves": [], "reason": "ok", "heading": "down", "actions": []}
    assert main([write(tmp_path, doc), "--port", sim.slave_path]) == 0, capsys.readouterr().err
    assert not any(e.what == "move" for e in sim.events)
    doc["heading"] = "north"  # said as bad, not taken for none
    assert main([write(tmp_path, doc), "--port", sim.slave_path]) == 2
    assert "heading must be up/down/left/right" in capsys.readouterr().err


def _drive_table_ii(tmp_path, sim, *extra):
    free = Grid(np.zeros((8, 8), np.int8), 1.2)
    grid = write_map(tmp_path / "grid.yaml", free)
    argv = [write(tmp_path, table_ii_plan()), "--port", sim.slave_path, "--grid", str(grid)]
    return main([*argv, "--set-pose", *extra]), free


@pytest.mark.parametrize("seed", range(6))
def test_each_step_drives_to_the_next_centre_so_move_errors_do_not_add_up(
    make_sim, tmp_path, capsys, seed
):
    """Every step drove one cell's length from wherever the chair stood: with 8 cm of error a
    move (the controller's odometry reporting it) the chair drifted off the cells' centres
    until a step was refused half-way, 2 routes of 8 (a review). Each step now drives to the
    next cell's centre from the pose the controller reports, and the route ends on its goal."""
    sim = make_sim(noise_m=0.08, seed=seed)
    rc, free = _drive_table_ii(tmp_path, sim)
    assert rc == 0, capsys.readouterr().err
    st = sim.status()
    x, y = free.cell_center(6, 5)
    assert math.hypot(st.x - x, st.y - y) < 0.3  # the move's own error, not the route's


def test_a_route_from_a_chair_stopped_between_cell_centres_is_driven(make_sim, tmp_path, capsys):
    """A chair stopped mid-move (a new route, a cell closed ahead) stands more than a quarter
    cell from every centre: each route from there was refused at its first step, for good,
    and the chair was stranded (a review). It drives on from where it stands, to the next
    cell's centre."""
    free = Grid(np.zeros((8, 8), np.int8), 1.2)
    grid = write_map(tmp_path / "grid.yaml", free)
    x, y = free.cell_center(2, 2)
    sim = make_sim(pose=(float(x) + 0.59, float(y), 0.0))  # facing right, 0.59 m on
    plan = {"cells": [[2, 2], [2, 3], [2, 4]], "grid": grid_of(8, 8) | {"origin": [0, 0, 0]}}
    argv = [write(tmp_path, plan), "--port", sim.slave_path, "--grid", str(grid)]
    assert main([*argv, "--heading", "right"]) == 0, capsys.readouterr().err
    st = sim.status()
    assert (st.x, st.y) == pytest.approx(tuple(float(v) for v in free.cell_center(2, 4)), abs=1e-3)


def test_without_grid_the_pose_is_checked_on_the_cells_the_plan_was_made_on(
    make_sim, tmp_path, capsys
):
    """Without --grid the chair's pose was checked against cells of a grid made up at the
    origin, not the plan's: a chair on an occupied cell 3 m off the plan's start drove the
    whole route through occupied cells and out of the room, exit 0, and a chair on the start
    itself was refused (a review). The plan's own record of its grid places its cells; a plan
    without one is driven only with --no-pose-check."""
    planned_on = Grid(np.zeros((8, 8), np.int8), 1.2, (-1.3, -6.6, 0.0))
    plan = table_ii_plan(grid=grid_of(8, 8) | {"origin": list(planned_on.origin)})
    path = write(tmp_path, plan)
    x, y = (float(v) for v in planned_on.cell_center(2, 0))
    sim = make_sim(pose=(x, y, -math.pi / 2))  # on the start, facing down
    assert main([path, "--port", sim.slave_path]) == 0, capsys.readouterr().err
    st = sim.status()
    assert (st.x, st.y) == pytest.approx(tuple(float(v) for v in planned_on.cell_center(6, 5)))
    x, y = (float(v) for v in planned_on.cell_center(5, 1))
    elsewhere = make_sim(pose=(x, y, -math.pi / 2))  # 3.6 m off the start, the review's cell
    assert main([path, "--port", elsewhere.slave_path]) == 1
    assert "is in cell (5, 1), not in cell (2, 0)" in capsys.readouterr().err
    assert sim_moves(elsewhere) == []
    unplaced = write(tmp_path, table_ii_plan(), "unplaced.json")
    assert main([unplaced, "--port", elsewhere.slave_path]) == 2
    assert "where its cells lie is unknown" in capsys.readouterr().err
    assert main([unplaced, "--port", elsewhere.slave_path, "--set-pose", "--no-pose-check"]) == 2
    assert sim_moves(elsewhere) == []


def test_a_reader_that_leaves_the_jsonl_output_stops_the_route_and_says_so(make_sim, tmp_path):
    """`wheelgrid drive --jsonl | head -n 1`: the second record's print raised BrokenPipeError,
    which nothing caught: the route was abandoned after 2 of 9 moves with no word of it,
    exit 141 (a review). The chair is stopped and it is said, exit 1."""
    import subprocess

    from wheelgrid_common.testing import managed_process, python_module

    sim = make_sim(time_scale=5.0)
    free = write_map(tmp_path / "grid.yaml", Grid(np.zeros((8, 8), np.int8), 1.2))
    argv = python_module("wheelgrid_drive.cli", write(tmp_path, table_ii_plan()))
    argv += ["--port", sim.slave_path, "--grid", str(free), "--set-pose", "--jsonl"]
    pipes = {"stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    with managed_process(argv, **pipes) as proc:
        assert json.loads(proc.stdout.readline())["ack"] == "ACK"
        proc.stdout.close()  # the reader leaves
        _, err = proc.communicate(timeout=60)
    assert proc.returncode == 1, err
    assert "the output was closed (its reader left): the route is not driven on; chair " in err
    assert "stopped" in err and "Traceback" not in err
    assert len(sim_moves(sim)) < 9


def test_a_plans_record_of_its_grid_is_read_as_json_numbers():
    """``"rows": true`` passed as a count (a bool is a Python int) and ended in a traceback;
    a resolution written ``1`` placed the cells but was not the step length, which fell back
    to 1.2 m (a review)."""
    from wheelgrid_drive.cli import grid_of_plan

    good = grid_of(8, 8) | {"resolution": 1, "origin": [0, 0, 0]}
    g = grid_of_plan(good)
    assert g is not None and g.resolution == 1.0 and g.data.shape == (8, 8)
    for bad in ({"rows": True}, {"cols": False}, {"resolution": True}, {"origin": [0, True, 0]}):
        assert grid_of_plan(good | bad) is None, bad


def test_without_grid_a_whole_metre_plan_drives_its_own_cells(make_sim, tmp_path, capsys):
    """The plan's ``"resolution": 1`` is its step length without --grid, as 1.0 is: with
    --no-pose-check each move drives one cell's length (1.2 m, and the route ended 20 %
    beyond its goal)."""
    plan = table_ii_plan(grid=grid_of(8, 8) | {"resolution": 1, "origin": [0, 0, 0]})
    planned_on = Grid(np.zeros((8, 8), np.int8), 1.0)
    x, y = (float(v) for v in planned_on.cell_center(2, 0))
    for extra in ([], ["--no-pose-check"]):
        sim = make_sim(pose=(x, y, -math.pi / 2))
        argv = [write(tmp_path, plan), "--port", sim.slave_path, *extra]
        assert main(argv) == 0, capsys.readouterr().err
        st = sim.status()
        goal = tuple(float(v) for v in planned_on.cell_center(6, 5))
        assert (st.x, st.y) == pytest.approx(goal, abs=0.05), extra
