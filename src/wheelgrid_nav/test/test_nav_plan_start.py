"""The chair's own cell: unknown is allowed (the sensor on the chair never sees under it),
occupied never is, and no other unknown cell becomes usable."""

import numpy as np
import pytest

from wheelgrid_nav.planner import PlanInputError, PlannerConfig, plan


def _grid():
    g = np.zeros((3, 4), dtype=np.int8)
    g[1, 1] = -1
    return g


def test_unknown_start_cell_is_allowed_by_default():
    g = _grid()
    g[0, 0] = -1
    res = plan(g, (0, 0), (2, 3))
    assert res.ok and res.cells[0] == (0, 0) and (1, 1) not in res.cells
    assert len(res.cells) - 1 == 5


def test_unknown_start_can_be_refused_and_occupied_start_always_is():
    g = _grid()
    g[0, 0] = -1
    with pytest.raises(PlanInputError, match="not free"):
        plan(g, (0, 0), (2, 3), PlannerConfig(allow_unknown_start=False))
    g[0, 0] = 100
    with pytest.raises(PlanInputError, match="not free"):
        plan(g, (0, 0), (2, 3))


def test_unknown_goal_is_still_refused():
    with pytest.raises(PlanInputError, match="not free"):
        plan(_grid(), (0, 0), (1, 1))


def test_unknown_start_does_not_make_the_same_cell_an_acceptable_goal():
    """The start relaxation is for the chair's own cell only: asked to "plan" from an unknown
    cell to itself, the planner must refuse the goal, not report a converged empty route."""
    g = np.zeros((8, 8), dtype=np.int8)
    g[7, 7] = -1
    with pytest.raises(PlanInputError, match=r"goal cell \(7,7\) is not free"):
        plan(g, (7, 7), (7, 7))
    g[7, 7] = 100
    with pytest.raises(PlanInputError, match="not free"):
        plan(g, (7, 7), (7, 7))
    # a known free start may still be its own goal (a zero-move route)
    assert plan(g, (0, 0), (0, 0)).cells == [(0, 0)]


def test_a_heading_route_never_comes_back_into_an_unknown_start_cell():
    """A three-point turn through the chair's own cell re-enters it, and the drive enters only
    cells known to be free: from an unknown start the route may only leave it."""
    g = np.full((3, 10), 100, dtype=np.int8)
    g[1, :] = 0
    g[0, 8] = 0  # a pocket beside the start: the turn would come back into (1, 8)
    g[1, 8] = -1
    res = plan(g, (1, 8), (1, 0), method="qlearning-heading", heading="right")
    assert res.ok, res.reason
    assert res.cells == [(1, c) for c in range(8, -1, -1)]  # backs up the corridor instead
    assert res.cost == pytest.approx(16.0) == res.optimal_cost
