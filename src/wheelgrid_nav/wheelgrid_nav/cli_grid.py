"""``wheelgrid grid MAP.ply --out DIR``: a levelled 3D map -> the safe 2D grid files.

Writes DIR/grid.yaml + grid.pgm (cells, for Nav2's map_server and the planner), DIR/fine.yaml +
fine.pgm (the fine safe obstacle map) and DIR/grid.png (the paper's Fig. 12). A PCD map made
elsewhere is read too, and ``--level`` puts its floor at z = 0 first (DIR/levelling.yaml says
how it was moved). Exit codes: 0 ok, 2 bad input (missing/corrupt PLY or PCD, empty map, no
floor, everything above the safe height, bad config) with one line on stderr, 1 on a failure to
write.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path

from wheelgrid_common import params
from wheelgrid_common.fileio import folder_problem, out_folder, read_cloud
from wheelgrid_nav.grid import (
    GridError,
    GridNodeConfig,
    GridResult,
    build_grid,
    grid_config,
    grid_text,
)
from wheelgrid_nav.level import MAX_TILT_DEG, LevelError, Levelling, level_map


def _parser() -> argparse.ArgumentParser:
    docs = params.cli_help(GridNodeConfig)
    p = argparse.ArgumentParser(
        prog="wheelgrid grid",
        description="Turn a levelled 3D map (PLY or PCD, z up, floor at z = 0) into the safe 2D "
        "grid of wheelchair-sized cells (the paper's section II.B).",
    )
    p.add_argument(
        "map",
        type=Path,
        help="the map: a PLY point cloud (wheelgrid map's map.ply) or a PCL .pcd file",
    )
    p.add_argument(
        "--level",
        action="store_true",
        help="for a z-up map made elsewhere: find its floor (the lowest large level surface) "
        f"and move the map so that it lies flat at z = 0 (a floor leaning over "
        f"{MAX_TILT_DEG:g} deg is refused); DIR/levelling.yaml holds the transform, as the "
        "grid's origin is then in the levelled frame",
    )
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


def levelling_yaml(levelling: Levelling, source: Path) -> str:
    """What ``--level`` did, for relating the grid to the map it came from."""
    import yaml

    return yaml.safe_dump(
        {
            "source": str(source),
            "levelled_from_source": [
                [round(float(v), 9) for v in row] for row in levelling.matrix()
            ],
            "meaning": "levelled = T @ source (homogeneous points, metres): the grid's origin "
            "is in the levelled frame",
            "floor_z_in_source_m": round(levelling.floor_z, 4),
            "tilt_deg": round(levelling.tilt_deg, 3),
            "floor_points": levelling.floor_points,
            "floor_rms_m": round(levelling.rms_m, 4),
        },
        sort_keys=False,
    )


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
        return _fail(f"{args.map}: a folder, not a PLY or PCD map file{hint}")
    if not args.map.is_file():
        return _fail(f"{args.map}: no such map file")
    kind = "PCD" if args.map.suffix.lower() == ".pcd" else "PLY"
    try:
        points = read_cloud(args.map)
    except ModuleNotFoundError:  # open3d not installed: said by `wheelgrid`, not the file
        raise
    except Exception as exc:  # the readers raise several types for corrupt files
        # the readers' own errors name the file and say what is wrong; others get their type
        detail = str(exc).removeprefix(f"{args.map}: ")
        detail = detail if isinstance(exc, ValueError) else f"{type(exc).__name__}: {detail}"
        return _fail(f"{args.map}: not a readable {kind} point cloud: {detail}")
    levelling = None
    if args.level:
        try:
            points, levelling = level_map(points)
        except LevelError as exc:
            return _fail(f"{args.map}: --level: {exc}")
    try:
        result = build_grid(points, gcfg)
    except GridError as exc:
        hint = ""
        if levelling is None and exc.cause in ("no_floor", "all_above_band", "only_floor"):
            hint = " (a map made elsewhere: --level finds its floor and puts it at z = 0)"
        return _fail(f"{args.map}: {exc}{hint}")
    try:
        from wheelgrid_nav.grid_png import write_outputs

        extra = {} if levelling is None else {"levelling.yaml": levelling_yaml(levelling, args.map)}
        files = write_outputs(result, args.out, png=not args.no_png, extra=extra)
    except OSError as exc:
        return _fail(f"cannot write {args.out}: {exc}", 1)
    for doubt in result.stats["warnings"]:
        print(f"wheelgrid grid: warning: {doubt}", file=sys.stderr)
    if levelling is not None and not args.quiet:  # -q: the summary line only (the YAML has it)
        print(levelling.line())
    print(summary(result))
    if not args.quiet:
        print(grid_text(result.grid))
        print("wrote " + " ".join(str(p) for p in files.values()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
