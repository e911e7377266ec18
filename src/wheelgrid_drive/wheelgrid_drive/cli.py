"""``wheelgrid drive PLAN.json --port DEV``: send a plan to the motor controller over serial.

The plan comes from ``wheelgrid plan --json``: an object with ``cells`` [[r, c], ...], ``moves``
[...] and optionally ``actions`` (Table II rows). Everything in it is cross-checked before the
chair moves (cells are 4-neighbours, moves agree with cells, given actions agree with our own
Table II conversion): a plan that disagrees with itself is a bad plan, and a wheelchair does not
execute bad plans. Exit codes: 0 done, 1 a step failed (the chair has been stopped), 2 bad input.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import signal
import sys
import threading
from pathlib import Path
from typing import Any, TypeGuard

import numpy as np

from wheelgrid_common.params import DefaultsHelpFormatter
from wheelgrid_drive import actions
from wheelgrid_drive import protocol as proto
from wheelgrid_drive.link import LinkError, MotorLink, check_link_settings
from wheelgrid_drive.runner import (
    OFF_CELL,
    OFF_LINE,
    OFF_SIDE,
    CellCheck,
    command_record,
    controller_step_length,
    grid_cell_check,
    off_centre_problem,
    run_steps,
)


class PlanError(ValueError):
    """The plan file is unusable (message is shown to the user as is)."""


def load_plan(
    doc: Any, heading: str | None = None
) -> tuple[list[actions.Step], list[tuple[int, int]]]:
    """Validate a plan object and convert it to Table II steps: ``(steps, cells)``."""
    if not isinstance(doc, dict):
        raise PlanError("plan must be a JSON object with 'cells'")
    cells_raw = doc.get("cells")
    if cells_raw == []:
        # what `wheelgrid plan --json` writes when it finds no route: say so, with its reason
        reason = doc.get("reason")
        raise PlanError(
            "the plan is empty: the planner found no route"
            + (f" ({reason})" if isinstance(reason, str) and reason else "")
            + "; nothing to drive"
        )
    if not isinstance(cells_raw, list):
        raise PlanError("plan has no 'cells' list")
    # `wheelgrid plan` writes cells only for a verified route; a file that says otherwise (a
    # planner's refusal edited, another tool's output) was driven all the same
    reason = doc.get("reason", "ok")
    if reason != "ok" or doc.get("converged", True) is not True:
        raise PlanError(
            f"the plan is not a verified route (reason {reason!r}, converged "
            f"{doc.get('converged', '?')}); nothing to drive"
        )
    # Integers only: int() truncated [2.9, 0.7] to (2, 0) and took true and "3" as cells, and
    # a wheelchair must not guess which cell a plan meant.
    if not all(
        isinstance(c, list) and len(c) == 2 and all(type(v) is int for v in c) for c in cells_raw
    ):
        raise PlanError("'cells' must be [[row, col], ...] of integers")
    cells = [(int(c[0]), int(c[1])) for c in cells_raw]
    try:
        moves = actions.moves_from_cells(cells)
    except ValueError as exc:
        raise PlanError(str(exc)) from exc
    given_moves = doc.get("moves")
    if given_moves is not None and (
        not isinstance(given_moves, list) or [str(m).lower() for m in given_moves] != moves
    ):
        raise PlanError(f"'moves' {given_moves} disagree with 'cells' (which give {moves})")
    acts = doc.get("actions")
    plan_heading = None
    if acts:
        if not isinstance(acts, list) or not all(isinstance(a, dict) for a in acts):
            raise PlanError("'actions' must be a list of objects")
        plan_heading = str(acts[0].get("heading", "")).lower() or None
    elif isinstance(doc.get("heading"), str):  # no move: `wheelgrid plan --heading` says it
        plan_heading = doc["heading"].lower() or None
    if heading and plan_heading and heading.lower() != plan_heading:
        raise PlanError(
            f"--heading {heading} disagrees with the plan's start heading {plan_heading}"
        )
    start_heading = (heading or plan_heading or "").lower()
    if not start_heading:
        raise PlanError("start heading unknown: the plan has no 'actions'; give --heading")
    if start_heading not in actions.DELTA:
        raise PlanError(f"heading must be up/down/left/right, got {start_heading!r}")
    steps = actions.plan_steps(cells[0], moves, start_heading)
    if acts:
        if len(acts) != len(steps):
            raise PlanError(f"plan has {len(acts)} actions for {len(steps)} moves")
        for i, (given, step) in enumerate(zip(acts, steps, strict=True)):
            ours = step.to_json()
            for key, value in ours.items():
                if key in given and _norm(given[key]) != _norm(value):
                    raise PlanError(
                        f"action {i + 1}: plan says {key}={given[key]!r}, Table II gives {value!r}"
                    )
    return steps, cells


def plan_grid_problem(planned: Any, grid: Any) -> tuple[str | None, bool]:
    """Why the grid a plan names (``wheelgrid plan --json``'s ``grid``, made by
    :func:`~wheelgrid_common.map_io.grid_identity`) is not ``grid`` (None: it is, or the plan
    names none, from before it did or another tool), and whether the cells changed since.
    Changed cells on the same geometry are no refusal: every cell of the route is checked
    free on ``grid`` anyway."""
    from wheelgrid_common.map_io import grid_identity

    if not isinstance(planned, dict):
        return None, False
    ours = grid_identity(grid)
    rows, cols = ours["rows"], ours["cols"]
    if (planned.get("rows"), planned.get("cols")) != (rows, cols):
        return f"{planned.get('rows')} x {planned.get('cols')} cells, not {rows} x {cols}", False
    res = planned.get("resolution")
    if not isinstance(res, int | float) or abs(res - ours["resolution"]) > 1e-9:
        return f"cells of {res} m, not {ours['resolution']:g} m", False
    origin = planned.get("origin")
    if not (
        isinstance(origin, list)
        and len(origin) == 3
        and all(
            isinstance(v, int | float) and abs(v - o) <= 1e-6
            for v, o in zip(origin, ours["origin"], strict=True)
        )
    ):
        return f"origin {origin}, not {[round(v, 6) for v in ours['origin']]}", False
    digest = planned.get("cells_sha256")
    return None, digest is not None and digest != ours["cells_sha256"]


def _norm(v: Any) -> Any:
    if isinstance(v, list | tuple):
        return [_norm(x) for x in v]
    if isinstance(v, str):
        return v.strip().upper().replace("-", "_")
    return v


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wheelgrid drive",
        description="Convert a plan's moves into chair actions (the paper's Table II) and send "
        "them to the motor controller over serial (docs/serial-protocol.md). The chair is "
        "stopped on any failure.",
        formatter_class=DefaultsHelpFormatter,
    )
    p.add_argument("plan", help="plan JSON from 'wheelgrid plan --json'")
    p.add_argument("--port", help="serial device of the motor controller (or a simulator pty)")
    p.add_argument("--baud", type=int, default=115200, help="serial speed (bit/s)")
    p.add_argument(
        "--heading",
        choices=list(actions.DELTA),
        help="the chair's start heading (default: the plan's)",
    )
    p.add_argument(
        "--cell-size",
        type=float,
        default=None,
        help="metres per cell (default: the --grid's resolution, else the plan's, else 1.2)",
    )
    p.add_argument(
        "--speed", type=float, default=3.0, help=f"km/h, capped at {proto.MAX_SPEED_KMH:g}"
    )
    p.add_argument("--grid", help="safe grid YAML: refuse any step into a cell not free in it")
    p.add_argument(
        "--set-pose",
        action="store_true",
        help="first tell the controller it stands on the start cell centre (simulator/demo)",
    )
    p.add_argument(
        "--no-pose-check",
        action="store_true",
        help="drive without the controller's reported pose (for a controller whose pose is not "
        "in the plan's frame): each step then drives one cell from wherever the chair stands, "
        "where with it each drives to the next cell's centre",
    )
    p.add_argument("--reply-timeout", type=float, default=0.1, help="seconds per attempt")
    p.add_argument("--retries", type=int, default=3, help="resends of an unanswered frame")
    p.add_argument("--dry-run", action="store_true", help="print the Table II rows only")
    p.add_argument("--jsonl", action="store_true", help="print one JSON object per command")
    return p


def _err(msg: str) -> int:
    print(f"wheelgrid drive: {msg}", file=sys.stderr)
    return 2


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(sys.argv[1:] if argv is None else argv)
    import serial  # noqa: F401  (not installed: one line from `wheelgrid`, not "cannot open")

    try:
        doc = json.loads(Path(args.plan).read_text())
    except (OSError, ValueError, RecursionError) as exc:  # RecursionError: nested too deep
        return _err(f"cannot read plan {args.plan}: {type(exc).__name__}: {exc}")
    try:
        steps, cells = load_plan(doc, args.heading)
    except PlanError as exc:
        return _err(str(exc))
    if not args.speed >= proto.MIN_SPEED_KMH:  # NaN too
        return _err(f"--speed must be >= {proto.MIN_SPEED_KMH:g} km/h, not {args.speed:g}")
    try:
        check_link_settings(args.baud, args.reply_timeout, args.retries)
    except ValueError as exc:
        return _err(f"--{str(exc).replace('_', '-')}")
    if args.speed > proto.MAX_SPEED_KMH:
        print(
            f"wheelgrid drive: --speed {args.speed:g} km/h capped at {proto.MAX_SPEED_KMH:g} km/h",
            file=sys.stderr,
        )
    speed = min(args.speed, proto.MAX_SPEED_KMH)
    grid = None
    if args.grid:
        from wheelgrid_common.map_io import read_map

        try:
            grid = read_map(args.grid)
        except (OSError, ValueError) as exc:
            return _err(f"cannot read grid {args.grid}: {exc}")
        if args.cell_size is not None and abs(args.cell_size - grid.resolution) > 1e-6:
            return _err(f"--cell-size {args.cell_size} != grid resolution {grid.resolution}")
        problem, changed = plan_grid_problem(doc.get("grid"), grid)
        if problem:
            return _err(f"the plan was made on another grid than {args.grid}: {problem}")
        if changed:
            print(
                f"wheelgrid drive: warning: cells of {args.grid} changed since the plan was made "
                "on it; every cell of the route is checked free on it as it is now",
                file=sys.stderr,
            )
    planned_on = doc.get("grid") if isinstance(doc.get("grid"), dict) else {}
    if grid is None:
        print(
            "wheelgrid drive: warning: no --grid: nothing checks that the route's cells are "
            "free (give the grid the plan was made on)",
            file=sys.stderr,
        )
        planned_res = planned_on.get("resolution")
        if _number(planned_res) and planned_res > 0:  # JSON's 1 is an int, as good as 1.0
            if args.cell_size is not None and abs(args.cell_size - planned_res) > 1e-6:
                return _err(
                    f"--cell-size {args.cell_size:g} m, but the plan was made on cells of "
                    f"{planned_res:g} m: every step would drive the wrong length"
                )
            args.cell_size = planned_res  # the plan's own cells, not 1.2 m
    cell_size = grid.resolution if grid is not None else args.cell_size
    if cell_size is None:
        cell_size = 1.2
    if problem := proto.move_length_problem(cell_size):
        return _err(problem)
    from wheelgrid_common.map_io import CHAIR_GRID_HINT, chair_cell_problem

    if problem := chair_cell_problem(cell_size):
        return _err(f"{problem}; {CHAIR_GRID_HINT}")
    check: CellCheck | None = grid_cell_check(lambda: grid) if grid is not None else None
    if check is not None:
        from wheelgrid_common.map_io import UNKNOWN

        assert grid is not None
        r0, c0 = cells[0]
        # The chair's own cell may be unknown, as the planner allows (allow_unknown_start): a
        # sensor on the chair never sees the floor under it. Refused here, `wheelgrid plan`'s
        # own plans on such a grid could not be driven; the drive node already took them.
        # Every cell the chair moves into must still be free (below).
        own_unknown = grid.inside(r0, c0) and int(grid.data[r0][c0]) == UNKNOWN
        bad = None if own_unknown else check(cells[0])
        if bad:
            return _err(f"start {bad}")
        # The grid is a file: every cell of the route is known now. Checked only step by step,
        # a route through a cell the grid does not call free drove the chair up to it and
        # stopped it there, mid-route, with exit 1. The runner still checks each step.
        for k, cell in enumerate(cells[1:], 1):
            bad = check(cell)
            if bad:
                return _err(
                    f"step {k}/{len(cells) - 1} of the plan goes into {bad} in {args.grid}: "
                    "the route is not free on this grid; plan again on it (nothing was sent)"
                )

    # with --jsonl, stdout is JSON lines alone (a reader parsed the header as a record)
    notes = sys.stderr if args.jsonl else sys.stdout
    print(
        f"wheelgrid drive: {len(steps)} step(s) from {cells[0]} "
        f"heading {steps[0].heading if steps else '-'}"
        f", {cell_size:g} m per cell at {speed:g} km/h",
        file=notes,
    )
    # where the plan's cells lie: the grid's, else the plan's own record of it (a chair's pose
    # checked against cells of a grid made up at the origin, without --grid, drove a route
    # from an occupied cell through occupied ones, out of the room, exit 0; a review)
    where = grid if grid is not None else grid_of_plan(planned_on)
    if where is None and steps and not args.dry_run and (args.set_pose or not args.no_pose_check):
        return _err(
            "no --grid, and the plan does not say which grid it was made on (a plan of another "
            "tool): where its cells lie is unknown, so the chair's pose cannot be checked "
            "against them; give --grid (or --no-pose-check, without --set-pose, for a "
            "controller whose pose is not in the plan's frame)"
        )
    if args.dry_run or not steps:
        for i, s in enumerate(steps, 1):
            if args.jsonl:
                print(json.dumps(s.to_json()))
            else:
                print(f"  {i}: {_describe(s)}")
        return 0
    if not args.port:
        return _err("--port is required (or --dry-run)")
    start_pose = None
    if args.set_pose:
        assert where is not None
        x, y = (float(v) for v in where.cell_center(*cells[0]))
        yaw = actions.YAW[steps[0].heading] + float(where.origin[2])
        try:
            proto.pack_pose(x, y, yaw)
        except ValueError as exc:
            return _err(f"--set-pose: the start cell's {exc}")
        start_pose = (x, y, yaw)

    def on_event(kind: str, message: str) -> None:
        if kind not in ("timeout",):
            print(f"  ! {kind}: {message}", file=sys.stderr)

    link = MotorLink(
        args.port,
        args.baud,
        reply_timeout=args.reply_timeout,
        retries=args.retries,
        on_event=on_event,
    )
    try:
        link.open()
    except LinkError as exc:
        print(f"wheelgrid drive: {exc}", file=sys.stderr)
        return 1
    total = len(steps)
    counter = {"i": 0}
    current: list[actions.Step] = []  # the step whose checks or move are under way

    def on_start(step: actions.Step) -> None:
        current[:] = [step]

    def on_step(step: actions.Step, rec: dict[str, Any]) -> None:
        current.clear()
        counter["i"] += 1
        if args.jsonl:
            print(json.dumps(rec), flush=True)
            return
        extra = f" seq {rec['seq']}," if "seq" in rec else ""
        if "pose" in rec:
            x, y = rec["pose"]
            extra += f" chair at x {x:.3f} m, y {y:.3f} m"
        reason = f": {rec['reason']}" if "reason" in rec else ""
        line = f"  {counter['i']}/{total}: {_describe(step)} -> {rec['ack']}{extra}{reason}"
        print(line, flush=True)

    replaced = _stop_on_signals()
    try:
        link.start_heartbeat()
        st = link.status()
        if st.moving:
            link.stop()
            msg = "the controller reports a move in progress; stopped"
            print(f"wheelgrid drive: {msg}", file=sys.stderr)
            return 1
        if start_pose is not None:
            link.set_pose(*start_pose)
        result = run_steps(
            link,
            steps,
            distance_m=cell_size,
            speed_kmh=speed,
            cell_check=check,
            on_step=on_step,
            # each step drives to the next cell's centre from where the chair really stands:
            # checked on the plan's cells alone, a chair turned a few degrees per turn, or
            # standing off the plan's start, drove a free-checked route through occupied
            # cells, exit 0
            step_length=None if args.no_pose_check else controller_step_length(link, where),
            on_start=on_start,
        )
        # the runner sent STOP already; once more, to learn whether the controller heard it
        stop_note = "" if result.ok else _stopped(link)
        short = None
        if result.ok and not args.no_pose_check:
            # a last move reported done short of (or past) its cell was "steps done", exit 0,
            # with the chair in another cell, an occupied one included: no next step's check
            # reads it (the drive node checks it, "plan ended short of its goal")
            st = link.status()
            short = off_centre_problem(where, st.x, st.y, cells[-1])
            if short:
                stop_note = _stopped(link)
    except (LinkError, KeyboardInterrupt, Terminated, BrokenPipeError) as exc:
        stopped = _stopped(link)
        if isinstance(exc, LinkError):
            why, code = str(exc), 1
        elif isinstance(exc, BrokenPipeError):
            # `--jsonl | head -n 1`: the route was abandoned with no word of it, exit 141 (a
            # review). Said on stderr; stdout, gone, goes to /dev/null from here on
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
            why, code = "the output was closed (its reader left): the route is not driven on", 1
        elif isinstance(exc, KeyboardInterrupt):
            why, code = "interrupted", 130
        else:
            why, code = f"terminated ({signal.Signals(exc.signum).name})", 128 + exc.signum
        if current:  # the step under way: the only one no record said anything of
            rec = command_record(current[0], "INTERRUPTED", reason=f"{why}; {stopped}")
            last = link.last_status
            if last is not None:
                rec["pose"] = [round(last.x, 3), round(last.y, 3)]
            on_step(current[0], rec)
        print(f"wheelgrid drive: {why}; {stopped}", file=sys.stderr)
        return code
    finally:
        for sig, handler in replaced.items():
            signal.signal(sig, handler)
        link.close()
    if short:
        print(
            f"wheelgrid drive: the plan ended short of its goal: {short}; {stop_note}",
            file=sys.stderr,
        )
        return 1
    if not result.ok:
        hint = ""
        if result.refused and result.done == 0 and OFF_CELL in result.error:
            # It named --set-pose and --no-pose-check: followed, a chair 7.7 m off the start
            # drove the plan's moves from where it stood, past the grid's edge, exit 0 (a
            # review). Neither is a way past this for a real chair.
            hint = (
                " (the controller's pose is not on the plan's start cell: drive the chair "
                "there, or plan again from where it stands, `wheelgrid plan --start-xy X,Y`)"
            )
        elif result.refused and result.done == 0 and OFF_SIDE in result.error:
            hint = (
                " (the chair stands too far off its start cell's centre for this move: drive "
                "it nearer the centre first)"
            )
        elif result.refused and result.done == 0 and OFF_LINE in result.error:
            # the chair stands on its cell but faces another way: --set-pose would overwrite
            # the controller's heading with the plan's, and every move would go astray
            hint = (
                " (the chair does not face the plan's start heading: turn it, or plan again "
                "with --heading as it stands; --set-pose would tell the controller a heading "
                "the chair does not have)"
            )
        print(
            f"wheelgrid drive: step {result.done + 1}/{result.total} failed: {result.error}"
            f"{hint}; {stop_note}",
            file=sys.stderr,
        )
        return 1
    ls = link.stats
    print(
        f"wheelgrid drive: {result.done}/{result.total} steps done; link: {ls.sent} frames sent, "
        f"{ls.replies} replies, {ls.retries} retries, {ls.timeouts} timeouts, {ls.garbled} "
        f"garbled, {ls.naks} NAKs",
        file=notes,
    )
    return 0


STOP_UNCONFIRMED = (
    "STOP NOT CONFIRMED by the controller: the chair may still be moving (its own watchdog "
    "stops it 0.5 s after the last frame); check the chair"
)


class Terminated(BaseException):
    """SIGTERM or SIGHUP (a launcher, systemd, ``timeout``, a closed terminal or ssh session)
    while the chair drives: raised where the run is, as Ctrl-C's KeyboardInterrupt is, and a
    BaseException for the same reason (no ``except Exception`` on the way swallows it)."""

    def __init__(self, signum: int) -> None:
        super().__init__(signum)
        self.signum = signum


def _raise_terminated(signum: int, frame: Any) -> None:
    raise Terminated(signum)


STOPPING_SIGNALS = (signal.SIGTERM, signal.SIGHUP)


def _stop_on_signals() -> dict[int, Any]:
    """Make SIGTERM, SIGHUP and SIGINT stop the chair, and return the handlers replaced ({}
    where none can be set: not the main thread). SIGTERM, and then SIGHUP (the terminal
    closed), killed the command outright mid-move with no STOP sent: the chair drove on until
    the controller's own watchdog, 0.4 m. And a command started in the background by a
    script (`&`) inherits SIGINT ignored: its Ctrl-C, or a launcher's SIGINT, drove on."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    previous: dict[int, Any] = {}
    for sig, handler in (
        *((s, _raise_terminated) for s in STOPPING_SIGNALS),
        (signal.SIGINT, signal.default_int_handler),
    ):
        old = signal.signal(sig, handler)
        previous[sig] = old if old is not None else signal.SIG_DFL  # None: one set from C
    return previous


