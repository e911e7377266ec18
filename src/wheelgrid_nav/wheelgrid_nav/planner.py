"""Tabular Q-learning route planner on the safe grid (the paper's section III.D), ROS-free.

States are free cells (or, for the heading-aware variant, (cell, heading) pairs); actions are
the four grid moves up/down/left/right. Training is plain sample-based Q-learning,
``Q(s,a) += alpha * (r + gamma * max_a' Q(s',a') - Q(s,a))``, vectorised by running many
epsilon-greedy agents at once (exploring starts from every free cell, as the hint to the issue
allows), so an 8 x 8 room trains in milliseconds and a 64 x 64 one in well under a second.

A wheelchair must never follow a half-learned route, so the planner is deliberately strict:

* unknown cells and everything outside the grid count as walls;
* training stops only when the greedy route from the start has been *stable* for
  ``stable_checks`` consecutive checks and reaches the goal at the optimal cost;
* the returned route is then *verified* independently of the learner: every cell free,
  4-connected, ending at the goal, and as cheap as breadth-first search (plain) or Dijkstra
  over (cell, heading) (heading-aware) says is possible on the same grid;
* if the budget runs out first, :func:`plan` returns no route and says why.

BFS / Dijkstra only *check* the learned route and decide convergence; the route itself always
comes from the learned Q-table.
"""

from __future__ import annotations

import heapq
import itertools
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from wheelgrid_common.params import check_bounds, check_finite
from wheelgrid_common.params import field as pfield
from wheelgrid_nav.actions import DELTAS, LEFT_OF, MOVES, OPPOSITE, RIGHT_OF, cells_to_moves

METHODS: tuple[str, ...] = ("qlearning", "qlearning-heading")
_DELTA = np.array([DELTAS[m] for m in MOVES], dtype=np.int64)  # (4, 2) row/col steps
_HEADING_INDEX = {m: i for i, m in enumerate(MOVES)}
# A convergence check costs about one training step, so checking rarely saves nothing; a
# larger interval only means no route is accepted within any practical budget.
MAX_CHECK_EVERY = 1_000_000


@dataclass
class PlannerConfig:
    """Q-learning hyper-parameters, rewards and the training budget (one place for all)."""

    learning_rate: float = pfield(
        1.0,
        "Q-learning step size alpha in (0, 1]; 1 is exact for the grid's deterministic moves",
        bounds=(0.0, 1.0),
    )
    discount: float = pfield(
        1.0,
        "discount gamma in (0, 1]; 1 keeps the learned route the cheapest one (the task ends at "
        "the goal) and keeps value differences on long corridors above float precision",
        bounds=(0.0, 1.0),
    )
    epsilon: float = pfield(
        0.1, "probability of a random (exploratory) move per step", bounds=(0.0, 1.0)
    )
    reward_step: float = pfield(
        -1.0, "reward for every move to a neighbouring free cell", bounds=(-math.inf, 0.0)
    )
    reward_blocked: float = pfield(
        -10.0,
        "reward for trying to enter a wall, occupied or unknown cell (the chair stays)",
        bounds=(-math.inf, 0.0),
    )
    reward_goal: float = pfield(
        100.0, "extra reward on reaching the goal (ends the episode)", bounds=(0.0, math.inf)
    )
    reward_turn: float = pfield(
        -0.5,
        "heading-aware only: extra reward for a quarter turn (left/right-forward)",
        bounds=(-math.inf, 0.0),
    )
    reward_backward: float = pfield(
        -1.0,
        "heading-aware only: extra reward for backing up (the costliest manoeuvre)",
        bounds=(-math.inf, 0.0),
    )
    q_init: str = pfield(
        "heuristic",
        "initial Q values: 'heuristic' = reward_goal + reward_step x Manhattan distance to the "
        "goal (an upper bound of every true value when discount is 1, so every untried move "
        "looks worth trying and no half-explored route locks in; with discount < 1 it falls "
        "back to 'optimistic'), 'optimistic' = max(reward_goal, 0), 'zero' = 0",
    )
    replay: int = pfield(
        128,
        "replay the last N steps' transitions newest-first every N steps (0 = off)",
        bounds=(0, math.inf),
    )
    agents: int = pfield(
        0,
        "parallel agents; 0 = one per state (exploring starts from every free cell/heading)",
        bounds=(0, math.inf),
    )
    max_episode_steps: int = pfield(
        0, "steps before an episode is cut; 0 = 2 x number of states", bounds=(0, math.inf)
    )
    max_episodes: int = pfield(
        2_000_000, "training budget in episodes (all agents together)", bounds=(1, math.inf)
    )
    max_seconds: float = pfield(
        10.0,
        "planning budget in wall-clock time, from the search for the optimum to the learned "
        "route (checked every step, > 0 and finite)",
        "s",
        bounds=(0.0, math.inf),
    )
    check_every: int = pfield(
        8,
        f"training steps between convergence checks (1 to {MAX_CHECK_EVERY})",
        bounds=(1, MAX_CHECK_EVERY),
    )
    stable_checks: int = pfield(
        2,
        "consecutive checks the greedy route must stay the same and optimal to converge",
        bounds=(1, math.inf),
    )
    seed: int = pfield(
        0, "random seed (>= 0); the same seed and grid give the same route", bounds=(0, math.inf)
    )
    allow_unknown_start: bool = pfield(
        True,
        "the chair's own cell may be unknown (a sensor on the chair never sees the floor under "
        "it); an occupied start is still refused and every other cell must be free",
    )


