"""The Q-learning planner core on hand-made grids: optimal, verified, deterministic, safe."""

import math

import numpy as np
import pytest

from wheelgrid_nav.actions import moves_to_actions
from wheelgrid_nav.grid_synth import maze
from wheelgrid_nav.planner import (
    PlanInputError,
    PlannerConfig,
    _build_mdp,
    _optimal_cost,
    astar,
    bfs_distances,
    check_config,
    plan,
    verify_route,
)
from wheelgrid_nav.planner_node import forward_yaw, heading_from_yaw, path_poses

PAPER_OCCUPIED = [(3, 0), (3, 1), (3, 2), (3, 3), (3, 4), (5, 0), (5, 1), (5, 2), (5, 3), (4, 4)]
PAPER_ROUTE = [(2, 0)] + [(2, c) for c in range(1, 6)] + [(r, 5) for r in range(3, 7)]


def paper_grid() -> np.ndarray:
    g = np.zeros((8, 8), dtype=np.int8)
    for r, c in [*PAPER_OCCUPIED, (6, 7)]:  # (6, 7): a pillar off the route
        g[r, c] = 100
    return g


def random_grid(rng, rows, cols, p):
    return np.where(rng.random((rows, cols)) < p, 100, 0).astype(np.int8)


def test_the_time_budget_holds_from_the_start_of_planning():
    """max_seconds bounded the learning only: the search for the optimum before it (a
    pure-Python Dijkstra) took 11.6 s on a 600 x 600 grid, and the planner node was held that
    long (a review's find). The budget now starts with the planning, the plain planner takes
    its optimum from BFS (every move costs the same), and the search stops at the deadline."""
    rng = np.random.default_rng(8)
    cfg = PlannerConfig()
    for _ in range(20):
        grid = random_grid(rng, 12, 12, 0.25)
        free = grid == 0
        cells = np.argwhere(free)
        s, g = (tuple(int(v) for v in cells[i]) for i in rng.choice(len(cells), 2, replace=False))
        steps = int(bfs_distances(free, g)[s])
        if steps <= 0:
            continue
        mdp = _build_mdp(free, s, g, cfg, None)
        assert mdp is not None and _optimal_cost(mdp) == steps * -cfg.reward_step
    free = np.ones((70, 70), dtype=bool)  # 19,600 heading states: past the first time check
    mdp = _build_mdp(free, (0, 0), (69, 69), cfg, "right")
    assert _optimal_cost(mdp, deadline=0.0) is None
    res = plan(
        np.zeros((70, 70), dtype=np.int8), (0, 0), (69, 69), PlannerConfig(max_seconds=1e-9),
        method="qlearning-heading", heading="right",
    )  # fmt: skip
    assert not res.ok and res.reason == "not converged"


def test_paper_grid_unique_shortest_route():
    res = plan(paper_grid(), (2, 0), (6, 5))
    assert res.ok and res.converged and res.reason == "ok"
    assert res.cells == PAPER_ROUTE
    assert res.moves == ["right"] * 5 + ["down"] * 4
    assert res.bfs_length == 9 and res.cost == 9.0 and res.optimal_cost == 9.0
    assert res.episodes > 0 and res.updates > 0
    actions = [a["action"] for a in moves_to_actions(res.cells, "down")]
    assert actions == ["left-forward"] + ["forward"] * 4 + ["right-forward"] + ["forward"] * 3


def test_heading_variant_on_the_paper_grid_matches_table_ii():
    res = plan(paper_grid(), (2, 0), (6, 5), method="qlearning-heading", heading="down")
    assert res.ok
    assert res.cells == PAPER_ROUTE
    # 9 moves + two quarter turns at 0.5 extra each
    assert res.cost == pytest.approx(10.0) and res.optimal_cost == pytest.approx(10.0)


def test_same_seed_same_training_different_seed_same_route():
    g = paper_grid()
    a = plan(g, (0, 0), (7, 0), PlannerConfig(seed=3))
    b = plan(g, (0, 0), (7, 0), PlannerConfig(seed=3))
    c = plan(g, (0, 0), (7, 0), PlannerConfig(seed=4))
    assert a.ok and b.ok and c.ok
    assert (a.cells, a.episodes, a.steps, a.updates) == (b.cells, b.episodes, b.steps, b.updates)
    assert len(c.cells) == len(a.cells) == a.bfs_length + 1


