"""Benchmark of the Q-learning planner: optimality on many grids, and speed against A*.

    python bench/bench_planner.py [--quick] [--json FILE] [--repeats N] [--grids N]

Part 1, optimality: random grids (4..32 cells a side, 0..45 % obstacles), perfect mazes and grids
cut in two by a wall (no path). For each: the planner's route must be exactly as long as a BFS
shortest path, and where BFS finds no path the planner must return none.

Part 2, speed (median wall time of N runs after a warm-up, same process, and CPU time beside
it because the 2 cores are shared): the paper's 8 x 8 grid, random 16/32/64 grids with 25 %
obstacles, and mazes of 17/33/65 cells; plain ``qlearning`` and ``qlearning-heading``; the
baseline is A* (Manhattan heuristic, pure Python heapq) on the same grid, start and goal.
``ratio`` = planner time / A* time (how many times slower learning is than searching).
"""

from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from wheelgrid_nav.grid_synth import maze
from wheelgrid_nav.planner import PlannerConfig, astar, bfs_distances, plan

PAPER_OCCUPIED = [(3, 0), (3, 1), (3, 2), (3, 3), (3, 4), (5, 0), (5, 1), (5, 2), (5, 3), (4, 4)]


def paper_grid() -> np.ndarray:
    g = np.zeros((8, 8), dtype=np.int8)
    for r, c in [*PAPER_OCCUPIED, (6, 7)]:
        g[r, c] = 100
    return g


def random_case(rng: np.random.Generator, i: int) -> tuple[np.ndarray, tuple, tuple, str]:
    kind = ("random", "random", "random", "maze", "split")[i % 5]
    if kind == "maze":
        g = maze(int(rng.choice([9, 15, 21, 31])), rng)
    else:
        rows, cols = int(rng.integers(4, 33)), int(rng.integers(4, 33))
        g = np.where(rng.random((rows, cols)) < rng.random() * 0.45, 100, 0).astype(np.int8)
        if kind == "split":  # a full wall: start and goal on opposite sides have no path
            cols = max(cols, 5)
            g = np.zeros((rows, cols), np.int8) if g.shape[1] < 5 else g
            w = int(rng.integers(1, cols - 1))
            g[:, w] = 100
            left, right = np.argwhere(g[:, :w] == 0), np.argwhere(g[:, w + 1 :] == 0)
            if len(left) and len(right):
                s = tuple(int(v) for v in left[rng.integers(len(left))])
                t = right[rng.integers(len(right))]
                return g, s, (int(t[0]), int(t[1]) + w + 1), kind
    free = np.argwhere(g == 0)
    if len(free) < 2:
        g[0, 0] = g[-1, -1] = 0
        free = np.argwhere(g == 0)
    a, b = rng.choice(len(free), 2, replace=False)
    return g, tuple(int(v) for v in free[a]), tuple(int(v) for v in free[b]), kind


