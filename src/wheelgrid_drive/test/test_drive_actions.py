"""Table II of the paper, row by row, and the conversion rule it follows."""

import math

import pytest

from wheelgrid_drive.actions import (
    DELTA,
    YAW,
    convert,
    heading_from_yaw,
    move_between,
    moves_from_cells,
    opposite,
    plan_steps,
    turn_left,
    turn_right,
)

# (from, to, current direction d, predicted action a, new direction d', actual action)
TABLE_II = [
    ((2, 0), (2, 1), "down", "right", "right", "LEFT_FORWARD"),
    ((2, 1), (2, 2), "right", "right", "right", "FORWARD"),
    ((2, 2), (2, 3), "right", "right", "right", "FORWARD"),
    ((2, 3), (2, 4), "right", "right", "right", "FORWARD"),
    ((2, 4), (2, 5), "right", "right", "right", "FORWARD"),
    ((2, 5), (3, 5), "right", "down", "down", "RIGHT_FORWARD"),
    ((3, 5), (4, 5), "down", "down", "down", "FORWARD"),
    ((4, 5), (5, 5), "down", "down", "down", "FORWARD"),
    ((5, 5), (6, 5), "down", "down", "down", "FORWARD"),
]


def test_table_ii_row_by_row():
    steps = plan_steps((2, 0), ["right"] * 5 + ["down"] * 4, "down")
    assert len(steps) == len(TABLE_II)
    for step, (src, dst, d, a, d_new, act) in zip(steps, TABLE_II, strict=True):
        assert (step.src, step.dst, step.heading, step.move, step.new_heading, step.action) == (
            src,
            dst,
            d,
            a,
            d_new,
            act,
        )


def test_table_ii_from_cells_gives_the_same_moves():
    cells = [TABLE_II[0][0]] + [row[1] for row in TABLE_II]
    assert moves_from_cells(cells) == [row[3] for row in TABLE_II]


def test_facing_down_the_chairs_left_is_grid_right():
    # Seen from above with row 0 at the top: facing down the page, the chair's left hand is
    # on the right of the page.
    assert turn_left("down") == "right"
    assert turn_right("down") == "left"
    assert turn_left("up") == "left"
    assert turn_right("right") == "down"


@pytest.mark.parametrize("heading", list(DELTA))
def test_every_move_from_every_heading(heading):
    assert convert(heading, heading) == ("FORWARD", heading)
    assert convert(turn_left(heading), heading) == ("LEFT_FORWARD", turn_left(heading))
    assert convert(turn_right(heading), heading) == ("RIGHT_FORWARD", turn_right(heading))
    # Backward keeps the heading: the chair reverses one cell instead of turning around.
    assert convert(opposite(heading), heading) == ("BACKWARD", heading)


def test_left_and_right_turns_match_map_yaw():
    # Turning left (counter-clockwise) adds +90 deg of yaw in the map frame (z up).
    for h in DELTA:
        diff = YAW[turn_left(h)] - YAW[h]
        assert math.isclose(math.cos(diff), 0.0, abs_tol=1e-12)
        assert math.isclose(math.sin(diff), 1.0)


def test_backward_step_moves_against_heading():
    (step,) = plan_steps((4, 4), ["up"], "down")
    assert step.action == "BACKWARD" and step.dst == (3, 4) and step.new_heading == "down"


def test_non_neighbour_cells_and_bad_names_are_refused():
    with pytest.raises(ValueError, match="4-neighbours"):
        move_between((2, 2), (3, 3))
    with pytest.raises(ValueError, match="4-neighbours"):
        moves_from_cells([(0, 0), (0, 1), (0, 1)])
    with pytest.raises(ValueError):
        convert("north", "up")
    with pytest.raises(ValueError):
        plan_steps((0, 0), ["up"], "sideways")


def test_heading_from_yaw_refuses_an_ambiguous_pose():
    assert heading_from_yaw(0.05) == "right"
    assert heading_from_yaw(-math.pi / 2) == "down"
    assert heading_from_yaw(math.pi - 0.01) == "left"
    assert heading_from_yaw(math.pi / 2 + 0.3, grid_yaw=0.3) == "up"
    with pytest.raises(ValueError):
        heading_from_yaw(math.pi / 4)


def test_step_json_uses_plan_spelling():
    (step,) = plan_steps((2, 0), ["right"], "down")
    assert step.to_json() == {
        "from": [2, 0],
        "to": [2, 1],
        "heading": "down",
        "move": "right",
        "new_heading": "right",
        "action": "LEFT_FORWARD",
    }
