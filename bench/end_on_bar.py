"""How much of a thin bar seen end-on reaches the map: per frame, and fused over an approach.

    python bench/end_on_bar.py

A 5 cm bar 1 m long pointing away from the sensor (a rail, a table's side edge), its axis
along the view, 0.75 m high, 15 cm to the side; floor and a wall 2 m behind it. Depth frames
are ray cast by the simulator's camera (256 x 192, its noise, wild returns and flying pixels)
from 1.0 m height. Two readings, each with no filter and with the default filters
(``PreprocessConfig()``, the mapper's per-frame filtering):

* per frame, the share of the bar's points kept at bar-centre distances of 1-3.5 m (ten
  noise draws: median and range);
* fused: frames every 5 cm of an approach from 3.5 m to 2.4, 1.5 and 1.0 m, at their true
  poses, through the mapper's evidence map (``MapperConfig().evidence_map()``): the bar's
  points in the map and how many of its ten 10 cm stretches hold one.

Found by a review (2026-12-01): the outlier removal (eqs. 1-4), run after the downsampling,
takes most of such a bar 2-3.5 m ahead, where its image is a streak of a few pixels whose rows
lie centimetres apart along it. The README's Map section quotes these figures. Fidelity, not
speed: nothing here is timed, and it is no stage of `make bench`.
"""

from __future__ import annotations

import numpy as np

from wheelgrid_mapping.depth import depth_to_points
from wheelgrid_mapping.pipeline import MapperConfig
from wheelgrid_mapping.preprocess import PreprocessConfig, preprocess_for_map
from wheelgrid_sim.camera import DepthCamera

HEIGHT, RADIUS, SIDE, LENGTH = 0.75, 0.025, 0.15, 1.0
DRAWS = 10  # noise draws of each per-frame reading
CAMERA_HEIGHT = 1.0
#: optical (x right, y down, z ahead) -> world (x ahead, y left, z up)
OPTICAL_TO_WORLD = np.array([[0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0]])
FILTERS = {
    "no filter": PreprocessConfig(enable_sor=False, enable_pfc=False, map_mixed_pixels=False),
    "defaults": PreprocessConfig(),
}

CAM = DepthCamera()
K = CAM.intrinsics()
RAYS = CAM.rays()


def frame(distance: float, seed: int) -> np.ndarray:
    """An organised (H, W, 3) optical-frame cloud with the bar's centre ``distance`` ahead."""
    c = np.array([SIDE, CAMERA_HEIGHT - HEIGHT, distance])
    a = np.array([0.0, 0.0, 1.0])
    d = RAYS
    dp = d - np.outer(d @ a, a)
    wp = -c - (-c @ a) * a
    qa, qb, qc = (dp * dp).sum(1), 2 * dp @ wp, wp @ wp - RADIUS**2
    disc = qb * qb - 4 * qa * qc
    t = np.where(disc >= 0, (-qb - np.sqrt(np.abs(disc))) / (2 * qa), np.inf)
    t = np.where((t > 0) & (np.abs(-c @ a + t * (d @ a)) <= LENGTH / 2), t, np.inf)
    floor = np.where(d[:, 1] > 0, CAMERA_HEIGHT / np.maximum(d[:, 1], 1e-9), np.inf)
    wall = (distance + 2.0) / d[:, 2]
    clean = np.minimum(np.minimum(floor, wall), t).reshape(CAM.rows, CAM.cols)
    z = CAM._corrupt(clean, np.random.default_rng(seed))
    z = np.where(CAM.in_range(z), z, np.nan).astype(np.float32)
    return depth_to_points(z, K).reshape(CAM.rows, CAM.cols, 3)


def on_bar(points: np.ndarray, centre: np.ndarray, axis: np.ndarray) -> np.ndarray:
    """The offsets along the bar of ``points`` within 3 cm of its surface."""
    rel = points - centre
    s = rel @ axis
    perp = np.linalg.norm(rel - np.outer(s, axis), axis=1)
    return s[(perp < RADIUS + 0.03) & (np.abs(s) <= LENGTH / 2)]


def per_frame() -> None:
    centre, axis = np.array([SIDE, CAMERA_HEIGHT - HEIGHT, 0.0]), np.array([0.0, 0.0, 1.0])
    for distance in (1.0, 1.5, 2.0, 2.5, 3.0, 3.5):
        shares, raw = [], []
        for seed in range(DRAWS):
            counts = {}
            for name, cfg in FILTERS.items():
                pts, keep = preprocess_for_map(frame(distance, 100 + seed), cfg)
                kept = pts if keep is None else pts[keep]
                counts[name] = on_bar(kept, centre + np.array([0.0, 0.0, distance]), axis).size
            raw.append(counts["no filter"])
            shares.append(counts["defaults"] / max(counts["no filter"], 1))
        print(
            f"per frame, bar {distance:.1f} m ahead: {np.mean(raw):.1f} points unfiltered, "
            f"kept {100 * np.median(shares):.0f} % (median of {DRAWS} draws; "
            f"{100 * min(shares):.0f}-{100 * max(shares):.0f} %)"
        )


def approach(start: float, end: float, spacing: float = 0.05) -> None:
    distances = np.arange(start, end - 1e-9, -spacing)
    centre, axis = np.array([start, -SIDE, HEIGHT]), np.array([1.0, 0.0, 0.0])
    for name, cfg in FILTERS.items():
        ev = MapperConfig().evidence_map()
        for i, distance in enumerate(distances):
            pts, keep = preprocess_for_map(frame(distance, 100 + i), cfg)
            kept = pts if keep is None else pts[keep]
            sensor = np.array([start - distance, 0.0, CAMERA_HEIGHT])
            ev.add(kept @ OPTICAL_TO_WORLD.T + sensor, sensor)
        s = on_bar(ev.points(up=np.array([0.0, 0.0, 1.0])), centre, axis)
        stretches = np.unique(np.floor((s + LENGTH / 2) / 0.1).astype(int)).size
        print(
            f"map, approach {start:.1f} -> {end:.1f} m ({distances.size} frames), {name}: "
            f"{s.size} bar points, {stretches} of 10 stretches of 10 cm hold one"
        )


def main() -> None:
    per_frame()
    for end in (2.4, 1.5, 1.0):
        approach(3.5, end)


if __name__ == "__main__":
    main()
