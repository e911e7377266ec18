"""Grid moves + the chair's heading -> the chair's real actions (the paper's Table II).

The planner thinks in grid moves (up/down/left/right), but an electric wheelchair is not
omnidirectional: it can drive forward, back up, or turn a quarter to its own left or right while
moving forward. The drive package owns the authoritative conversion; the chain packages never
import each other, so the same rule lives here too (tested against Table II), letting the planner
print the actions it implies and cost its heading-aware routes the way the chair drives them.

Headings are grid directions in the image: up = row - 1, down = row + 1, left = col - 1,
right = col + 1. Facing "down", the chair's own left is "right" on the grid.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

MOVES: tuple[str, ...] = ("up", "down", "left", "right")
DELTAS: dict[str, tuple[int, int]] = {
    "up": (-1, 0),
    "down": (1, 0),
    "left": (0, -1),
    "right": (0, 1),
}
OPPOSITE: dict[str, str] = {"up": "down", "down": "up", "left": "right", "right": "left"}
# The grid direction on the chair's own left / right when it faces the key direction
# (turning counter-clockwise / clockwise as seen on the image).
LEFT_OF: dict[str, str] = {"up": "left", "left": "down", "down": "right", "right": "up"}
RIGHT_OF: dict[str, str] = {v: k for k, v in LEFT_OF.items()}

FORWARD, BACKWARD, LEFT_FORWARD, RIGHT_FORWARD = (
    "forward",
    "backward",
    "left-forward",
    "right-forward",
)


def convert(move: str, heading: str) -> tuple[str, str]:
    """(action, new heading) for one grid ``move`` made while facing ``heading``.

    Backing up keeps the heading: the chair reverses into the cell behind it without turning.
    """
    if move not in DELTAS or heading not in DELTAS:
        raise ValueError(f"unknown move/heading {move!r}/{heading!r} (use {', '.join(MOVES)})")
    if move == heading:
        return FORWARD, heading
    if move == OPPOSITE[heading]:
        return BACKWARD, heading
    if move == LEFT_OF[heading]:
        return LEFT_FORWARD, move
    return RIGHT_FORWARD, move


def move_between(a: Sequence[int], b: Sequence[int]) -> str:
    """The grid move from cell ``a`` to the 4-neighbour ``b``; ValueError if not adjacent."""
    d = (int(b[0]) - int(a[0]), int(b[1]) - int(a[1]))
    for name, delta in DELTAS.items():
        if delta == d:
            return name
    raise ValueError(f"cells {tuple(a)} and {tuple(b)} are not 4-neighbours")


def cells_to_moves(cells: Sequence[Sequence[int]]) -> list[str]:
    """Grid moves along a 4-connected cell path."""
    return [move_between(cells[i], cells[i + 1]) for i in range(len(cells) - 1)]


def moves_to_actions(cells: Sequence[Sequence[int]], heading: str) -> list[dict[str, Any]]:
    """Table II rows for a cell path driven from ``heading``.

    Each row: ``from``/``to`` cells, ``heading`` before the move, the grid ``move``,
    ``new_heading`` and the chair ``action``.
    """
    rows = []
    d = heading
    for i in range(len(cells) - 1):
        move = move_between(cells[i], cells[i + 1])
        action, d_new = convert(move, d)
        rows.append(
            {
                "from": [int(cells[i][0]), int(cells[i][1])],
                "to": [int(cells[i + 1][0]), int(cells[i + 1][1])],
                "heading": d,
                "move": move,
                "new_heading": d_new,
                "action": action,
            }
        )
        d = d_new
    return rows
