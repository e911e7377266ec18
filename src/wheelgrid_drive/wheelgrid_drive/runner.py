"""Executing a converted plan step by step over a :class:`~wheelgrid_drive.link.MotorLink`.

Shared by ``wheelgrid drive`` and the drive node, so both apply the same rules before every
single command: the abort flag (e-stop, new plan) is checked, the next cell must be known to be
free, and any failure ends the run with STOP. ROS-free.
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from wheelgrid_common.map_io import same_geometry as same_geometry
from wheelgrid_drive import protocol as proto
from wheelgrid_drive.actions import Step, moves_from_cells
from wheelgrid_drive.link import LinkAbortedError, LinkError, MotorLink

# (step, record) -> None; record is the drive_commands JSON object.
StepCallback = Callable[[Step, dict[str, Any]], None]
# cell -> None if the chair may enter it, else the reason it may not.
CellCheck = Callable[[tuple[int, int]], str | None]
# step -> (how far to drive it, None), or (0, why the chair cannot drive it from where it is).
StepLength = Callable[[Step], tuple[float, str | None]]

# the turn each action makes before it drives, and the direction it drives in
_TURN = {
    "FORWARD": 0.0,
    "BACKWARD": 0.0,
    "LEFT_FORWARD": math.pi / 2,
    "RIGHT_FORWARD": -math.pi / 2,
}
_SIGN = {"FORWARD": 1.0, "BACKWARD": -1.0, "LEFT_FORWARD": 1.0, "RIGHT_FORWARD": 1.0}


@dataclass
class RunResult:
    ok: bool
    done: int  # steps completed
    total: int
    error: str = ""
    refused: bool = False  # True when a cell check (not the link) ended the run
    aborted: bool = False


def grid_cell_check(grid_getter: Callable[[], Any]) -> CellCheck:
    """A cell check against the latest safe grid: only cells that are exactly FREE (0) pass.

    Unknown (-1), occupied (100), any intermediate cost, outside the grid, or no grid at all
    is a refusal: the chair never moves into a cell not known to be free.
    """

    def check(cell: tuple[int, int]) -> str | None:
        grid = grid_getter()
        if grid is None:
            return "no safe grid received"
        r, c = cell
        if not grid.inside(r, c):
            return f"cell {cell} is outside the safe grid ({grid.rows}x{grid.cols})"
        value = int(np.asarray(grid.data)[r, c])
        if value != 0:
            what = {100: "occupied", -1: "unknown"}.get(value, f"not free (value {value})")
            return f"cell {cell} is {what}"
        return None

    return check


def planned_grid_check(grid_getter: Callable[[], Any], planned_on: Any) -> CellCheck:
    """:func:`grid_cell_check` against the latest grid, refusing every cell once that grid no
    longer has the geometry of ``planned_on``: checked by index on a grid shifted by a cell,
    a plan's next cell is another place, and a chair was sent into an occupied one."""
    latest = grid_cell_check(grid_getter)

    def check(cell: tuple[int, int]) -> str | None:
        grid = grid_getter()
        if grid is not None and not same_geometry(grid, planned_on):
            return "the safe grid's size, resolution, origin or frame changed since planning"
        return latest(cell)

    return check


def _line_to_centre(
    grid: Any, x: float, y: float, yaw: float, step: Step
) -> tuple[float, float, float]:
    """(along, across, cell) of the next cell's centre seen from a chair at controller pose
    (``x``, ``y``, ``yaw``) about to drive ``step`` as the controller drives it (a quarter turn
    for left/right-forward, then straight along its own yaw): how far ahead along that line,
    how far off it, and the cell's size."""
    res = float(grid.resolution)
    heading = yaw + _TURN[step.action]
    ux, uy = _SIGN[step.action] * math.cos(heading), _SIGN[step.action] * math.sin(heading)
    cx, cy = (float(v) for v in grid.cell_center(*step.dst))
    return (cx - x) * ux + (cy - y) * uy, abs((cy - y) * ux - (cx - x) * uy), res


# How step_from_pose's three refusals read: the chair not in the step's first cell, a chair
# whose body would sweep the cells beside its way (off its cell's centre), and a move that
# would pass off the next cell's centre (a heading off); `wheelgrid drive` gives each its own
# advice (and none to a refusal of another kind, such as no pose from the controller).
OFF_CELL = "the chair at"
OFF_SIDE = "its body would sweep the cells beside its way"
OFF_LINE = "off its line"


def off_centre_problem(
    grid: Any, x: float, y: float, cell: tuple[int, int], tolerance: float = 0.25
) -> str | None:
    """Why a chair at (``x``, ``y``) does not stand in ``cell`` (more than ``tolerance`` cells
    from its centre), or None: after a plan's last step (a move reported done short of its
    cell)."""
    res = float(grid.resolution)
    cx, cy = (float(v) for v in grid.cell_center(*cell))
    off = math.hypot(x - cx, y - cy)
    if off > tolerance * res:
        return (
            f"{OFF_CELL} ({x:.2f}, {y:.2f}) is {off:.2f} m from the centre of cell "
            f"{tuple(cell)}, more than {tolerance:g} cell"
        )
    return None


