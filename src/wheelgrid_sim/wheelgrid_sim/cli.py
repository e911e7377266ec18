"""``wheelgrid simulate``: write a synthetic iPhone-LiDAR scan bag with its ground truth."""

from __future__ import annotations

import argparse
import contextlib
import sys

from wheelgrid_common.bagio import BagError
from wheelgrid_common.fileio import folder_problem, out_folder
from wheelgrid_common.progress import Progress
from wheelgrid_sim.simulate import make_scene, simulate
from wheelgrid_sim.trajectory import SPEED, nominal_duration, nominal_frames

CHAIR_SPEED = 3.0 / 3.6  # m/s: the paper's chair drives at <= 3 km/h
MAX_RATE_HZ = 1000.0  # a depth camera's frame rate; inf ended in an OverflowError traceback
MIN_RATE_HZ = 1e-3  # a frame every 17 minutes; 1e-300 overflowed the stamps (exit 1)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wheelgrid simulate",
        description=(
            "Ray-cast a synthetic room with an ARKit-like depth camera along a wheelchair-like "
            "trajectory; write DIR/scan (rosbag2, /iphone/points) and the exact ground truth "
            "(scene.json, poses.tum, poses_map.tum, truth.json, expected_grid.yaml/.pgm)."
        ),
    )
    p.add_argument(
        "--out",
        type=out_folder,
        required=True,
        metavar="DIR",
        help="output folder (DIR/scan must not exist yet)",
    )
    p.add_argument(
        "--seed", type=int, default=7, help="noise, trajectory and random-scene seed (default 7)"
    )
    p.add_argument(
        "--frames",
        type=int,
        default=None,
        help="number of depth frames; the whole path is spread over them, so fewer frames "
        "drive faster (default: the path at 0.8 m/s, 210 frames at 5 Hz in the paper room)",
    )
    p.add_argument("--rate", type=float, default=5.0, help="frame rate in Hz (default 5)")
    p.add_argument(
        "--scene",
        choices=("paper", "random"),
        default="paper",
        help="paper: the paper's 9.6 m room (default); random: a random room",
    )
    p.add_argument(
        "--stride",
        type=int,
        default=1,
        help="keep every N-th pixel of the 256x192 depth map (default 1)",
    )
    p.add_argument(
        "--storage",
        choices=("sqlite3", "mcap"),
        default="sqlite3",
        help="rosbag2 storage plugin (default sqlite3)",
    )
    p.add_argument(
        "--back-to-start",
        action="store_true",
        help="drive on to where the path began and turn to the heading it began with, so the "
        "scan closes its loop (the paper room: 371 frames, 74 s, not 210 and 42); the hand's "
        "+-35 deg sweep and the height's wander go on, so the last view can be that far off "
        "the first (paper room: 32 deg)",
    )
    p.add_argument(
        "--no-odometry",
        action="store_true",
        help="leave out /iphone/odometry (the ARKit-like pose with drift)",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.frames is not None and args.frames < 1:
        print("wheelgrid simulate: --frames must be >= 1", file=sys.stderr)
        return 2
    if not MIN_RATE_HZ <= args.rate <= MAX_RATE_HZ:
        # 1e-300 passed, and the frames' stamps overflowed: "failed", exit 1 (a review)
        print(
            f"wheelgrid simulate: --rate must be in [{MIN_RATE_HZ:g}, {MAX_RATE_HZ:g}] Hz, not "
            f"{args.rate}",
            file=sys.stderr,
        )
        return 2
    if args.seed < 0:  # a random room's traceback, the paper room's words without the flag
        print(f"wheelgrid simulate: --seed must be >= 0, not {args.seed}", file=sys.stderr)
        return 2
    nominal = nominal_duration(make_scene(args.scene, args.seed), args.back_to_start)  # s
    at_speed = nominal_frames(nominal, args.rate)
    if args.frames is None:
        args.frames = at_speed
    # one frame stands at the start: it drives nothing
    speed = SPEED * nominal * args.rate / (args.frames - 1) if args.frames > 1 else 0.0
    if not 1 <= args.stride <= 32:
        print("wheelgrid simulate: --stride must be in 1..32", file=sys.stderr)
        return 2
    made = not args.out.exists()
    why = folder_problem(args.out)  # bad input, before any frame: exit 2, not a failure
    if why:
        print(f"wheelgrid simulate: {why}", file=sys.stderr)
        return 2
    bar = Progress(args.frames, "simulate", unit="frames")

    def remove_made() -> None:
        # simulate() takes back what it wrote, but folder_problem made --out before it
        # looked, so the empty folder stayed (and "removed" was not quite true)
        if made:
            with contextlib.suppress(OSError):
                args.out.rmdir()

    try:
        res = simulate(
            args.out,
            seed=args.seed,
            frames=args.frames,
            rate=args.rate,
            scene=args.scene,
            stride=args.stride,
            storage=args.storage,
            odometry=not args.no_odometry,
            on_frame=lambda _i: bar.update(),
            back_to_start=args.back_to_start,
        )
    except (BagError, ValueError) as exc:
        bar.close()
        remove_made()
        print(f"wheelgrid simulate: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        bar.close()
        remove_made()
        print("wheelgrid simulate: interrupted; what it wrote is removed", file=sys.stderr)
        return 130
    except Exception as exc:  # a full disk: OSError, or sqlite3's OperationalError (a traceback)
        bar.close()
        remove_made()
        if isinstance(exc, ModuleNotFoundError):  # rosbags not installed: said by `wheelgrid`
            raise
        print(
            f"wheelgrid simulate: failed ({type(exc).__name__}: {exc}); what it wrote is removed",
            file=sys.stderr,
        )
        return 1
    bar.close()
    rows, cols = res.grid_shape
    topics = "/iphone/points" + ("" if args.no_odometry else " + /iphone/odometry")
    if speed > CHAIR_SPEED:
        print(
            f"wheelgrid simulate: warning: {res.frames} frames at {args.rate:g} Hz drive the path "
            f"at {speed:.2f} m/s, faster than a chair's 3 km/h ({CHAIR_SPEED:.2f} m/s); the "
            f"mapper refuses steps over registration.max_speed. --frames "
            f"{at_speed} drives it at {SPEED:g} m/s",
            file=sys.stderr,
        )
    print(
        f"wrote {res.frames} frames ({args.rate:g} Hz, {res.frames / args.rate:.1f} s, "
        f"driving {speed:.2f} m/s, "
        f"{res.points_per_frame} points/frame, {100 * res.valid_fraction:.0f} % valid) to "
        f"{res.bag} ({args.storage}, {res.bag_bytes / 1e6:.1f} MB, {topics}) + ground truth "
        f"({rows}x{cols} grid of 1.2 m cells, {res.occupied_cells} occupied) in "
        f"{res.seconds:.1f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