class PlanInputError(ValueError):
    """Start or goal unusable (outside the grid, occupied, unknown) or bad arguments."""


@dataclass
class PlanResult:
    """What :func:`plan` found. ``cells`` is empty whenever there is no verified route."""

    cells: list[tuple[int, int]]
    moves: list[str]
    converged: bool
    reason: str  # "ok", "unreachable", "not converged", or a verification failure
    method: str
    episodes: int = 0
    steps: int = 0  # batched training steps (each moves every agent once)
    updates: int = 0  # individual Q-learning updates
    seconds: float = 0.0
    cost: float = math.nan  # route cost in the method's own cost model (moves + manoeuvres)
    optimal_cost: float = math.nan  # the cheapest possible cost (BFS / Dijkstra)
    bfs_length: int = -1  # moves of a BFS shortest path, -1 when unreachable
    heading: str | None = None
    extra: dict[str, Any] = field(default_factory=dict)

    @property
    def ok(self) -> bool:
        return bool(self.cells) and self.converged


def free_mask(data: np.ndarray) -> np.ndarray:
    """Cells the chair may enter: only those marked free (0); unknown (-1) is NOT free."""
    return np.asarray(data) == 0


def check_cell(free: np.ndarray, cell: Sequence[int], what: str) -> tuple[int, int]:
    """Validate a start/goal cell; raises PlanInputError with a one-line reason."""
    r, c = int(cell[0]), int(cell[1])
    rows, cols = free.shape
    if not (0 <= r < rows and 0 <= c < cols):
        raise PlanInputError(f"{what} cell ({r},{c}) is outside the {rows}x{cols} grid")
    if not free[r, c]:
        raise PlanInputError(f"{what} cell ({r},{c}) is not free (occupied or unknown)")
    return r, c


def bfs_distances(free: np.ndarray, source: Sequence[int]) -> np.ndarray:
    """Moves from ``source`` to every cell over 4-connected free cells; -1 = unreachable."""
    dist = _bfs_until(free, source, math.inf)
    assert dist is not None  # no deadline
    return dist


def _bfs_until(free: np.ndarray, source: Sequence[int], deadline: float) -> np.ndarray | None:
    """:func:`bfs_distances`, or None once ``deadline`` (``time.perf_counter()``) has passed.

    Level by level over flat cell indices, each level one numpy step: a cell-by-cell Python
    queue took 1.1-1.6 s on a 700 x 700 grid, outside the ``max_seconds`` the planner
    promises (it counts from before this search)."""
    rows, cols = free.shape
    dist = np.full(rows * cols, -1, dtype=np.int64)
    r0, c0 = int(source[0]), int(source[1])
    if not free[r0, c0]:
        return dist.reshape(rows, cols)
    open_ = np.ascontiguousarray(free, dtype=bool).ravel()
    frontier = np.array([r0 * cols + c0])
    dist[frontier] = 0
    d = 0
    while frontier.size:
        if time.perf_counter() > deadline:
            return None
        d += 1
        col = frontier % cols
        cand = np.concatenate(
            (
                frontier[frontier >= cols] - cols,
                frontier[frontier < (rows - 1) * cols] + cols,
                frontier[col > 0] - 1,
                frontier[col < cols - 1] + 1,
            )
        )
        cand = np.unique(cand[open_[cand] & (dist[cand] < 0)])
        dist[cand] = d
        frontier = cand
    return dist.reshape(rows, cols)