def optimality(n: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    counts = {"grids": 0, "optimal": 0, "no_path_refused": 0, "failed": 0, "mazes": 0}
    worst = 0.0
    for i in range(n):
        g, s, t, kind = random_case(rng, i)
        dist = int(bfs_distances(g == 0, t)[s])
        t0 = time.perf_counter()
        res = plan(g, s, t, PlannerConfig(seed=i))
        worst = max(worst, time.perf_counter() - t0)
        counts["grids"] += 1
        counts["mazes"] += kind == "maze"
        if dist < 0:
            ok = res.cells == [] and res.reason == "unreachable"
            counts["no_path_refused"] += ok
        else:
            ok = res.ok and len(res.cells) - 1 == dist
            counts["optimal"] += ok
        if not ok:
            counts["failed"] += 1
            print(f"  FAILED case {i} ({kind}, {g.shape}): {res.reason}")
    counts["worst_seconds"] = worst
    return counts


def timed(fn, repeats: int) -> tuple[float, float]:
    """Median wall and CPU seconds of ``repeats`` calls after one warm-up."""
    fn()
    wall, cpu = [], []
    for _ in range(repeats):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - w0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def speed_cases(quick: bool) -> list[tuple[str, np.ndarray, tuple, tuple]]:
    rng = np.random.default_rng(1)
    cases = [("paper 8x8", paper_grid(), (2, 0), (6, 5))]
    for n in (16, 32) if quick else (16, 32, 64):
        g = np.where(rng.random((n, n)) < 0.25, 100, 0).astype(np.int8)
        g[0, 0] = g[n - 1, n - 1] = 0
        while bfs_distances(g == 0, (n - 1, n - 1))[0, 0] < 0:  # keep a route corner to corner
            g = np.where(rng.random((n, n)) < 0.25, 100, 0).astype(np.int8)
            g[0, 0] = g[n - 1, n - 1] = 0
        cases.append((f"random {n}x{n} 25%", g, (0, 0), (n - 1, n - 1)))
    for n in (17, 33) if quick else (17, 33, 65):
        cases.append((f"maze {n}x{n}", maze(n, rng), (1, 1), (n - 2, n - 2)))
    return cases


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CI size: fewer grids, no 64/65 cells")
    ap.add_argument("--json", help="write the figures as {'rows': [...]}")
    ap.add_argument("--repeats", type=int, default=0, help="timed runs per case (default 5/3)")
    ap.add_argument("--grids", type=int, default=0, help="grids for part 1 (default 300/60)")
    args = ap.parse_args(argv)
    repeats = args.repeats or (3 if args.quick else 5)
    n_grids = args.grids or (60 if args.quick else 300)
    rows: list[dict] = []
    failed = 0

    t0 = time.perf_counter()
    opt = optimality(n_grids)
    solvable = opt["optimal"]
    print(
        f"optimality: {opt['grids']} grids ({opt['mazes']} mazes) in "
        f"{time.perf_counter() - t0:.1f} s: {opt['optimal']} BFS-optimal routes, "
        f"{opt['no_path_refused']} no-path grids refused, {opt['failed']} failures; "
        f"slowest plan {opt['worst_seconds'] * 1000:.0f} ms"
    )
    good = opt["optimal"] + opt["no_path_refused"]
    rows.append(
        {
            "figure": "planner: BFS-optimal or correctly refused",
            "value": round(100.0 * good / max(1, opt["grids"]), 2),
            "unit": "%",
            "baseline": None,
            "ratio": None,
            "note": f"{opt['grids']} grids: {solvable} routes, {opt['no_path_refused']} no-path,"
            f" {opt['mazes']} mazes, {opt['failed']} failed",
        }
    )

    print(
        f"\n{'case':<20} {'method':<18} {'moves':>5} {'episodes':>9} {'steps':>6} "
        f"{'wall ms':>8} {'cpu ms':>7} {'A* ms':>7} {'ratio':>7}"
    )
    for name, g, s, t in speed_cases(args.quick):
        free = g == 0
        a_wall, _ = timed(lambda free=free, s=s, t=t: astar(free, s, t), repeats)
        a_len = len(astar(free, s, t)) - 1
        for method in ("qlearning", "qlearning-heading"):
            heading = "down" if method == "qlearning-heading" else None
            res = plan(g, s, t, method=method, heading=heading)
            if not res.ok:  # reported, never hidden: a failure here fails the benchmark
                print(f"{name:<20} {method:<18} NO ROUTE: {res.reason}")
                rows.append(
                    {
                        "figure": f"plan {name} ({method})",
                        "value": None,
                        "unit": "ms",
                        "baseline": round(a_wall * 1000, 3),
                        "ratio": None,
                        "note": f"no route: {res.reason}",
                    }
                )
                failed += 1
                continue
            if method == "qlearning" and len(res.moves) != a_len:
                print(f"{name:<20} {method:<18} NOT SHORTEST: {len(res.moves)} vs A* {a_len}")
                failed += 1
            wall, cpu = timed(
                lambda g=g, s=s, t=t, m=method, h=heading: plan(g, s, t, method=m, heading=h),
                repeats,
            )
            print(
                f"{name:<20} {method:<18} {len(res.moves):>5} {res.episodes:>9} {res.steps:>6} "
                f"{wall * 1000:>8.1f} {cpu * 1000:>7.1f} {a_wall * 1000:>7.2f} "
                f"{wall / a_wall:>7.0f}"
            )
            rows.append(
                {
                    "figure": f"plan {name} ({method})",
                    "value": round(wall * 1000, 2),
                    "unit": "ms",
                    "baseline": round(a_wall * 1000, 3),
                    "ratio": round(wall / a_wall, 1),
                    "note": f"A* ms baseline; {res.episodes} episodes, {res.steps} steps, "
                    f"{len(free.nonzero()[0])} free cells, {len(res.moves)} moves, "
                    f"cpu {cpu * 1000:.1f} ms",
                }
            )
    if args.json:
        Path(args.json).write_text(json.dumps({"rows": rows}, indent=1))
    return 0 if opt["failed"] == 0 and failed == 0 else 1


if __name__ == "__main__":
    raise SystemExit(main())