def _stopped(link: MotorLink) -> str:
    """STOP sent now, and what to tell the user: "chair stopped" only when the controller
    acknowledged it (a vanished port or a dead controller cannot)."""
    return "chair stopped" if link.stop() else STOP_UNCONFIRMED


def _describe(s: actions.Step) -> str:
    return (
        f"{s.src} -> {s.dst} heading {s.heading} move {s.move} => "
        f"{actions.PAPER_NAME[s.action]} (new heading {s.new_heading})"
    )


def _number(v: Any) -> TypeGuard[int | float]:
    """A finite JSON number (true and false are Python ints: ``"rows": true`` was a count)."""
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _count(v: Any) -> TypeGuard[int]:
    return isinstance(v, int) and not isinstance(v, bool)


def grid_of_plan(planned: Any) -> Any:
    """The geometry of the grid a plan was made on (``wheelgrid plan --json``'s ``grid``), its
    cells unknown: where the plan's cells lie, for the pose checks without ``--grid``. None
    where the plan does not say (a plan of another tool, or from before plans said it)."""
    from wheelgrid_common.map_io import UNKNOWN, Grid

    if not isinstance(planned, dict):
        return None
    rows, cols = planned.get("rows"), planned.get("cols")
    res, origin = planned.get("resolution"), planned.get("origin")
    if not isinstance(origin, list) or len(origin) != 3:
        return None
    if not (
        _count(rows)
        and _count(cols)
        and 0 < rows * cols <= 10**7  # a made-up count must not take the memory
        and rows > 0
        and _number(res)
        and res > 0
        and all(_number(v) for v in origin)
    ):
        return None
    return Grid(np.full((rows, cols), UNKNOWN, dtype=np.int8), float(res), tuple(origin))


if __name__ == "__main__":
    sys.exit(main())