def test_unknown_cells_are_never_free():
    g = np.zeros((3, 5), dtype=np.int8)
    g[1, 1:4] = -1  # an unknown strip in the middle: the short way is through it
    g[0, 2] = 100
    res = plan(g, (1, 0), (1, 4))
    assert res.ok
    assert all(g[r, c] == 0 for r, c in res.cells)
    assert len(res.cells) - 1 == 6  # around the bottom, not through the unknown cells
    with pytest.raises(PlanInputError, match="not free"):
        plan(g, (1, 2), (1, 4), PlannerConfig(allow_unknown_start=False))
    with pytest.raises(PlanInputError, match="not free"):
        plan(g, (1, 0), (0, 2))
    with pytest.raises(PlanInputError, match="outside"):
        plan(g, (1, 0), (3, 0))


def test_unreachable_goal_gives_no_route_without_training():
    g = np.zeros((5, 5), dtype=np.int8)
    g[:, 2] = 100  # a wall cuts the room in two
    res = plan(g, (0, 0), (4, 4))
    assert not res.ok and res.cells == [] and res.moves == []
    assert res.reason == "unreachable" and res.bfs_length == -1 and res.episodes == 0


def test_budget_exhausted_means_no_route():
    g = maze(21, np.random.default_rng(0))
    res = plan(g, (1, 1), (19, 19), PlannerConfig(max_episodes=1, check_every=1))
    assert not res.converged and not res.ok
    assert res.cells == [] and res.reason == "not converged"
    assert res.bfs_length > 0


def test_time_budget_bounds_training_whatever_check_every_is():
    """max_seconds is checked every step: with the largest check_every allowed (no
    convergence check for a million steps) training still stops at the time limit."""
    g = maze(21, np.random.default_rng(0))
    cfg = PlannerConfig(check_every=1_000_000, max_seconds=0.2)
    res = plan(g, (1, 1), (19, 19), cfg)
    assert not res.ok and res.reason == "not converged" and res.cells == []
    assert res.seconds < 2.0 and 0 < res.steps < 1_000_000


def test_random_grids_and_mazes_match_bfs_exactly():
    """~100 grids: every plan is exactly BFS-short, or there is no path and none is given."""
    rng = np.random.default_rng(42)
    found = unreachable = 0
    for i in range(100):
        if i % 10 == 9:
            n = int(rng.choice([9, 11, 15]))
            g = maze(n, rng)
        else:
            g = random_grid(
                rng, int(rng.integers(4, 16)), int(rng.integers(4, 16)), rng.random() * 0.45
            )
        free = np.argwhere(g == 0)
        if len(free) < 2:
            continue
        s, t = (tuple(int(v) for v in free[k]) for k in rng.choice(len(free), 2, replace=False))
        res = plan(g, s, t, PlannerConfig(seed=i))
        dist = bfs_distances(g == 0, t)[s]
        if dist < 0:
            assert res.cells == [] and res.reason == "unreachable"
            unreachable += 1
            continue
        assert res.ok, (i, res.reason)
        assert len(res.cells) - 1 == dist
        assert verify_route(g == 0, res.cells, s, t, int(dist)) == []
        assert len(astar(g == 0, s, t)) - 1 == dist
        found += 1
    assert found >= 60 and unreachable >= 3


def test_bfs_distances_match_a_cell_by_cell_search_everywhere():
    """The level-by-level search over flat indices (10x faster on a 700 x 700 grid, where the
    queue overran the planning budget) gives every cell's distance as the plain queue does:
    no move wraps from a row's end to the next row's start, on thin and wide grids."""
    from collections import deque

    def reference(free: np.ndarray, src: tuple[int, int]) -> np.ndarray:
        dist = np.full(free.shape, -1)
        dist[src] = 0
        queue = deque([src])
        while queue:
            r, c = queue.popleft()
            for rr, cc in ((r - 1, c), (r + 1, c), (r, c - 1), (r, c + 1)):
                inside = 0 <= rr < free.shape[0] and 0 <= cc < free.shape[1]
                if inside and free[rr, cc] and dist[rr, cc] < 0:
                    dist[rr, cc] = dist[r, c] + 1
                    queue.append((rr, cc))
        return dist

    rng = np.random.default_rng(5)
    for shape in [
        (1, 9),
        (9, 1),
        (2, 2),
        *((int(a), int(b)) for a, b in rng.integers(1, 30, (40, 2))),
    ]:
        free = rng.random(shape) > 0.3
        src = tuple(int(v) for v in rng.integers(0, shape))
        free[src] = True
        np.testing.assert_array_equal(bfs_distances(free, src), reference(free, src), str(shape))
    blocked = np.zeros((3, 3), bool)
    assert (bfs_distances(blocked, (1, 1)) == -1).all()  # a source not free reaches nothing


