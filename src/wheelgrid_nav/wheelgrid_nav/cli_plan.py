"""``wheelgrid plan``: learn and verify a route on a saved safe grid, print it like Table II.

Cells are (row, col) with row 0 the top row of the grid image (the paper's Table II): "down"
is row + 1, "right" is col + 1. Start and goal may also be given in metres in the map frame.
Exit codes: 0 route found and verified; 2 bad input (start/goal outside, occupied or unknown,
goal unreachable, bad flags); 1 training did not converge within its budget (no route given:
a chair never gets a half-learned one).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from wheelgrid_common.map_io import Grid, read_map
from wheelgrid_common.params import describe, load_yaml
from wheelgrid_nav.actions import MOVES, moves_to_actions
from wheelgrid_nav.planner import METHODS, PlanInputError, PlannerConfig, PlanResult, plan


def _pair(text: str, kind: type, what: str) -> tuple[Any, Any]:
    parts = text.replace(" ", "").split(",")
    if len(parts) != 2:
        raise PlanInputError(f"{what} must be two comma-separated numbers, got {text!r}")
    try:
        return kind(parts[0]), kind(parts[1])
    except ValueError:
        raise PlanInputError(f"{what}: cannot read {text!r} as two {kind.__name__}s") from None


def _cell(grid: Grid, rc: str | None, xy: str | None, what: str) -> tuple[int, int]:
    if (rc is None) == (xy is None):
        raise PlanInputError(f"give exactly one of --{what} R,C or --{what}-xy X,Y")
    if rc is not None:
        return _pair(rc, int, f"--{what}")
    x, y = _pair(str(xy), float, f"--{what}-xy")
    return grid.cell_of(x, y)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wheelgrid plan",
        description="Plan up/down/left/right moves on a safe grid with Q-learning; the route is "
        "verified (free, 4-connected, shortest) before it is printed.",
        epilog="Planner settings (--config YAML, plain mapping or a 'planner:' section): "
        + "; ".join(f"{k}: {v}" for k, v in describe(PlannerConfig).items()),
    )
    p.add_argument("grid", help="map_server YAML of the safe grid (grid.yaml)")
    p.add_argument("--start", metavar="R,C", help="start cell (row, col), row 0 = top row")
    p.add_argument("--goal", metavar="R,C", help="goal cell (row, col)")
    p.add_argument("--start-xy", metavar="X,Y", help="start in metres in the map frame")
    p.add_argument("--goal-xy", metavar="X,Y", help="goal in metres in the map frame")
    p.add_argument("--heading", choices=MOVES, help="the chair's heading at the start (grid)")
    p.add_argument("--method", choices=METHODS, default="qlearning", help="default qlearning")
    p.add_argument("--seed", type=int, help="random seed (overrides the config's)")
    p.add_argument("--config", help="YAML with PlannerConfig fields")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--png", metavar="FILE", help="write the grid with the route as a PNG")
    return p


def result_json(res: PlanResult, heading: str | None) -> dict[str, Any]:
    """The ``--json`` object (also used by the planner node's logs and the benchmark)."""
    out: dict[str, Any] = {
        "cells": [[r, c] for r, c in res.cells],
        "moves": list(res.moves),
        "episodes": res.episodes,
        "converged": res.converged,
        "seconds": round(res.seconds, 6),
        "method": res.method,
        "reason": res.reason,
        "cost": None if res.cost != res.cost else res.cost,
        "shortest_moves": res.bfs_length,
    }
    if heading is not None:
        out["heading"] = heading
        out["actions"] = moves_to_actions(res.cells, heading) if res.cells else []
    return out


def format_table(res: PlanResult, heading: str | None) -> str:
    """A readable table; with a heading it has the paper's Table II columns."""
    lines = []
    if heading is not None:
        head = ("State of wheelchair", "Current direction (d)", "Predicted action (a)")
        head += ("New direction (d')", "Actual action")
        rows = [
            (
                f"({a['from'][0]},{a['from'][1]}) to ({a['to'][0]},{a['to'][1]})",
                a["heading"].capitalize(),
                a["move"].capitalize(),
                a["new_heading"].capitalize(),
                a["action"].title(),
            )
            for a in moves_to_actions(res.cells, heading)
        ]
    else:
        head = ("Step", "State of wheelchair", "Predicted action (a)")
        rows = [
            (str(i + 1), f"({a[0]},{a[1]}) to ({b[0]},{b[1]})", m.capitalize())
            for i, (a, b, m) in enumerate(
                zip(res.cells[:-1], res.cells[1:], res.moves, strict=True)
            )
        ]
    widths = [
        max(len(h), *(len(r[i]) for r in rows)) if rows else len(h) for i, h in enumerate(head)
    ]
    lines.append("  ".join(h.ljust(w) for h, w in zip(head, widths, strict=True)).rstrip())
    lines.append("  ".join("-" * w for w in widths))
    lines += ["  ".join(v.ljust(w) for v, w in zip(r, widths, strict=True)).rstrip() for r in rows]
    lines.append(
        f"{len(res.moves)} moves (shortest possible {res.bfs_length}); {res.method}: converged "
        f"after {res.episodes} episodes, {res.seconds * 1000:.1f} ms"
    )
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        cfg = load_yaml(PlannerConfig, args.config, section="planner")
    except (OSError, ValueError) as exc:
        print(f"wheelgrid plan: bad --config: {exc}", file=sys.stderr)
        return 2
    if args.seed is not None:
        cfg.seed = args.seed
    try:
        grid = read_map(args.grid)
    except (OSError, ValueError) as exc:
        print(f"wheelgrid plan: cannot read grid {args.grid}: {exc}", file=sys.stderr)
        return 2
    try:
        start = _cell(grid, args.start, args.start_xy, "start")
        goal = _cell(grid, args.goal, args.goal_xy, "goal")
        res = plan(grid.data, start, goal, cfg, method=args.method, heading=args.heading)
    except PlanInputError as exc:
        print(f"wheelgrid plan: {exc}", file=sys.stderr)
        return 2
    if args.png:
        from wheelgrid_nav.plan_png import save_plan_png

        save_plan_png(args.png, grid.data, res.cells, start, goal)
    if args.json:
        print(json.dumps(result_json(res, args.heading)))
    if res.reason == "unreachable":
        print(
            f"wheelgrid plan: goal {goal} cannot be reached from start {start} over free cells",
            file=sys.stderr,
        )
        return 2
    if not res.ok:
        print(
            f"wheelgrid plan: no route: {res.reason} (no half-learned route is given)",
            file=sys.stderr,
        )
        return 1
    if not args.json:
        print(format_table(res, args.heading))
        if args.png:
            print(f"wrote {Path(args.png)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