def _start_problem(grid: Any, x: float, y: float, step: Step, tolerance: float) -> str | None:
    """Why a chair at (``x``, ``y``) is too far off its cell's centre to start ``step``
    (see :func:`step_to_centre`), or None."""
    res = float(grid.resolution)
    sx, sy = (float(v) for v in grid.cell_center(*step.src))
    dx, dy = (float(v) for v in grid.cell_center(*step.dst))
    if _TURN[step.action]:
        off = math.hypot(x - sx, y - sy)
        where = f"{off:.2f} m from the centre of cell {tuple(step.src)}"
    else:
        n = math.hypot(dx - sx, dy - sy)
        off = abs((x - sx) * (dy - sy) - (y - sy) * (dx - sx)) / n
        where = f"{off:.2f} m beside the line through the centres of its cells"
    if off <= tolerance * res:
        return None
    how = "turns in place" if _TURN[step.action] else "drives straight"
    return (
        f"{step.action} {how}, and from ({x:.2f}, {y:.2f}), {where} (more than {tolerance:g} "
        f"cell), {OFF_SIDE}"
    )


def step_to_centre(
    grid: Any, x: float, y: float, yaw: float, step: Step, tolerance: float = 0.25
) -> tuple[float, str | None]:
    """(distance, None) that takes a chair at controller pose (``x``, ``y``, ``yaw``) anywhere
    in ``step``'s first cell to the next cell's centre, as the controller drives (a quarter
    turn for left/right-forward, then straight along its own yaw); or (0, why not).

    A /cmd_vel step drove one cell's length from wherever the chair stood: from the far side
    of its cell, or after a stop mid-cell, that ended beyond the one cell checked free. Both
    ends lie in the two cells, whose union is a rectangle, so the path between stays in them.
    The move must pass within ``tolerance`` cells of the centre (the heading's error).

    That rectangle holds the chair's reference point, not its body, which is about a cell
    wide: a straight move starts within ``tolerance`` cells of the line through the two
    centres (anywhere along it: a chair stopped mid-move goes on), and a turn, made in place,
    within ``tolerance`` cells of its cell's centre. From the edge of its cell a turn swung
    the body 0.6 m into an occupied neighbour, and a straight move 0.57 m (a review)."""
    if problem := _start_problem(grid, x, y, step, tolerance):
        return 0.0, problem
    along, miss, res = _line_to_centre(grid, x, y, yaw, step)
    if miss > tolerance * res or not 0.25 * res <= along <= 1.5 * res:
        return 0.0, (
            f"{step.action} from ({x:.2f}, {y:.2f}) facing {math.degrees(yaw):.0f} deg passes "
            f"{miss:.2f} m from the centre of cell {step.dst} ({along:.2f} m ahead): more than "
            f"{tolerance:g} cell {OFF_LINE}"
        )
    # up to 1.5 cells: over 2 m on cells over 1.33 m, which one move cannot drive
    if problem := proto.move_length_problem(along, f"the way to cell {step.dst}'s centre"):
        return 0.0, problem
    return along, None


def step_from_pose(
    grid: Any, x: float, y: float, yaw: float, step: Step, tolerance: float = 0.25
) -> tuple[float, str | None]:
    """(distance, None) that takes a chair at controller pose (``x``, ``y``, ``yaw``) standing
    in ``step``'s first cell to the next cell's centre (:func:`step_to_centre`), or (0, why
    not): every step of a plan, from where the controller says the chair is.

    Each step drove one cell's length from wherever the chair stood, checked to start within a
    quarter cell of its cell's centre: per-move errors added up until a route stopped half-way
    (8 cm a move), a chair 0.29 m ahead of its cell ended 0.29 m past the next, and a chair
    stopped mid-move (a new route, a closed cell) was more than a quarter cell from every
    centre, so no route from there could ever be driven (a review)."""
    here = tuple(int(v) for v in grid.cell_of(x, y))
    if here != tuple(step.src):
        return 0.0, f"{OFF_CELL} ({x:.2f}, {y:.2f}) is in cell {here}, not in cell {step.src}"
    return step_to_centre(grid, x, y, yaw, step, tolerance)


def controller_step_length(
    link: MotorLink, grid: Any, tolerance: float = 0.25
) -> Callable[[Step], tuple[float, str | None]]:
    """Before each step, the controller's pose now and :func:`step_from_pose` from it: the
    drive node's and ``wheelgrid drive``'s step length. ``grid`` needs ``resolution``,
    ``cell_center`` and ``cell_of`` only."""

    def length(step: Step) -> tuple[float, str | None]:
        try:
            st = link.status()
        except LinkError as exc:
            return 0.0, f"no controller pose: {exc}"
        return step_from_pose(grid, st.x, st.y, st.yaw, step, tolerance)

    return length


