"""``wheelgrid plan``: learn and verify a route on a saved safe grid, print it like Table II.

Cells are (row, col) with row 0 the top row of the grid image (the paper's Table II): "down"
is row + 1, "right" is col + 1. Start and goal may also be given in metres in the map frame.
Exit codes: 0 route found and verified; 2 bad input (start/goal outside, occupied or unknown,
goal unreachable, bad flags); 1 training did not converge within its budget (no route given:
a chair never gets a half-learned one).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import math
import re
import sys
from pathlib import Path
from typing import Any

from wheelgrid_common.map_io import (
    CHAIR_GRID_HINT,
    Grid,
    chair_cell_problem,
    grid_identity,
    read_map,
)
from wheelgrid_common.params import describe, load_yaml
from wheelgrid_nav.actions import MOVES, moves_to_actions
from wheelgrid_nav.planner import METHODS, PlanInputError, PlannerConfig, PlanResult, plan

# Options whose value may start with "-" (a negative row/column or map coordinate), and what
# such a value looks like. argparse takes "-0.5,1" for an option (only plain numbers such as
# "-0.5" pass), so these values are attached with "=" before parsing; -inf/-nan are attached
# too, so that the user hears they are not finite rather than "expected one argument".
_COORD_OPTIONS = ("--start", "--goal", "--start-xy", "--goal-xy")
_NEGATIVE_VALUE = re.compile(r"-\s*(?:\d|\.\d|inf|nan)", re.IGNORECASE)


def _attach_negative_values(argv: list[str]) -> list[str]:
    """Rewrite ``--start-xy -0.5,1`` as ``--start-xy=-0.5,1`` (and the same for --goal-xy,
    --start, --goal, or an unambiguous abbreviation argparse would accept) so a negative
    coordinate is read as the option's value. Anything after ``--`` is left alone."""
    out: list[str] = []
    i = 0
    while i < len(argv):
        tok = argv[i]
        if tok == "--":
            out += argv[i:]
            break
        if (
            i + 1 < len(argv)
            and len(tok) > 2
            and tok.startswith("--")
            and "=" not in tok
            and any(opt.startswith(tok) for opt in _COORD_OPTIONS)
            and _NEGATIVE_VALUE.match(argv[i + 1])
        ):
            out.append(f"{tok}={argv[i + 1]}")
            i += 2
            continue
        out.append(tok)
        i += 1
    return out


def _pair(text: str, kind: type, what: str) -> tuple[Any, Any]:
    parts = text.replace(" ", "").split(",")
    if len(parts) != 2:
        raise PlanInputError(f"{what} must be two comma-separated numbers, got {text!r}")
    try:
        a, b = kind(parts[0]), kind(parts[1])
    except ValueError:
        raise PlanInputError(f"{what}: cannot read {text!r} as two {kind.__name__}s") from None
    # float() accepts "nan" and "inf"; a cell computed from them is garbage (numpy casts NaN
    # to INT_MIN), so refuse them here with the value the user typed
    if kind is float:
        for value, raw in ((a, parts[0]), (b, parts[1])):
            if not math.isfinite(value):
                raise PlanInputError(f"{what}: coordinate {raw!r} is not finite")
    return a, b


def _cell(grid: Grid, rc: str | None, xy: str | None, what: str) -> tuple[int, int]:
    if (rc is None) == (xy is None):
        raise PlanInputError(f"give exactly one of --{what} R,C or --{what}-xy X,Y")
    if rc is not None:
        return _pair(rc, int, f"--{what}")
    x, y = _pair(str(xy), float, f"--{what}-xy")
    # No point of the grid is farther from its origin than rows + cols cells. Refusing farther
    # points here also keeps huge values (1e300) away from the float -> int cast in cell_of,
    # which would overflow into a bogus cell number.
    x0, y0 = grid.origin[0], grid.origin[1]
    if not math.hypot(x - x0, y - y0) <= (grid.rows + grid.cols) * grid.resolution:
        raise PlanInputError(
            f"--{what}-xy ({x:g}, {y:g}) m is outside the {grid.rows}x{grid.cols} grid"
        )
    return grid.cell_of(x, y)