def test_heading_variant_prefers_fewer_manoeuvres():
    g = np.zeros((3, 3), dtype=np.int8)
    # facing right at (0,0) to (2,2): right, right, down, down needs one quarter turn; any
    # other 4-move route needs two or three.
    res = plan(g, (0, 0), (2, 2), method="qlearning-heading", heading="right")
    assert res.ok
    assert res.moves == ["right", "right", "down", "down"]
    actions = [a["action"] for a in moves_to_actions(res.cells, "right")]
    assert actions == ["forward", "forward", "right-forward", "forward"]
    # the plain planner only promises a shortest route
    plain = plan(g, (0, 0), (2, 2))
    assert plain.ok and len(plain.moves) == 4


def test_heading_variant_backs_up_a_dead_end_corridor():
    g = np.full((3, 6), 100, dtype=np.int8)
    g[1, :] = 0  # a one-cell-wide corridor: no room to turn
    res = plan(g, (1, 4), (1, 1), method="qlearning-heading", heading="right")
    assert res.ok and res.moves == ["left"] * 3
    assert {a["action"] for a in moves_to_actions(res.cells, "right")} == {"backward"}
    assert res.cost == pytest.approx(3 * 2.0)


def corridor_with_a_side_pocket() -> np.ndarray:
    """A one-cell-wide corridor (row 1) with a one-cell pocket above column 8."""
    g = np.full((3, 10), 100, dtype=np.int8)
    g[1, :] = 0
    g[0, 8] = 0
    return g


def test_heading_variant_turns_round_in_a_side_pocket():
    """Facing the corridor's end, the cheapest way back is a three-point turn: into the pocket,
    back out into the same cell, then forward (12 against 16 for backing up eight cells). The
    route enters (1, 8) twice, at two headings, and was refused as "visits a cell twice": the
    node's default method had no route to a goal the chair could reach."""
    res = plan(
        corridor_with_a_side_pocket(), (1, 8), (1, 0), method="qlearning-heading", heading="right"
    )
    assert res.ok, res.reason
    assert res.cells == [(1, 8), (0, 8), (1, 8)] + [(1, c) for c in range(7, -1, -1)]
    assert res.cost == pytest.approx(12.0) == res.optimal_cost
    actions = [a["action"] for a in moves_to_actions(res.cells, "right")]
    assert actions == ["left-forward", "backward", "left-forward"] + ["forward"] * 7
    # the plain planner still never comes back to a cell
    plain = plan(corridor_with_a_side_pocket(), (1, 8), (1, 0))
    assert plain.ok and len(set(plain.cells)) == len(plain.cells) == 9


def test_heading_variant_on_random_grids_hits_the_dijkstra_optimum():
    rng = np.random.default_rng(7)
    for i in range(15):
        g = random_grid(rng, 10, 10, 0.25)
        free = np.argwhere(g == 0)
        s, t = (tuple(int(v) for v in free[k]) for k in rng.choice(len(free), 2, replace=False))
        heading = ["up", "down", "left", "right"][i % 4]
        res = plan(g, s, t, PlannerConfig(seed=i), method="qlearning-heading", heading=heading)
        if res.reason == "unreachable":
            continue
        assert res.ok, res.reason
        assert res.cost == pytest.approx(res.optimal_cost)
        assert verify_route(g == 0, res.cells, s, t) == []
        assert len(res.moves) >= res.bfs_length


def test_verify_route_catches_every_kind_of_bad_route():
    free = paper_grid() == 0
    assert verify_route(free, PAPER_ROUTE, (2, 0), (6, 5), 9) == []
    assert verify_route(free, [], (2, 0), (6, 5)) == ["empty route"]
    through_wall = [(2, 0), (3, 0), (4, 0)]
    assert any("not free" in p for p in verify_route(free, through_wall, (2, 0), (4, 0)))
    jump = [(2, 0), (2, 2)]
    assert any("4-neighbours" in p for p in verify_route(free, jump, (2, 0), (2, 2)))
    assert any("end at the goal" in p for p in verify_route(free, PAPER_ROUTE[:-1], (2, 0), (6, 5)))
    detour = [(2, 0), (1, 0), (1, 1), (2, 1)]
    assert any("shortest" in p for p in verify_route(free, detour, (2, 0), (2, 1), 1))