def command_record(step: Step, ack: str, t: float | None = None, **extra: Any) -> dict[str, Any]:
    """The JSON object published per executed command (drive_commands / CLI output)."""
    rec: dict[str, Any] = step.to_json()
    rec["ack"] = ack
    rec["t"] = time.time() if t is None else t
    rec.update(extra)
    return rec


def run_steps(
    link: MotorLink,
    steps: Sequence[Step],
    *,
    distance_m: float,
    speed_kmh: float,
    cell_check: CellCheck | None = None,
    abort: threading.Event | None = None,
    on_step: StepCallback | None = None,
    timeout: float | None = None,
    on_start: Callable[[Step], None] | None = None,
    step_length: StepLength | None = None,
    connection: int | None = None,
) -> RunResult:
    """Drive ``steps`` one by one; stops the chair and returns at the first problem.

    ``on_start(step)`` is called before the step's checks and its command, so an observer (the
    node) knows which cell the chair is about to enter and can abort if it changes. Before, not
    after the checks: a grid that came between the check and ``on_start`` was compared with the
    previous step's cell by the node, and the chair was sent into a cell that grid had occupied.
    With the cell announced first, either the check reads the new grid or the node's grid
    callback sees the announced cell (and aborts). ``step_length(step)``, after the cell check,
    gives how far to drive the step from where the chair stands, or refuses it (see
    :func:`step_from_pose`); without it every step drives ``distance_m``.

    A link lost at any time during the run ends it, even when the port is back before the next
    step: the reconnection's STOP is where the chair stays, and the next step's MOVE, sent on
    the reopened port, drove on after a link fault with no new command. ``connection``: the
    link's connection count when the caller first asked the controller (its status, the start
    checks), so that a loss and reopen between those questions and the run ends it too; by
    default the count as the run starts.
    """
    total = len(steps)
    if connection is None:
        connection = link.connection
    for i, step in enumerate(steps):
        if abort is not None and abort.is_set():
            link.stop()
            return RunResult(False, i, total, "aborted before the next command", aborted=True)
        if on_start is not None:
            on_start(step)
        reason = cell_check(step.dst) if cell_check is not None else None
        distance = distance_m
        if not reason and step_length is not None:
            distance, reason = step_length(step)
        if reason:
            link.stop()
            if on_step is not None:
                on_step(step, command_record(step, "REFUSED", reason=reason))
            return RunResult(False, i, total, f"refused: {reason}", refused=True)
        if link.connection != connection:
            link.stop()
            why = "the link to the controller was lost during the plan: not resumed"
            if on_step is not None:
                on_step(step, command_record(step, "FAILED", reason=why))
            return RunResult(False, i, total, why)
        try:
            # the count goes with the move: a port lost and reopened after the check above
            # (the thread descheduled there) took the move on the reopened port
            seq, st = link.execute(step.action, distance, speed_kmh, timeout, abort, connection)
        except LinkAbortedError as exc:
            if on_step is not None:
                on_step(step, command_record(step, "ABORTED", reason=str(exc), **_seq(exc)))
            return RunResult(False, i, total, str(exc), aborted=True)
        except LinkError as exc:
            link.stop()  # already sent by the link; again, cheap, in case it was lost
            if on_step is not None:
                on_step(step, command_record(step, "FAILED", reason=str(exc), **_seq(exc)))
            return RunResult(False, i, total, str(exc))
        if on_step is not None:
            on_step(
                step,
                command_record(step, "ACK", seq=seq, pose=[round(st.x, 3), round(st.y, 3)]),
            )
    return RunResult(True, total, total)


def _seq(exc: LinkError) -> dict[str, int]:
    """``seq`` of the move the controller acknowledged before ``exc``: the chair moved."""
    return {} if exc.seq is None else {"seq": exc.seq}


def dumps_record(rec: dict[str, Any]) -> str:
    return json.dumps(rec, separators=(",", ":"))


def cells_from_points(
    grid: Any, points: Sequence[Sequence[float]], tolerance: float = 0.25
) -> list[tuple[int, int]]:
    """Grid cells of a path through cell centres (map-frame x, y), validated.

    Each point must lie within ``tolerance`` cells of its cell's centre (a path that does not
    go through centres was planned on another grid: a doubt), inside the grid, and consecutive
    cells must be 4-neighbours. Repeated cells are collapsed. ValueError otherwise.
    """
    cells: list[tuple[int, int]] = []
    for i, p in enumerate(points):
        x, y = float(p[0]), float(p[1])
        r, c = grid.cell_of(x, y)
        if not grid.inside(r, c):
            raise ValueError(f"path point {i} ({x:.2f}, {y:.2f}) is outside the safe grid")
        cx, cy = grid.cell_center(r, c)
        off = float(np.hypot(x - cx, y - cy))
        if off > tolerance * grid.resolution:
            raise ValueError(
                f"path point {i} ({x:.2f}, {y:.2f}) is {off:.2f} m from the centre of cell "
                f"{(r, c)}: the plan was not made on this grid"
            )
        if not cells or cells[-1] != (r, c):
            cells.append((r, c))
    moves_from_cells(cells)  # raises on a diagonal or a jump
    return cells
