"""``wheelgrid grid MAP.ply --out DIR``: a levelled 3D map -> the safe 2D grid files.

Writes DIR/grid.yaml + grid.pgm (cells, for Nav2's map_server and the planner), DIR/fine.yaml +
fine.pgm (the fine safe obstacle map) and DIR/grid.png (the paper's Fig. 12). Exit codes: 0 ok,
2 bad input (missing/corrupt PLY, empty map, no floor, everything above the safe height, bad
config) with one line on stderr, 1 on a failure to write.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from wheelgrid_common import params
from wheelgrid_common.fileio import folder_problem, out_folder, read_ply
from wheelgrid_nav.grid import (
    GridError,
    GridNodeConfig,
    GridResult,
    build_grid,
    grid_config,
    grid_text,
)


def _parser() -> argparse.ArgumentParser:
    docs = params.cli_help(GridNodeConfig)
    p = argparse.ArgumentParser(
        prog="wheelgrid grid",
        description="Turn a levelled 3D map (PLY, z up, floor at z = 0) into the safe 2D grid "
        "of wheelchair-sized cells (the paper's section II.B).",
    )
    p.add_argument("map", type=Path, help="the map: a PLY point cloud (wheelgrid map's map.ply)")
    p.add_argument("--out", type=out_folder, required=True, help="output folder")
    p.add_argument("--safe-height", type=float, help=docs["safe_height"])
    p.add_argument("--cell-size", type=float, help=docs["cell_size"])
    p.add_argument("--density-threshold", type=float, help=docs["density_threshold"])
    p.add_argument("--pixel-size", type=float, help=docs["pixel_size"])
    p.add_argument("--alignment", choices=("walls", "map"), help=docs["alignment"])
    p.add_argument(
        "--config",
        type=Path,
        help="YAML with grid parameters (plain mapping, a 'grid:' section, or a ROS params file)",
    )
    p.add_argument(
        "--no-png",
        action="store_true",
        help="skip grid.png (an older grid.png in --out is removed: it shows another grid)",
    )
    p.add_argument("-q", "--quiet", action="store_true", help="print only the summary line")
    return p


def _fail(msg: str, code: int = 2) -> int:
    print(f"wheelgrid grid: {msg}", file=sys.stderr)
    return code


def summary(result: GridResult) -> str:
    g, st = result.grid, result.stats
    return (
        f"{st['map_points']} map points ({st['points']} up to the safe height) -> "
        f"{g.rows} x {g.cols} cells of {g.resolution:g} m "
        f"(yaw {st['yaw_deg']:.2f} deg, origin {g.origin[0]:.3f} {g.origin[1]:.3f} m): "
        f"{st['occupied']} occupied, {st['free']} free, {st['unknown']} unknown"
    )


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    try:
        cfg = params.load_yaml(GridNodeConfig, args.config, section="grid")
        overrides = {
            "safe_height": args.safe_height,
            "cell_size": args.cell_size,
            "density_threshold": args.density_threshold,
            "pixel_size": args.pixel_size,
            "alignment": args.alignment,
        }
        cfg = dataclasses.replace(cfg, **{k: v for k, v in overrides.items() if v is not None})
        gcfg = grid_config(cfg)
        gcfg.validate()
    except (OSError, ValueError) as exc:
        return _fail(f"bad config: {exc}")
    # before the work: a grid built and then not saved cost the user the wait for nothing
    problem = folder_problem(args.out)
    if problem:
        return _fail(f"--out {args.out}: {problem}")
    if args.map.is_dir():
        inside = args.map / "map.ply"
        hint = f"; `wheelgrid map --out` wrote {inside}" if inside.is_file() else ""
        return _fail(f"{args.map}: a folder, not a PLY map file{hint}")
    if not args.map.is_file():
        return _fail(f"{args.map}: no such map file")
    try:
        points = read_ply(args.map)
    except Exception as exc:  # read_ply raises several types for corrupt files
        return _fail(f"{args.map}: not a readable PLY point cloud ({type(exc).__name__}: {exc})")
    try:
        result = build_grid(points, gcfg)
    except GridError as exc:
        return _fail(f"{args.map}: {exc}")
    try:
        from wheelgrid_nav.grid_png import write_outputs

        files = write_outputs(result, args.out, png=not args.no_png)
    except OSError as exc:
        return _fail(f"cannot write {args.out}: {exc}", 1)
    for doubt in result.stats["warnings"]:
        print(f"wheelgrid grid: warning: {doubt}", file=sys.stderr)
    print(summary(result))
    if not args.quiet:
        print(grid_text(result.grid))
        print("wrote " + " ".join(str(p) for p in files.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
