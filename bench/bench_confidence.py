"""ARKit confidence on the real capture: which pixels it marks low, and what ``min_confidence`` does
to the map and the safe grid.

Why: every iPhone path (the bridge, ``depth_to_cloud``, ``wheelgrid map`` on a Stray export)
drops pixels below ``min_confidence`` (default 1: low goes, medium and high stay), and the
simulator has no confidence channel, so only the real capture can say whether that default is
right. Figures (printed, and with ``--json FILE`` as ``{"rows": [...]}``):

* per pixel class, the share ARKit calls low / medium / high: pixels at a depth edge (a
  4-neighbour more than 8 cm + 3 % of the depth away: where flying pixels are), on its near
  (foreground) or far (background) side, and the other pixels by range;
* the capture mapped (ARKit prior, a keyframe every 0.1 s, loop closure) with
  ``min_confidence`` 0, 1 and 2: map points, time, points more than 5 cm below the floor (none
  can be real), and the fine safe map's occupied / free / unknown area.

Run: ``python bench/bench_confidence.py [--quick] [--json out.json]``; skipped (no rows) when
``../shared/data/stray-iphone-room`` is absent.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
from bench_mapping import LOOP_OVERRIDES, MAPPER_OVERRIDES, ROWS, SHARED, row, run_mapper

from wheelgrid_common.map_io import FREE, OCCUPIED, UNKNOWN
from wheelgrid_mapping.cli_map import stray_frames
from wheelgrid_mapping.loop_closure import LoopClosureConfig
from wheelgrid_mapping.pipeline import MapperConfig
from wheelgrid_mapping.preprocess import PreprocessConfig
from wheelgrid_mapping.registration import RegistrationConfig
from wheelgrid_mapping.stray import StrayExport
from wheelgrid_nav.grid import build_grid
from wheelgrid_sim.camera import DepthCamera

STRAY = SHARED / "data" / "stray-iphone-room"
LEVELS = ("low", "medium", "high")


def edge_classes(depth: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(valid, near side of an edge, far side of an edge) masks of a depth image (m, NaN = none).

    The simulator's own edge test (:meth:`DepthCamera.edges`, where it puts flying pixels), with
    its range opened to the whole capture (seen: 0.46-6.3 m), so the shares below say what a
    real phone's confidence does to those pixels.
    """
    edge, nb = DepthCamera(min_range=0.01, max_range=100.0).edges(depth)
    with np.errstate(invalid="ignore"):
        near, far = edge & (nb > depth), edge & (nb < depth)
    return np.isfinite(depth), near, far


def pixel_shares(export: StrayExport, step: int) -> None:
    spans = {
        "other, 0-2 m": (0.0, 2.0),
        "other, 2-4 m": (2.0, 4.0),
        "other, beyond 4 m": (4.0, np.inf),
    }
    counts: dict[str, np.ndarray] = {}
    for i in range(0, len(export), step):
        fr = export.frame(i)
        if fr.confidence is None:
            print("confidence: this export has no confidence images, skipped")
            return
        depth = np.where(fr.depth > 0, fr.depth, np.nan)  # NaN (and any 0) = no return
        valid, near, far = edge_classes(depth)
        conf = fr.confidence.astype(np.int64)
        other = valid & ~near & ~far
        z = np.nan_to_num(depth)
        masks = {"edge, near side": near, "edge, far side": far}
        masks |= {name: other & (z >= lo) & (z < hi) for name, (lo, hi) in spans.items()}
        for name, mask in masks.items():
            c = np.bincount(np.clip(conf[mask], 0, 2), minlength=3)
            counts[name] = counts.get(name, np.zeros(3, dtype=np.int64)) + c
    for name, c in counts.items():
        total = max(int(c.sum()), 1)
        for level, n in zip(LEVELS, c, strict=True):
            row(f"real capture, {name}: pixels ARKit calls {level}", 100.0 * n / total, "%")


def mapped(min_confidence: int, limit: int, interval: float) -> None:
    total, frames = stray_frames(STRAY, True)
    cfg = MapperConfig(min_frame_interval=interval, **MAPPER_OVERRIDES)
    t0 = time.perf_counter()
    m = run_mapper(
        frames,
        min(total, limit),
        RegistrationConfig(),
        cfg,
        keep=True,
        pre=PreprocessConfig(min_confidence=min_confidence),
    )
    m.close_loops(LoopClosureConfig(**LOOP_OVERRIDES))
    wall = time.perf_counter() - t0
    pts = m.map_points()
    label = f"real capture, min_confidence {min_confidence}"
    row(f"{label}: map points", float(pts.shape[0]), "points")
    row(f"{label}: mapping time (with loop closure)", wall, "s")
    row(f"{label}: map points > 5 cm below the floor", 100.0 * np.mean(pts[:, 2] < -0.05), "%")
    fine = build_grid(pts).fine
    px = fine.resolution**2
    for name, value in (("occupied", OCCUPIED), ("free", FREE), ("unknown", UNKNOWN)):
        row(f"{label}: fine safe map {name}", float((fine.data == value).sum()) * px, "m2")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer frames")
    ap.add_argument("--json", type=Path, help="write the rows as JSON")
    args = ap.parse_args(argv)
    if not STRAY.exists():
        print(f"confidence: {STRAY} not present, skipped")
    else:
        export = StrayExport(STRAY)
        pixel_shares(export, 50 if args.quick else 10)
        for level in (0, 1, 2):
            mapped(level, 100 if args.quick else 10_000, 0.1)
    if args.json:
        args.json.write_text(json.dumps({"rows": ROWS}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