def _png_problem(path: str) -> str | None:
    """Why ``--png PATH`` cannot be written, checked before any training; None if it can."""
    target = Path(path)
    if target.is_dir():
        return f"{path} is a directory"
    if not target.parent.is_dir():
        return f"directory {target.parent} does not exist"
    if target.is_file():
        # it is replaced, or removed when the plan is refused: never a file that is no
        # picture (`--png grid.yaml`, a slip of the hand, would have taken the grid)
        try:
            with target.open("rb") as fh:
                head = fh.read(8)
        except OSError as exc:
            return f"{path}: {exc}"
        if head != b"\x89PNG\r\n\x1a\n":
            return f"{path} exists and is not a PNG picture: not replaced"
        from wheelgrid_nav.plan_png import is_plan_png

        if not is_plan_png(path):
            # a plan that succeeded replaced `wheelgrid grid`'s Fig. 12 picture with its
            # route's (a review), and a map's own PNG image would have gone the same way
            return (
                f"{path} is a picture `wheelgrid plan` did not write (grid.png, a map's image?): "
                "not replaced"
            )
    return None


def _refused(png: str | None) -> int:
    """Exit 2 for a plan refused, and an earlier plan's picture at ``png`` removed: it showed
    another route under the name asked for (a review). Only a picture this command wrote (its
    text chunk says so): removing any PNG there took `wheelgrid grid`'s Fig. 12 picture, and
    a map's own PNG image before the map was read (a review)."""
    from wheelgrid_nav.plan_png import is_plan_png

    if png and is_plan_png(png):
        with contextlib.suppress(OSError):  # the refusal is said either way
            Path(png).unlink()
    return 2


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
    p.add_argument(
        "--heading",
        choices=MOVES,
        help="the chair's heading on the grid at the start; with it, "
        "the route also gets the Table II actions (default: none, moves only)",
    )
    p.add_argument("--method", choices=METHODS, default="qlearning", help="default qlearning")
    p.add_argument("--seed", type=int, help="random seed (overrides the config's)")
    p.add_argument("--config", help="YAML with PlannerConfig fields")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--png", metavar="FILE", help="write the grid with the route as a PNG")
    return p


def result_json(res: PlanResult, heading: str | None, grid: Any = None) -> dict[str, Any]:
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
        # -1 is "unreachable"; a search the time budget cut off found no length: null
        "shortest_moves": res.bfs_length
        if res.bfs_length >= 0 or res.reason == "unreachable"
        else None,
    }
    if heading is not None:
        out["heading"] = heading
        out["actions"] = moves_to_actions(res.cells, heading) if res.cells else []
    if grid is not None:
        out["grid"] = grid_identity(grid)
    return out


def format_table(res: PlanResult, heading: str | None) -> str:
    """A readable table; with a heading it has the paper's Table II columns."""
    lines = []
    head: tuple[str, ...]
    rows: list[tuple[str, ...]]
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
    argv = sys.argv[1:] if argv is None else list(argv)
    args = build_parser().parse_args(_attach_negative_values(argv))
    try:
        cfg = load_yaml(PlannerConfig, args.config, section="planner")
    except (OSError, ValueError) as exc:
        print(f"wheelgrid plan: bad --config: {exc}", file=sys.stderr)
        return _refused(args.png)
    if args.seed is not None:
        cfg.seed = args.seed
    if args.png and (problem := _png_problem(args.png)):
        print(f"wheelgrid plan: cannot write --png: {problem}", file=sys.stderr)
        return 2
    try:
        grid = read_map(args.grid)
    except (OSError, ValueError) as exc:
        print(f"wheelgrid plan: cannot read grid {args.grid}: {exc}", file=sys.stderr)
        return _refused(args.png)
    if problem := chair_cell_problem(grid.resolution):
        print(f"wheelgrid plan: {args.grid}: {problem}; {CHAIR_GRID_HINT}", file=sys.stderr)
        return _refused(args.png)
    try:
        start = _cell(grid, args.start, args.start_xy, "start")
        goal = _cell(grid, args.goal, args.goal_xy, "goal")
        res = plan(grid.data, start, goal, cfg, method=args.method, heading=args.heading)
    except PlanInputError as exc:
        print(f"wheelgrid plan: {exc}", file=sys.stderr)
        return _refused(args.png)
    if args.png:
        from wheelgrid_nav.plan_png import plan_caption, save_plan_png

        try:
            words = plan_caption(res.cells, start, goal, res.reason)
            save_plan_png(args.png, grid.data, res.cells, start, goal, caption=words)
        except OSError as exc:  # e.g. no permission: the early check cannot foresee all
            print(f"wheelgrid plan: cannot write --png {args.png}: {exc}", file=sys.stderr)
            return 2
    if args.json:
        print(json.dumps(result_json(res, args.heading, grid)))
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
