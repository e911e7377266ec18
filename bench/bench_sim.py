"""Benchmark of the simulator: depth rendering per frame and whole bag writing.

    python bench/bench_sim.py [--quick] [--json FILE]

Figures:

* render time of one full 256x192 frame (noise on) in the paper scene padded to 60 boxes,
  against a baseline measured in the same process: the plain float64 slab test over ALL boxes
  with no culling (what the renderer did first) -- the ratio is the speed-up;
* ``simulate`` throughput (frames/s) for the bundled bag's settings (stride 3, 210 frames;
  ``--quick``: 40 frames) and the resulting bag size per frame.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from wheelgrid_sim import Box, DepthCamera, make_trajectory, paper_scene, simulate


def baseline_raycast(origin: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """The unculled float64 slab test over every box (reference implementation)."""
    inv = 1.0 / np.where(np.abs(d) < 1e-12, 1e-12, d)
    tnear = np.full((d.shape[0], lo.shape[0]), -np.inf)
    tfar = np.full_like(tnear, np.inf)
    for k in range(3):
        ta = np.multiply.outer(inv[:, k], lo[:, k] - origin[k])
        tb = np.multiply.outer(inv[:, k], hi[:, k] - origin[k])
        np.maximum(tnear, np.minimum(ta, tb), out=tnear)
        np.minimum(tfar, np.maximum(ta, tb), out=tfar)
    np.where((tnear <= tfar) & (tnear > 0), tnear, np.inf).min(axis=1)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="CI-size run")
    ap.add_argument("--json", type=Path, help="write the rows as JSON here")
    args = ap.parse_args(argv)

    scene = paper_scene()
    rng = np.random.default_rng(0)
    while len(scene.boxes) < 60:
        x, y = rng.uniform(1.0, 8.0, 2)
        scene.boxes.append(Box("clutter", "pillar", (x, y, 0.0), (x + 0.1, y + 0.1, 0.5)))
    cam = DepthCamera()
    n = 8 if args.quick else 30
    _, poses = make_trajectory(scene, n, 5.0, 1)
    lo, hi = scene.box_arrays()
    noise_rng = np.random.default_rng(1)
    ours, base = [], []
    for T in poses:
        t0 = time.perf_counter()
        cam.render(scene, T, noise_rng)
        ours.append(time.perf_counter() - t0)
        t0 = time.perf_counter()
        baseline_raycast(T[:3, 3], cam.rays() @ T[:3, :3].T, lo, hi)
        base.append(time.perf_counter() - t0)
    render_ms, base_ms = 1e3 * statistics.median(ours), 1e3 * statistics.median(base)

    frames = 40 if args.quick else 210
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        res = simulate(Path(tmp) / "s", seed=7, frames=frames, rate=5.0, stride=3)
        wall = time.perf_counter() - t0
    fps = frames / wall
    kb_per_frame = res.bag_bytes / frames / 1e3

    rows = [
        {
            "figure": "sim render 256x192 frame, 60 boxes, noise on (median)",
            "value": round(render_ms, 1),
            "unit": "ms",
            "baseline": round(base_ms, 1),
            "ratio": round(base_ms / render_ms, 2),
            "note": "baseline: unculled float64 slab test only (no noise)",
        },
        {
            "figure": f"sim simulate paper scene, stride 3, {frames} frames",
            "value": round(fps, 1),
            "unit": "frames/s",
            "baseline": None,
            "ratio": None,
            "note": f"{kb_per_frame:.0f} kB/frame in the bag (points + odometry)",
        },
    ]
    for r in rows:
        extra = (
            f" (baseline {r['baseline']} {r['unit']}, ratio {r['ratio']})" if r["baseline"] else ""
        )
        print(f"{r['figure']}: {r['value']} {r['unit']}{extra}; {r['note']}")
    if args.json:
        args.json.write_text(json.dumps({"rows": rows}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