def astar(free: np.ndarray, start: Sequence[int], goal: Sequence[int]) -> list[tuple[int, int]]:
    """A* with the Manhattan heuristic: the classic baseline the benchmark compares against."""
    rows, cols = free.shape
    s, g = (int(start[0]), int(start[1])), (int(goal[0]), int(goal[1]))
    if not (free[s] and free[g]):
        return []
    gcost = {s: 0}
    parent: dict[tuple[int, int], tuple[int, int]] = {}
    heap = [(abs(s[0] - g[0]) + abs(s[1] - g[1]), 0, s)]
    while heap:
        _, gc, cur = heapq.heappop(heap)
        if cur == g:
            path = [cur]
            while path[-1] in parent:
                path.append(parent[path[-1]])
            return path[::-1]
        if gc > gcost[cur]:
            continue
        for dr, dc in DELTAS.values():
            nb = (cur[0] + dr, cur[1] + dc)
            if 0 <= nb[0] < rows and 0 <= nb[1] < cols and free[nb]:
                ng = gc + 1
                if ng < gcost.get(nb, 1 << 60):
                    gcost[nb] = ng
                    parent[nb] = cur
                    heapq.heappush(heap, (ng + abs(nb[0] - g[0]) + abs(nb[1] - g[1]), ng, nb))
    return []


# ------------------------------------------------------------------------------------------
# The MDPs: transition and reward tables over state indices.
# ------------------------------------------------------------------------------------------


@dataclass
class _Mdp:
    nxt: np.ndarray  # (S, 4) int64: next state (== s when the move is blocked)
    rew: np.ndarray  # (S, 4) float64
    terminal: np.ndarray  # (S,) bool: goal states
    cost: np.ndarray  # (S, 4) float64: manoeuvre cost of the move (inf when blocked)
    cell_of_state: np.ndarray  # (S, 2) int64 row, col
    start: int
    heading_of_state: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))


