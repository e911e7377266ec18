"""The paper's Table II: grid moves + the chair's heading -> the chair's actual actions.

The Q-learning planner thinks in grid moves (up/down/left/right), but an electric wheelchair is
not omnidirectional: it can only drive forward or backward along its heading, or turn in place.
So each move is converted, given the chair's current heading ``d``, into an actual action
``a_xt`` and a new heading ``d'``:

* move == heading             -> FORWARD        (heading kept)
* move == heading turned left  -> LEFT_FORWARD   (turn 90 deg to the chair's left, then forward)
* move == heading turned right -> RIGHT_FORWARD  (turn 90 deg to the chair's right, then forward)
* move == opposite of heading  -> BACKWARD       (heading kept: reversing one cell is safer and
  shorter than a 180 deg turn in place; the paper lists "backward" among the chair's actions
  but no Table II row uses it, so the kept heading is this project's choice)

Grid directions are IMAGE directions (see docs/CONVENTIONS.md): up = row - 1, down = row + 1,
left = col - 1, right = col + 1. Seen from above with row 0 at the top, a chair facing "down"
has its own left on grid "right" -- exactly Table II's first row (Down + Right -> Left-Forward).

ROS-free on purpose: the CLI, the drive node and the tests all share this one rule.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass

HEADINGS: tuple[str, ...] = ("up", "right", "down", "left")  # clockwise seen from above
ACTIONS: tuple[str, ...] = ("FORWARD", "BACKWARD", "LEFT_FORWARD", "RIGHT_FORWARD")

# (d_row, d_col) of one move in image orientation.
DELTA: dict[str, tuple[int, int]] = {
    "up": (-1, 0),
    "down": (1, 0),
    "left": (0, -1),
    "right": (0, 1),
}

# Map-frame yaw of each grid direction for a grid with origin yaw 0 (x = col, y = up the image).
YAW: dict[str, float] = {"right": 0.0, "up": math.pi / 2, "left": math.pi, "down": -math.pi / 2}

# The paper's spelling of each action (Table II), for printing.
PAPER_NAME: dict[str, str] = {
    "FORWARD": "Forward",
    "BACKWARD": "Backward",
    "LEFT_FORWARD": "Left-Forward",
    "RIGHT_FORWARD": "Right-Forward",
}


def _check_direction(name: str, what: str) -> str:
    value = str(name).strip().lower()
    if value not in DELTA:
        raise ValueError(f"{what} must be one of up/down/left/right, got {name!r}")
    return value


def turn_left(heading: str) -> str:
    """The grid direction on the chair's left when it faces ``heading`` (counter-clockwise)."""
    h = _check_direction(heading, "heading")
    return HEADINGS[(HEADINGS.index(h) - 1) % 4]


def turn_right(heading: str) -> str:
    """The grid direction on the chair's right when it faces ``heading`` (clockwise)."""
    h = _check_direction(heading, "heading")
    return HEADINGS[(HEADINGS.index(h) + 1) % 4]


def opposite(heading: str) -> str:
    h = _check_direction(heading, "heading")
    return HEADINGS[(HEADINGS.index(h) + 2) % 4]


def convert(move: str, heading: str) -> tuple[str, str]:
    """Table II for one step: ``(action, new_heading)`` for grid ``move`` at ``heading``."""
    m = _check_direction(move, "move")
    h = _check_direction(heading, "heading")
    if m == h:
        return "FORWARD", h
    if m == turn_left(h):
        return "LEFT_FORWARD", m
    if m == turn_right(h):
        return "RIGHT_FORWARD", m
    return "BACKWARD", h  # m is the opposite direction: reverse, keep facing the same way


@dataclass(frozen=True)
class Step:
    """One row of Table II: the cells, the headings before/after, the move and the action."""

    src: tuple[int, int]
    dst: tuple[int, int]
    heading: str
    move: str
    new_heading: str
    action: str

    def to_json(self) -> dict[str, object]:
        """The plan-JSON / drive_commands spelling (``from``/``to`` are Python keywords here)."""
        d = asdict(self)
        return {
            "from": list(d["src"]),
            "to": list(d["dst"]),
            "heading": self.heading,
            "move": self.move,
            "new_heading": self.new_heading,
            "action": self.action,
        }


def move_between(a: Sequence[int], b: Sequence[int]) -> str:
    """The grid move from cell ``a`` to 4-neighbour ``b``; ValueError for anything else."""
    dr, dc = int(b[0]) - int(a[0]), int(b[1]) - int(a[1])
    for name, delta in DELTA.items():
        if (dr, dc) == delta:
            return name
    raise ValueError(
        f"cells {tuple(a)} -> {tuple(b)} are not 4-neighbours (a chair moves one cell at a time)"
    )


def moves_from_cells(cells: Sequence[Sequence[int]]) -> list[str]:
    """The moves along a cell path; every consecutive pair must be 4-neighbours."""
    return [move_between(cells[i], cells[i + 1]) for i in range(len(cells) - 1)]


def plan_steps(start: Sequence[int], moves: Sequence[str], heading: str) -> list[Step]:
    """Convert a whole move sequence from ``start`` at ``heading`` into Table II rows."""
    cell = (int(start[0]), int(start[1]))
    h = _check_direction(heading, "start heading")
    steps: list[Step] = []
    for raw in moves:
        m = _check_direction(raw, "move")
        action, new_h = convert(m, h)
        dr, dc = DELTA[m]
        nxt = (cell[0] + dr, cell[1] + dc)
        steps.append(Step(cell, nxt, h, m, new_h, action))
        cell, h = nxt, new_h
    return steps


def heading_from_yaw(yaw: float, grid_yaw: float = 0.0, tolerance: float = math.radians(20)) -> str:
    """The grid direction nearest a map-frame yaw; ValueError if it is not near any axis.

    A pose that is not clearly aligned with a grid axis is a doubt, and a doubt must not turn
    into a guessed heading (a wrong heading turns every LEFT into a RIGHT).
    """
    rel = yaw - grid_yaw
    for name, ref in YAW.items():
        diff = math.atan2(math.sin(rel - ref), math.cos(rel - ref))
        if abs(diff) <= tolerance:
            return name
    raise ValueError(
        f"yaw {math.degrees(yaw):.1f} deg is not within {math.degrees(tolerance):.0f} deg "
        "of a grid direction"
    )
