"""Grid moves + heading -> chair actions, checked against the paper's Table II."""

import pytest

from wheelgrid_nav.actions import (
    BACKWARD,
    FORWARD,
    LEFT_FORWARD,
    RIGHT_FORWARD,
    cells_to_moves,
    convert,
    move_between,
    moves_to_actions,
)

# The paper's Table II: state, current direction d, predicted action a, new direction d', action
TABLE_II = [
    ((2, 0), (2, 1), "down", "right", "right", "left-forward"),
    ((2, 1), (2, 2), "right", "right", "right", "forward"),
    ((2, 2), (2, 3), "right", "right", "right", "forward"),
    ((2, 3), (2, 4), "right", "right", "right", "forward"),
    ((2, 4), (2, 5), "right", "right", "right", "forward"),
    ((2, 5), (3, 5), "right", "down", "down", "right-forward"),
    ((3, 5), (4, 5), "down", "down", "down", "forward"),
    ((4, 5), (5, 5), "down", "down", "down", "forward"),
    ((5, 5), (6, 5), "down", "down", "down", "forward"),
]


def test_table_ii_reproduced_row_by_row():
    cells = [(2, 0)] + [(2, c) for c in range(1, 6)] + [(r, 5) for r in range(3, 7)]
    moves = cells_to_moves(cells)
    assert moves == ["right"] * 5 + ["down"] * 4
    rows = moves_to_actions(cells, "down")
    assert len(rows) == len(TABLE_II)
    for row, (a, b, d, move, d_new, action) in zip(rows, TABLE_II, strict=True):
        assert row == {
            "from": list(a),
            "to": list(b),
            "heading": d,
            "move": move,
            "new_heading": d_new,
            "action": action,
        }


@pytest.mark.parametrize(
    ("move", "heading", "action", "new_heading"),
    [
        # facing down (row + 1) the chair's own left is grid "right" (col + 1)
        ("right", "down", LEFT_FORWARD, "right"),
        ("left", "down", RIGHT_FORWARD, "left"),
        ("down", "down", FORWARD, "down"),
        ("up", "down", BACKWARD, "down"),
        # facing up the chair's left is grid "left"
        ("left", "up", LEFT_FORWARD, "left"),
        ("right", "up", RIGHT_FORWARD, "right"),
        # facing right (col + 1) its left is "up" (row - 1)
        ("up", "right", LEFT_FORWARD, "up"),
        ("down", "right", RIGHT_FORWARD, "down"),
        ("left", "right", BACKWARD, "right"),
        ("down", "left", LEFT_FORWARD, "down"),
        ("up", "left", RIGHT_FORWARD, "up"),
    ],
)
def test_convert_each_manoeuvre(move, heading, action, new_heading):
    assert convert(move, heading) == (action, new_heading)


def test_left_then_right_quarter_turns_cancel():
    # four left turns bring the chair back to its original heading
    d = "down"
    for _ in range(4):
        from wheelgrid_nav.actions import LEFT_OF

        action, d = convert(LEFT_OF[d], d)
        assert action == LEFT_FORWARD
    assert d == "down"


def test_bad_inputs_are_rejected():
    with pytest.raises(ValueError):
        convert("north", "down")
    with pytest.raises(ValueError):
        move_between((0, 0), (1, 1))