def _neighbour_index(free: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Free-cell numbering and, per free cell and move, the free neighbour's index or -1."""
    rows, cols = free.shape
    index = np.full((rows, cols), -1, dtype=np.int64)
    rc = np.argwhere(free)
    index[rc[:, 0], rc[:, 1]] = np.arange(len(rc))
    nb = np.full((len(rc), 4), -1, dtype=np.int64)
    for a in range(4):
        rr, cc = rc[:, 0] + _DELTA[a, 0], rc[:, 1] + _DELTA[a, 1]
        ok = (rr >= 0) & (rr < rows) & (cc >= 0) & (cc < cols)
        nb[ok, a] = index[rr[ok], cc[ok]]
    return index, nb


def _build_mdp(
    free: np.ndarray,
    start: tuple[int, int],
    goal: tuple[int, int],
    cfg: PlannerConfig,
    heading: str | None,
    reenter_start: bool = True,
    deadline: float = math.inf,
) -> _Mdp | None:
    """The MDP over ``free``; with ``reenter_start`` False no move enters the start cell (an
    unknown cell the chair stands on may be left, never driven into). None once ``deadline``
    (``time.perf_counter()``) has passed, looked at between its stages: the heading-aware
    build of a 1000 x 1000 grid took 2.6 s, inside no budget."""
    index, nb = _neighbour_index(free)
    if time.perf_counter() > deadline:
        return None
    if not reenter_start:
        nb[nb == index[start]] = -1
    rc = np.argwhere(free)
    n = len(rc)
    move_cost = -cfg.reward_step
    if heading is None:  # plain: state = free cell
        blocked = nb < 0
        nxt = np.where(blocked, np.arange(n)[:, None], nb)
        cost = np.where(blocked, np.inf, move_cost)
        terminal = np.zeros(n, dtype=bool)
        terminal[index[goal]] = True
        rew = np.where(blocked, cfg.reward_blocked, cfg.reward_step)
        rew = rew + np.where(~blocked & terminal[nxt], cfg.reward_goal, 0.0)
        return _Mdp(nxt, rew, terminal, cost, rc, int(index[start]))
    # heading-aware: state = cell * 4 + heading; the move's direction becomes the new heading
    # except when backing up, which keeps it (Table II).
    extra = np.zeros((4, 4))  # [heading, move] -> extra reward of that manoeuvre
    new_h = np.zeros((4, 4), dtype=np.int64)
    for h, hname in enumerate(MOVES):
        for a, mname in enumerate(MOVES):
            if mname == OPPOSITE[hname]:
                extra[h, a], new_h[h, a] = cfg.reward_backward, h
            elif mname in (LEFT_OF[hname], RIGHT_OF[hname]):
                extra[h, a], new_h[h, a] = cfg.reward_turn, a
            else:
                new_h[h, a] = a
    cell = np.repeat(np.arange(n), 4)
    hd = np.tile(np.arange(4), n)
    states = np.arange(4 * n)
    ncell = nb[cell]  # (S, 4)
    blocked = ncell < 0
    if time.perf_counter() > deadline:
        return None
    nxt = np.where(blocked, states[:, None], ncell * 4 + new_h[hd])
    step_rew = cfg.reward_step + extra[hd]
    if time.perf_counter() > deadline:
        return None
    cost = np.where(blocked, np.inf, -step_rew)
    terminal = cell == index[goal]
    rew = np.where(blocked, cfg.reward_blocked, step_rew)
    rew = rew + np.where(~blocked & terminal[nxt], cfg.reward_goal, 0.0)
    start_state = int(index[start]) * 4 + _HEADING_INDEX[heading]
    return _Mdp(nxt, rew, terminal, cost, rc[cell], start_state, hd)


_LIST_BLOCK = 65536  # states turned into lists between two looks at the deadline


def _optimal_cost(mdp: _Mdp, deadline: float = math.inf) -> float | None:
    """Dijkstra over the MDP's move costs from the start to any goal state (inf if none);
    None once ``deadline`` (``time.perf_counter()``) has passed: on a 600 x 600 grid this
    pure-Python search alone took 11.6 s, outside the ``max_seconds`` the planner promises.

    The plain planner does not need it: every move costs the same, so its optimum is exactly
    BFS length x cost (:func:`plan`).
    """
    S = len(mdp.terminal)
    dist = np.full(S, np.inf)
    dist[mdp.start] = 0.0
    heap = [(0.0, mdp.start)]
    # as lists (fast to index one by one), a block at a time with the deadline between: the
    # lists alone took 4.9 s on a 1000 x 1000 grid, 2.4 s past a 2 s budget
    nxt: list[list[int]] = []
    cost: list[list[float]] = []
    for k in range(0, S, _LIST_BLOCK):
        if time.perf_counter() > deadline:
            return None
        nxt += mdp.nxt[k : k + _LIST_BLOCK].tolist()
        cost += mdp.cost[k : k + _LIST_BLOCK].tolist()
    terminal = mdp.terminal
    if time.perf_counter() > deadline:
        return None
    pops = 0
    while heap:
        pops += 1
        if pops % 4096 == 0 and time.perf_counter() > deadline:
            return None
        d, s = heapq.heappop(heap)
        if d > dist[s]:
            continue
        if terminal[s]:
            return d
        for a in range(4):
            c = cost[s][a]
            if c == math.inf:
                continue
            t, nd = nxt[s][a], d + c
            if nd < dist[t]:
                dist[t] = nd
                heapq.heappush(heap, (nd, t))
    return math.inf


def _rowmax(q: np.ndarray) -> np.ndarray:
    """Row maxima of an (N, 4) array; ~5x faster than ``q.max(axis=1)`` on short rows."""
    return np.maximum(np.maximum(q[:, 0], q[:, 1]), np.maximum(q[:, 2], q[:, 3]))


def _greedy_route(Q: np.ndarray, mdp: _Mdp, tol: float) -> tuple[list[int], float] | None:
    """States visited by the greedy policy from the start and the route's cost.

    None if the policy loops or bumps into a wall (a blocked move stays in place). Ties
    (within ``tol``) go to the lowest move index so the route is deterministic.
    """
    S = len(Q)
    floor = _rowmax(Q) - tol
    greedy = np.argmax(floor[:, None] <= Q, axis=1)
    go = mdp.nxt[np.arange(S), greedy].tolist()
    terminal = mdp.terminal.tolist()
    seen = {mdp.start}
    route = [mdp.start]
    s = mdp.start
    while not terminal[s]:
        s = go[s]
        if s in seen:
            return None
        seen.add(s)
        route.append(s)
    states = np.asarray(route[:-1])
    return route, float(mdp.cost[states, greedy[states]].sum())


def verify_route(
    free: np.ndarray,
    cells: Sequence[Sequence[int]],
    start: Sequence[int],
    goal: Sequence[int],
    bfs_length: int | None = None,
    allow_revisits: bool = False,
) -> list[str]:
    """Independent safety check of a route; returns the problems found (empty = verified).

    Checks every cell is inside and free, consecutive cells are 4-neighbours, the route starts
    at ``start`` and ends at ``goal``, no cell comes twice (unless ``allow_revisits``: a
    heading-aware route may turn round in a side pocket and come back out into the cell it
    left, at another heading), and (given ``bfs_length``) it is no longer than that.
    """
    problems = []
    if not cells:
        return ["empty route"]
    rows, cols = free.shape
    for r, c in cells:
        if not (0 <= r < rows and 0 <= c < cols) or not free[r, c]:
            problems.append(f"cell ({r},{c}) is not free")
    for a, b in itertools.pairwise(cells):
        if abs(a[0] - b[0]) + abs(a[1] - b[1]) != 1:
            problems.append(f"cells ({a[0]},{a[1]}) and ({b[0]},{b[1]}) are not 4-neighbours")
    if tuple(cells[0]) != tuple(start):
        problems.append("route does not begin at the start")
    if tuple(cells[-1]) != tuple(goal):
        problems.append("route does not end at the goal")
    if not allow_revisits and len({tuple(c) for c in cells}) != len(cells):
        problems.append("route visits a cell twice")
    if bfs_length is not None and len(cells) - 1 > bfs_length:
        problems.append(f"route has {len(cells) - 1} moves, the shortest has {bfs_length}")
    return problems


def _initial_values(mdp: _Mdp, cfg: PlannerConfig) -> np.ndarray:
    """Per-state initial Q value (see PlannerConfig.q_init)."""
    S = len(mdp.terminal)
    if cfg.q_init == "zero":
        return np.zeros(S)
    if cfg.q_init == "optimistic" or cfg.discount < 1.0:
        # every reward but the goal's is negative, so no (discounted) return exceeds this
        return np.full(S, max(cfg.reward_goal, 0.0))
    goal_rc = mdp.cell_of_state[np.argmax(mdp.terminal)]
    manhattan = np.abs(mdp.cell_of_state - goal_rc).sum(axis=1)
    # every route needs at least Manhattan-many moves, each worth at most reward_step, so this
    # bounds Q(s, a) from above for every move a (a blocked move only adds a penalty)
    bound = cfg.reward_goal + cfg.reward_step * manhattan
    if len(mdp.heading_of_state):
        bound = bound - _manoeuvre_lower_bound(mdp, goal_rc, cfg)
    return bound


def _manoeuvre_lower_bound(mdp: _Mdp, goal_rc: np.ndarray, cfg: PlannerConfig) -> np.ndarray:
    """Least extra manoeuvre cost any route from (cell, heading) to the goal must pay.

    A route must move in every grid direction that points towards the goal. Moving across the
    heading is a quarter turn; moving against it is backing up (or two quarter turns). So with
    two needed directions at least one turn is unavoidable, and more when the chair faces away.
    """
    turn, back = -cfg.reward_turn, -cfg.reward_backward
    d = goal_rc - mdp.cell_of_state  # (S, 2) row, col offsets to the goal
    need_v = np.where(d[:, 0] > 0, 1, np.where(d[:, 0] < 0, 0, -1))  # MOVES index or -1
    need_h = np.where(d[:, 1] > 0, 3, np.where(d[:, 1] < 0, 2, -1))
    h = mdp.heading_of_state
    opposite = np.array([1, 0, 3, 2])[h]
    lb = np.zeros(len(h))
    for need, other in ((need_v, need_h), (need_h, need_v)):
        has = need >= 0
        ahead = need == h
        against = need == opposite
        across = has & ~ahead & ~against
        alone = other < 0
        # only this direction is needed: across -> one turn, against -> back up or two turns
        lb = np.where(alone & across, turn, lb)
        lb = np.where(alone & against, min(back, 2 * turn), lb)
    both = (need_v >= 0) & (need_h >= 0)
    facing_one = (need_v == h) | (need_h == h)
    # both needed: facing one of them, one turn; facing away from one, a turn for the other
    # plus backing up or a second turn for the first
    lb = np.where(both & facing_one, turn, lb)
    lb = np.where(both & ~facing_one, turn + min(back, turn), lb)
    return lb


# The replay history is (replay x agents) int64: at most this many entries (2 GiB)
MAX_HISTORY = 2**28
# The smallest reward size (other than 0) the cost checks can tell apart from their tolerance
MIN_REWARD = 1e-6
# agents 0 (one per state) takes fewer where the history cannot hold them all, but not fewer
# than this: a replay that leaves fewer is the setting's fault, and refused
MIN_AUTO_AGENTS = 64
# Each agent also holds a few (agents x 4) float64 arrays a step: 2**24 agents is ~2 GiB of
# them; 2**28 passed the history check with replay 1 and died allocating 8 GiB (exit 1)
MAX_AGENTS = 2**24


def _learn(mdp: _Mdp, cfg: PlannerConfig, optimal: float, deadline: float) -> dict[str, Any]:
    """Batched epsilon-greedy Q-learning until the greedy route is optimal and stable, or
    until ``deadline`` (``time.perf_counter()``: :func:`plan`'s start plus ``max_seconds``).

    Every step moves all agents once and applies one Q-learning update per agent; every
    ``replay`` steps the transitions just experienced are replayed newest-first (reverse-sweep
    experience replay), which carries the goal's value back along whole trajectories instead
    of one cell per step. Each replayed update is the same sample-based Q-learning update.
    """
    rng = np.random.default_rng(cfg.seed)
    S = len(mdp.terminal)
    nonterminal = np.nonzero(~mdp.terminal)[0]
    # agents 0: one per state, as many as the history allows (one per state of a 724 x 724
    # open grid, heading-aware, with replay 128 was "bad input", exit 2, for any goal), but
    # no fewer than MIN_AUTO_AGENTS: a replay so long that fewer fit is refused below
    B = cfg.agents
    if B == 0:
        B = min(len(nonterminal), MAX_AGENTS)
        fit = MAX_HISTORY // max(cfg.replay, 1)
        if fit >= min(B, MIN_AUTO_AGENTS):
            B = min(B, fit)
    if B > MAX_AGENTS:
        raise PlanInputError(f"agents {B} is more than {MAX_AGENTS} (memory): lower agents")
    if max(cfg.replay, 1) * B > MAX_HISTORY:
        # replay 1e8 (or agents 1e9) passed the settings check and ended in a 38.7 GiB
        # allocation error, a traceback, exit 1
        raise PlanInputError(
            f"replay {cfg.replay} x {B} agents would keep {max(cfg.replay, 1) * B * 8 / 2**30:.1f}"
            f" GiB of history (at most {MAX_HISTORY * 8 / 2**30:.0f}): lower replay or agents"
        )
    max_ep_steps = cfg.max_episode_steps if cfg.max_episode_steps > 0 else 2 * S
    check_every = cfg.check_every  # check_config keeps it in [1, MAX_CHECK_EVERY]
    H = max(0, cfg.replay)
    alpha, gamma, eps = cfg.learning_rate, cfg.discount, cfg.epsilon
    rewards = [cfg.reward_step, cfg.reward_blocked, cfg.reward_turn, cfg.reward_backward]
    resolution = min(abs(v) for v in rewards if v != 0.0)
    # A tiny random offset per (s, a) breaks ties among untried moves in a random order (so
    # agents do not all try "up" first) without a per-step tie-break draw; it is far below
    # any real reward difference, and route costs are always judged on the exact cost table.
    noise = 1e-6 * resolution
    Q = (_initial_values(mdp, cfg)[:, None] + noise * rng.random((S, 4))).ravel()
    Q.reshape(S, 4)[mdp.terminal] = 0.0
    Q2 = Q.reshape(S, 4)
    nxt, rew = mdp.nxt.ravel(), mdp.rew.ravel()
    terminal = mdp.terminal
    tol = 2 * noise
    cost_tol = cost_tolerance(cfg, optimal)  # how near the optimum a learned route must come
    # exploring starts: a random permutation of every non-goal state (the start included)
    pos = rng.permutation(nonterminal)[:B] if len(nonterminal) >= B else rng.choice(nonterminal, B)
    pos[0] = mdp.start
    age = np.zeros(B, dtype=np.int64)
    history = np.zeros((max(H, 1), B), dtype=np.int64)
    episodes, steps, updates = B, 0, 0
    prev_route: list[int] | None = None
    stable = 0
    route: list[int] | None = None
    route_cost = math.nan
    converged = False

    def update(idx: np.ndarray) -> np.ndarray:
        s2 = nxt[idx]
        done = terminal[s2]
        target = rew[idx] + gamma * np.where(done, 0.0, _rowmax(Q2[s2]))
        # Deterministic moves: duplicate (s, a) pairs in a batch share one target, and a plain
        # fancy-index write applies it once (the last write wins). That is one update where
        # applying them one by one would be several: the same with alpha 1 (the default),
        # a smaller step towards the same target otherwise, still a Q-learning update.
        Q[idx] += alpha * (target - Q[idx])
        return s2

    while True:
        q = Q2[pos]
        # random tie-break among (near-)greedy moves, so agents do not all try "up" first
        near = q >= (_rowmax(q) - tol)[:, None]
        act = np.argmax(near * rng.random(q.shape), axis=1)
        explore = rng.random(B) < eps
        act[explore] = rng.integers(0, 4, int(explore.sum()))
        idx = pos * 4 + act
        s2 = update(idx)
        steps += 1
        updates += B
        if H:
            history[(steps - 1) % H] = idx
            if steps % H == 0:
                for k in range(H - 2, -1, -1):  # newest first; the newest was just applied
                    if time.perf_counter() > deadline:  # a pass overran max_seconds by 2.7 s
                        break
                    update(history[k])
                    updates += B
        age += 1
        restart = terminal[s2] | (age >= max_ep_steps)
        k = int(restart.sum())
        if k:
            s2[restart] = rng.choice(nonterminal, k)
            age[restart] = 0
            episodes += k
        pos = s2
        if steps % check_every == 0:
            found = _greedy_route(Q2, mdp, tol)
            route, route_cost = found if found else (None, math.nan)
            good = found is not None and abs(found[1] - optimal) <= cost_tol
            if good and route == prev_route:
                stable += 1
            else:
                stable = 1 if good else 0
            prev_route = route if good else None
            if stable >= cfg.stable_checks:
                converged = True
                break
        # The budgets are checked every step, not only at convergence checks: with a large
        # check_every the time limit would otherwise not bound the training at all.
        if episodes >= cfg.max_episodes or time.perf_counter() > deadline:
            break
    return {
        "Q": Q2,
        "route": route if converged else None,
        "cost": route_cost,
        "converged": converged,
        "episodes": episodes,
        "steps": steps,
        "updates": updates,
    }


def plan(
    data: np.ndarray,
    start: Sequence[int],
    goal: Sequence[int],
    cfg: PlannerConfig | None = None,
    method: str = "qlearning",
    heading: str | None = None,
) -> PlanResult:
    """Learn and verify a route from ``start`` to ``goal`` (row, col) on a grid.

    ``data`` is a Grid's ``data`` (0 free, 100 occupied, -1 unknown) or a boolean free mask.
    ``method`` "qlearning" learns over cells (the paper); "qlearning-heading" over (cell,
    heading) with turns and backing up costing extra (needs ``heading``), so routes with fewer
    manoeuvres win. Raises :class:`PlanInputError` for a bad start/goal/method; an unreachable
    goal or an unconverged training returns a result with no cells and the reason.
    """
    cfg = cfg or PlannerConfig()
    check_config(cfg, method)
    if method not in METHODS:
        raise PlanInputError(f"unknown method {method!r} (use {' or '.join(METHODS)})")
    if heading is not None and heading not in DELTAS:
        raise PlanInputError(f"unknown heading {heading!r} (use {', '.join(MOVES)})")
    if method == "qlearning-heading" and heading is None:
        raise PlanInputError("method qlearning-heading needs the start heading")
    arr = np.asarray(data)
    grid_free = arr if arr.dtype == bool else free_mask(arr)
    free = grid_free
    start_unknown = False
    if cfg.allow_unknown_start and arr.dtype != bool:
        r0, c0 = int(start[0]), int(start[1])
        if 0 <= r0 < arr.shape[0] and 0 <= c0 < arr.shape[1] and arr[r0, c0] < 0:
            free = free.copy()
            free[r0, c0] = True  # the chair stands there: it may leave, never come back
            start_unknown = True
    s = check_cell(free, start, "start")
    # The goal is judged on the grid as given: the relaxation above is for the chair's own
    # cell only, and must not make an unknown goal "free" when the goal is that same cell.
    g = check_cell(grid_free, goal, "goal")
    t0 = time.perf_counter()
    # The time budget counts from t0, the start of planning: the search for the optimum and
    # the MDP are part of the work (a large grid held the node tens of seconds past it).
    deadline = t0 + cfg.max_seconds
    dist = _bfs_until(free, g, deadline)
    if dist is None:
        took = time.perf_counter() - t0
        return PlanResult([], [], False, "not converged", method, heading=heading, seconds=took)
    bfs_len = int(dist[s])
    res = PlanResult([], [], False, "", method, bfs_length=bfs_len, heading=heading)
    if bfs_len < 0:
        res.reason = "unreachable"
        res.seconds = time.perf_counter() - t0
        return res
    if s == g:
        res.cells, res.converged, res.reason, res.cost, res.optimal_cost = [s], True, "ok", 0, 0
        res.seconds = time.perf_counter() - t0
        return res
    heading_aware = method == "qlearning-heading"
    if time.perf_counter() > deadline:  # the search used the budget: no MDP built past it
        res.reason = "not converged"
        res.seconds = time.perf_counter() - t0
        return res
    # A heading-aware route may come back into a cell (a three-point turn), but not into an
    # unknown start: the drive enters only cells known to be free, and stopped there.
    mdp = _build_mdp(
        free,
        s,
        g,
        cfg,
        heading if heading_aware else None,
        reenter_start=not start_unknown,
        deadline=deadline,
    )
    found = None
    if mdp is not None and time.perf_counter() <= deadline:
        found = bfs_len * -cfg.reward_step if not heading_aware else _optimal_cost(mdp, deadline)
    if mdp is None or found is None:
        res.reason = "not converged"
        res.seconds = time.perf_counter() - t0
        return res
    optimal = found
    out = _learn(mdp, cfg, optimal, deadline)
    res.episodes, res.steps, res.updates = out["episodes"], out["steps"], out["updates"]
    res.optimal_cost = optimal
    res.converged = out["converged"]
    if not res.converged:
        res.reason = "not converged"
        res.seconds = time.perf_counter() - t0
        return res
    route = out["route"]
    cells = [(int(r), int(c)) for r, c in mdp.cell_of_state[route]]
    res.cost = out["cost"]
    # the plain planner must match BFS exactly; the heading-aware one may trade length for
    # fewer manoeuvres, and is held to the Dijkstra optimum of its own cost model instead.
    problems = verify_route(
        free, cells, s, g, None if heading_aware else bfs_len, allow_revisits=heading_aware
    )
    if start_unknown and s in cells[1:]:
        problems.append(f"route comes back into the unknown start cell ({s[0]},{s[1]})")
    if abs(res.cost - optimal) > cost_tolerance(cfg, optimal):
        problems.append(f"route cost {res.cost} is not the optimum {optimal}")
    res.seconds = time.perf_counter() - t0
    if problems:
        res.converged = False
        res.reason = "verification failed: " + "; ".join(problems)
        return res
    res.cells = cells
    res.moves = cells_to_moves(cells)
    res.reason = "ok"
    return res


def cost_tolerance(cfg: PlannerConfig, optimal: float) -> float:
    """How far a route's cost may lie from the optimum and still be it: float rounding (1e-9
    of it), but never half the smallest reward or more. Relative alone, on a route of cost
    1e5 (reward_step -1e4) a turn of -1e-5 more passed as the cheapest (a review)."""
    sizes = [abs(v) for v in (cfg.reward_step, cfg.reward_turn, cfg.reward_backward) if v]
    return min(1e-9 * max(1.0, abs(optimal)), 0.5 * min(sizes, default=1.0))


def check_config(cfg: PlannerConfig, method: str | None = None) -> None:
    """Reject settings under which the learned optimum would not be the cheapest route.

    ``method`` "qlearning-heading" also needs ``discount`` 1: under 1 a route of fewer steps
    is worth more than one of fewer turns, the learned route is never the cheapest the check
    asks for, and every goal ended "not converged" after ``max_seconds`` (holding the node).
    A negative ``reward_goal`` made reaching the goal a loss, to the same end."""
    try:
        # an infinite or NaN reward never converges (every goal then held the node for
        # max_seconds and ended "not converged"), and a NaN max_seconds compares false in
        # the time check and would remove the limit
        check_finite(cfg)
    except ValueError as exc:
        raise PlanInputError(str(exc)) from None
    if cfg.max_episodes < 1 or min(cfg.replay, cfg.agents, cfg.max_episode_steps) < 0:
        raise PlanInputError("max_episodes must be >= 1; replay, agents, max_episode_steps >= 0")
    if not 0.0 < cfg.learning_rate <= 1.0:
        raise PlanInputError("learning_rate must be in (0, 1]")
    if not 0.0 < cfg.discount <= 1.0:
        raise PlanInputError("discount must be in (0, 1]")
    if method == "qlearning-heading" and cfg.discount != 1.0:
        raise PlanInputError(
            "discount must be 1 with qlearning-heading: under 1 fewer steps outweigh fewer "
            "turns, and the cheapest route is never learned"
        )
    if cfg.reward_goal < 0:
        raise PlanInputError("reward_goal must not be negative: reaching the goal is no loss")
    if not 0.0 <= cfg.epsilon <= 1.0:
        raise PlanInputError("epsilon must be in [0, 1]")
    if cfg.reward_step >= 0 or cfg.reward_blocked >= 0:
        raise PlanInputError("reward_step and reward_blocked must be negative")
    if cfg.reward_turn > 0 or cfg.reward_backward > 0:
        raise PlanInputError("reward_turn and reward_backward must not be positive")
    small = [
        name
        for name in ("reward_step", "reward_blocked", "reward_turn", "reward_backward")
        if 0.0 < abs(getattr(cfg, name)) < MIN_REWARD
    ]
    if small:
        # route costs are compared to within 1e-9 of the optimum: with every reward under
        # that, a route two moves and a turn longer passed as the cheapest (a review)
        raise PlanInputError(
            f"{', '.join(small)} must be 0 or at least {MIN_REWARD:g} in size: the learned "
            "route's cost is checked against the optimum to 1e-9"
        )
    if cfg.q_init not in ("heuristic", "optimistic", "zero"):
        raise PlanInputError("q_init must be heuristic, optimistic or zero")
    if cfg.stable_checks < 1:
        raise PlanInputError("stable_checks must be at least 1")
    if not 1 <= cfg.check_every <= MAX_CHECK_EVERY:
        raise PlanInputError(f"check_every must be from 1 to {MAX_CHECK_EVERY}")
    if not cfg.max_seconds > 0:
        raise PlanInputError("max_seconds must be a positive finite number")
    if cfg.seed < 0:  # numpy's generators take only non-negative seeds
        raise PlanInputError(f"seed must be a non-negative integer, got {cfg.seed}")
    try:  # the ranges the parameters declare (the explanations above first)
        check_bounds(cfg)
    except ValueError as exc:
        raise PlanInputError(str(exc)) from None
