"""Peak memory of the map rebuild after loop closure, against the number of kept frames.

    python bench/rebuild_memory.py [--repeats 4 8 16]

``Mapper.close_loops`` rebuilds the map from every kept frame at its corrected pose. The first
150 frames of the bundled bag are mapped once (with their ARKit-like prior); their kept frames,
repeated N times, stand for a longer scan, and each N is rebuilt in a fresh process, whose peak
resident memory (VmHWM, reset just before the rebuild) is read against its memory before it.
The rebuild merged every frame only at the end, and peaked at ~0.9 MB a kept frame (a review);
merged a million points at a time, it stays near the map's own size. Memory and time, not
fidelity: it is no stage of `make bench` (bench/run_all.py runs the bench_*.py scripts).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

BAG = Path(__file__).resolve().parent.parent / "bags" / "paper_room" / "scan"
FRAMES = 150


def _status(key: str) -> int:
    """A /proc/self/status figure in MiB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1]) // 1024
    raise KeyError(key)


def rebuild(repeats: int) -> str:
    from wheelgrid_common.bagio import BagReader
    from wheelgrid_common.pointcloud2 import read_xyz
    from wheelgrid_mapping.cli_map import _odometry_poses
    from wheelgrid_mapping.pipeline import Mapper, transform

    mapper = Mapper(keep_frames=True)
    with BagReader(BAG) as bag:
        prior_stamps, prior_poses = _odometry_poses(bag, "/iphone/odometry")
        for i, (_, _, msg) in enumerate(bag.messages(["/iphone/points"])):
            if i >= FRAMES:
                break
            stamp = msg.header.stamp.sec + msg.header.stamp.nanosec * 1e-9
            xyz = read_xyz(msg, drop_invalid=False).reshape(msg.height, msg.width, 3)
            prior = prior_poses[int(np.argmin(np.abs(prior_stamps - stamp)))]
            mapper.add_frame(xyz, stamp, msg.header.frame_id, prior=prior)
    frames = list(mapper.frames) * repeats
    keeps = list(mapper._map_keep) * repeats
    poses = list(mapper.poses_odom) * repeats
    Path("/proc/self/clear_refs").write_text("5")  # VmHWM from here on
    before = _status("VmRSS")
    t0 = time.perf_counter()
    evidence = mapper.cfg.evidence_map()
    for pts, keep, pose in zip(frames, keeps, poses, strict=True):
        kept = pts if keep is None else pts[keep]
        evidence.add(transform(kept.astype(np.float64), pose), pose[:3, 3])
    points = evidence.points()
    seconds = time.perf_counter() - t0
    peak = _status("VmHWM")
    kept_mib = sum(f.nbytes for f in frames) / 2**20
    return (
        f"{len(frames):5d} kept frames ({kept_mib:.0f} MiB): the rebuild adds "
        f"{peak - before} MiB at its peak (VmHWM {peak} MiB), {seconds:.1f} s, "
        f"{points.shape[0]} map points"
    )


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--repeats", type=int, nargs="+", default=[4, 8, 16])
    p.add_argument("--one", type=int, help=argparse.SUPPRESS)  # the child's own run
    args = p.parse_args(argv)
    if args.one:
        print(rebuild(args.one), flush=True)
        return 0
    for n in args.repeats:  # a fresh process each: one's peak must not hide the next's
        run = subprocess.run(
            [sys.executable, __file__, "--one", str(n)], capture_output=True, text=True
        )
        print(run.stdout.strip() or run.stderr.strip().splitlines()[-1], flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