def test_bad_configs_and_methods_are_rejected():
    g = paper_grid()
    with pytest.raises(PlanInputError):
        plan(g, (2, 0), (6, 5), PlannerConfig(reward_step=1.0))
    with pytest.raises(PlanInputError):
        plan(g, (2, 0), (6, 5), PlannerConfig(learning_rate=0.0))
    with pytest.raises(PlanInputError):
        plan(g, (2, 0), (6, 5), method="astar")
    with pytest.raises(PlanInputError, match="heading"):
        plan(g, (2, 0), (6, 5), method="qlearning-heading")
    # numpy refuses negative seeds with a bare ValueError; the planner says what is wrong
    with pytest.raises(PlanInputError, match="seed must be a non-negative integer"):
        plan(g, (2, 0), (6, 5), PlannerConfig(seed=-1))
    # no convergence check ever (0) or only after an impractical number of steps
    for every in (0, -3, 1_000_001, 1_000_000_000):
        with pytest.raises(PlanInputError, match="check_every"):
            plan(g, (2, 0), (6, 5), PlannerConfig(check_every=every))
    # an infinite or NaN reward never converges: each goal held the node for max_seconds
    for kw in ({"reward_step": math.nan}, {"reward_goal": math.inf}, {"reward_turn": -math.inf}):
        with pytest.raises(PlanInputError, match="must be finite"):
            plan(g, (2, 0), (6, 5), PlannerConfig(**kw))  # type: ignore[arg-type]
    for kw in ({"max_episodes": -1}, {"replay": -1}, {"agents": -2}):
        with pytest.raises(PlanInputError, match="max_episodes must be >= 1"):
            plan(g, (2, 0), (6, 5), PlannerConfig(**kw))  # type: ignore[arg-type]
    # a NaN time limit compares false and would never stop the training
    for seconds in (math.nan, math.inf, 0.0, -1.0):
        with pytest.raises(PlanInputError, match="max_seconds"):
            plan(g, (2, 0), (6, 5), PlannerConfig(max_seconds=seconds))


def test_settings_under_which_the_cheapest_route_is_never_learned_are_refused():
    """With qlearning-heading a discount under 1 makes fewer steps worth more than fewer turns:
    the learned route never matched the cheapest one, and every reachable goal ended "not
    converged" after max_seconds. A negative reward_goal did the same with either method."""
    free = np.zeros((3, 3), dtype=np.int8)
    turns = {"reward_turn": -0.25, "reward_backward": -5.0, "max_seconds": 2.0}
    with pytest.raises(PlanInputError, match="discount must be 1 with qlearning-heading"):
        plan(free, (0, 1), (1, 1), PlannerConfig(discount=0.9, **turns),
             method="qlearning-heading", heading="up")  # fmt: skip
    with pytest.raises(PlanInputError, match="reward_goal must not be negative"):
        plan(free, (0, 1), (1, 1), PlannerConfig(reward_goal=-50.0, discount=0.9))
    res = plan(free, (0, 1), (1, 1), PlannerConfig(**turns), method="qlearning-heading",
               heading="up")  # fmt: skip
    assert res.ok, res.reason


def test_smaller_learning_rate_and_discount_still_verified():
    g = paper_grid()
    cfg = PlannerConfig(learning_rate=0.5, discount=0.95, q_init="zero", seed=1)
    res = plan(g, (2, 0), (6, 5), cfg)
    assert res.ok and res.cells == PAPER_ROUTE


def test_node_helpers_headings_and_path_poses():
    from wheelgrid_common.map_io import Grid

    assert heading_from_yaw(0.0, 0.0) == "right"
    assert heading_from_yaw(math.pi / 2, 0.0) == "up"
    assert heading_from_yaw(-math.pi / 2 + 0.3, 0.0) == "down"
    assert heading_from_yaw(math.pi - 0.2, 0.0) == "left"
    # a grid turned by 90 deg: map yaw pi/2 is the grid's "right"
    assert heading_from_yaw(math.pi / 2, math.pi / 2) == "right"

    class Q:
        def __init__(self, x, y, z, w):
            self.x, self.y, self.z, self.w = x, y, z, w

    s = math.sqrt(0.5)
    assert forward_yaw(Q(0, 0, s, s)) == pytest.approx(math.pi / 2)  # body x -> map +y
    # optical frame looking along map +x: z_opt = x_map, x_opt = -y_map, y_opt = -z_map
    assert forward_yaw(Q(-0.5, 0.5, -0.5, 0.5), "iphone_depth_optical_frame") == pytest.approx(0.0)
    # the mapper's rule: "*_optical" is optical too (it read 90 deg off, as a body frame), and
    # a set convention (the mapper's sensor_convention) wins over the name
    assert forward_yaw(Q(-0.5, 0.5, -0.5, 0.5), "camera_optical") == pytest.approx(0.0)
    assert forward_yaw(Q(-0.5, 0.5, -0.5, 0.5), "camera", "optical") == pytest.approx(0.0)
    assert forward_yaw(Q(-0.5, 0.5, -0.5, 0.5), "camera") == pytest.approx(-math.pi / 2)
    # a quaternion off unit length is the same rotation: a third of a 90 deg yaw read 5.6 deg
    assert forward_yaw(Q(0, 0, 0.3 * s, 0.3 * s)) == pytest.approx(math.pi / 2)
    assert forward_yaw(Q(0, 0, 1e200, 0)) == pytest.approx(math.pi)

    grid = Grid(paper_grid(), 0.5, (1.0, 2.0, 0.0))
    poses = path_poses(grid, PAPER_ROUTE, "down")
    assert len(poses) == len(PAPER_ROUTE)
    x, y, yaw = poses[0]
    assert (x, y) == pytest.approx((1.0 + 0.25, 2.0 + (8 - 2 - 0.5) * 0.5))
    assert yaw == pytest.approx(-math.pi / 2)  # the start heading: grid down = -y
    assert poses[1][2] == pytest.approx(0.0)  # entered (2,1) moving right = +x
    assert poses[5][2] == pytest.approx(0.0)  # entered (2,5) moving right
    assert poses[6][2] == pytest.approx(-math.pi / 2)  # entered (3,5) moving down
    assert path_poses(grid, PAPER_ROUTE)[0][2] == pytest.approx(0.0)  # no heading: first move
    turned = Grid(paper_grid(), 0.5, (0.0, 0.0, math.pi / 2))
    assert path_poses(turned, PAPER_ROUTE)[1][2] == pytest.approx(math.pi / 2)


def test_the_replay_pass_and_the_mdp_stop_at_the_deadline_and_agents_are_bounded(monkeypatch):
    """The newest-first replay pass ran its replay - 1 updates past the deadline (2.7 s over
    on a 300 x 300 grid), and the heading MDP was built after the search had used the budget;
    agents 2**28 passed the memory check with replay 1 and died allocating 8 GiB (exit 1)."""
    import time

    import wheelgrid_nav.planner as planner_mod

    g = np.zeros((40, 40), dtype=np.int8)
    cfg = PlannerConfig(replay=50, agents=64, max_seconds=30.0)
    mdp = _build_mdp(g == 0, (0, 0), (39, 39), cfg, None)
    calls = {"n": 0}
    real = time.perf_counter

    class Clock:  # the deadline passes a few updates into the first replay pass (step 50)
        @staticmethod
        def perf_counter() -> float:
            calls["n"] += 1
            return real() + (1e6 if calls["n"] > 55 else 0.0)

    monkeypatch.setattr(planner_mod, "time", Clock)
    out = planner_mod._learn(mdp, cfg, 78.0, deadline=real() + 30.0)
    assert out["steps"] == 50 and not out["converged"], out
    assert out["updates"] < (50 + 49) * 64, out["updates"]  # the pass stopped within it
    monkeypatch.undo()
    with pytest.raises(PlanInputError, match="agents"):
        plan(g, (0, 0), (39, 39), PlannerConfig(agents=2**28, replay=1))


def test_json_says_null_for_a_shortest_length_the_budget_cut_off():
    """--json gave shortest_moves -1, which means unreachable, for a search that the time
    budget cut off before it found any length (a 700 x 700 grid, max_seconds 0.005)."""
    from wheelgrid_nav.cli_plan import result_json

    cut = plan(np.zeros((700, 700), np.int8), (0, 0), (699, 699), PlannerConfig(max_seconds=1e-9))
    assert cut.reason == "not converged" and result_json(cut, None)["shortest_moves"] is None
    walled = np.zeros((3, 3), np.int8)
    walled[:, 1] = 100
    gone = plan(walled, (0, 0), (0, 2))
    assert gone.reason == "unreachable" and result_json(gone, None)["shortest_moves"] == -1


def test_a_large_grid_is_given_up_at_the_budget_and_its_agents_fit_the_history(monkeypatch):
    """A review: on a 1000 x 1000 open grid a heading-aware plan with a 2 s budget took 6.5 s
    (the MDP's build and its move table turned into lists were never timed), and one agent
    per state times replay 128 passed MAX_HISTORY, so any goal on a 724 x 724 grid was "bad
    input". The build and the lists look at the deadline now, and agents 0 means as many as
    the history holds; an explicit agents value too large is still refused."""
    import wheelgrid_nav.planner as planner_mod

    free = np.ones((30, 30), dtype=bool)
    cfg = PlannerConfig()
    assert _build_mdp(free, (0, 0), (29, 29), cfg, "right", deadline=0.0) is None
    assert _build_mdp(free, (0, 0), (29, 29), cfg, None, deadline=0.0) is None
    monkeypatch.setattr(planner_mod, "MAX_HISTORY", 128 * 100)  # 100 agents at replay 128
    grid = np.zeros((12, 12), dtype=np.int8)
    res = plan(grid, (0, 0), (11, 11), PlannerConfig(replay=128), method="qlearning")
    assert res.ok and len(res.cells) == 23, res.reason
    with pytest.raises(PlanInputError, match="history"):
        plan(grid, (0, 0), (11, 11), PlannerConfig(replay=128, agents=143), method="qlearning")
    with pytest.raises(PlanInputError, match="history"):  # fewer than 64 would fit: refused
        plan(grid, (0, 0), (11, 11), PlannerConfig(replay=1280), method="qlearning")


def test_rewards_too_small_to_tell_from_the_cost_checks_tolerance_are_refused():
    """With every reward under 1e-9 the cost checks (to 1e-9 of the optimum) let a route two
    moves and a turn longer pass as the cheapest, "ok" (a review: 10 of 200 random grids)."""
    for name in ("reward_step", "reward_blocked", "reward_turn", "reward_backward"):
        with pytest.raises(PlanInputError, match=f"{name} must be 0 or at least 1e-06"):
            check_config(PlannerConfig(**{name: -1e-10}), "qlearning-heading")
    check_config(PlannerConfig(reward_turn=0.0, reward_backward=0.0), "qlearning-heading")


def test_the_cost_check_tells_one_turn_apart_however_large_the_route_cost():
    """The cost checks allowed 1e-9 of the optimum: with reward_step -1e4 and reward_turn
    -1e-5 a route of cost 1e5 could carry a turn more and pass as the cheapest (a review).
    The tolerance is never half the smallest reward or more; the learned route is still the
    Dijkstra optimum under such rewards."""
    from wheelgrid_nav.planner import cost_tolerance

    scaled = PlannerConfig(reward_step=-1e4, reward_turn=-1e-5, reward_backward=-1e-5)
    assert cost_tolerance(scaled, 1e5) == 0.5e-5  # half the turn, not 1e-4
    assert cost_tolerance(PlannerConfig(), 20.0) == pytest.approx(2e-8)  # as before
    grid = np.zeros((6, 6), dtype=np.int8)
    grid[2, 1:5] = 100
    res = plan(grid, (0, 0), (5, 5), scaled, method="qlearning-heading", heading="down")
    mdp = _build_mdp(grid == 0, (0, 0), (5, 5), scaled, "down")
    assert res.ok and mdp is not None
    assert res.cost == pytest.approx(_optimal_cost(mdp), abs=1e-7), (res.cost, res.cells)


def test_the_ranges_the_planner_parameters_declare_hold_every_valid_value_and_no_other():
    """The planner's parameters declared no range (`ros2 param describe planner
    learning_rate` showed none): each declared one now holds every value check_config takes
    and no other."""
    from wheelgrid_common.testing import check_declared_bounds

    ranged = check_declared_bounds(PlannerConfig, lambda c: check_config(c))
    assert {"learning_rate", "epsilon", "max_seconds", "reward_step", "seed"} <= set(ranged)
