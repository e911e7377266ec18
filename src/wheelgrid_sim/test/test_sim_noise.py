"""The depth error model: range-dependent noise, ~1 % outliers, flying pixels, NaN holes."""

from __future__ import annotations

import math

import numpy as np

from wheelgrid_sim import Box, DepthCamera, Scene, camera_pose
from wheelgrid_sim.scene import shell_boxes


def wall_scene(distance: float) -> tuple[Scene, np.ndarray]:
    """A camera at x = 1 m facing the east wall ``distance`` metres away, head on."""
    room = (0.0, 0.0, 1.0 + distance, 12.0)
    scene = Scene(room=room, boxes=shell_boxes(room, ceiling=8.0), name="wall", ceiling=8.0)
    return scene, camera_pose(1.0, 6.0, 4.0, yaw=0.0, pitch=0.0)


def test_noise_std_matches_the_model_and_grows_with_range() -> None:
    cam = DepthCamera(outlier_fraction=0.0, flying_probability=0.0)
    rng = np.random.default_rng(1)
    stds = []
    for dist in (1.0, 2.5, 4.0):
        scene, T = wall_scene(dist)
        errs = np.concatenate(
            [(cam.render(scene, T, rng) - dist).ravel() for _ in range(3)]
        ).astype(np.float64)
        errs = errs[np.isfinite(errs)]
        assert errs.size > 100_000
        std = float(np.std(errs))
        assert abs(float(np.mean(errs))) < 0.05 * std + 1e-4  # unbiased
        assert abs(std / float(cam.sigma(dist)) - 1.0) < 0.03
        stds.append(std)
    assert stds[0] < stds[1] < stds[2]
    assert stds[2] > 5 * stds[0]


def test_outlier_fraction_is_about_one_percent() -> None:
    cam = DepthCamera(flying_probability=0.0)
    scene, T = wall_scene(2.0)
    rng = np.random.default_rng(2)
    wild = total = 0
    for _ in range(4):
        err = cam.render(scene, T, rng).astype(np.float64) - 2.0
        finite = np.isfinite(err)
        total += int(finite.sum())
        wild += int((np.abs(err[finite]) > 8 * cam.sigma(2.0)).sum())
    frac = wild / total
    # Uniform outliers in [0.2, 5] m: ~93 % of them land > 8 sigma from the wall.
    assert 0.007 < frac < 0.012, frac


def test_flying_pixels_sit_between_foreground_and_background_at_edges_only() -> None:
    scene, T = wall_scene(4.0)  # wall at 4 m
    scene.boxes.append(Box("panel", "pillar", (2.0, 5.0, 0.0), (2.2, 6.0, 8.0)))  # 1 m ahead
    clean = DepthCamera().render(scene, T, noise=False)
    cam = DepthCamera(outlier_fraction=0.0, noise_base=1e-4, noise_quad=0.0)
    noisy = cam.render(scene, T, np.random.default_rng(3))
    between = (noisy > 1.05) & (noisy < 3.95)
    assert between.sum() > 20  # the panel's silhouette column produces mixed depths
    # Every mixed pixel is next to a depth jump of the noise-free image.
    jump = np.zeros_like(clean, dtype=bool)
    jump[:, 1:] |= np.abs(np.diff(clean, axis=1)) > 1.0
    jump[:, :-1] |= np.abs(np.diff(clean, axis=1)) > 1.0
    assert jump[between].all()
    # Away from edges the noise stays tiny.
    far = ~jump & np.isfinite(noisy)
    assert np.nanmax(np.abs(noisy[far] - clean[far])) < 1e-3


def test_no_return_beyond_range_is_nan_and_noise_free_render_is_exact() -> None:
    cam = DepthCamera()
    scene, T = wall_scene(7.0)
    depth = cam.render(scene, T, np.random.default_rng(4))
    row = depth[cam.rows // 2]
    # Only outliers (~1 %) can return anything from a wall beyond 5 m.
    assert np.isnan(row).mean() > 0.95
    scene2, T2 = wall_scene(3.0)
    exact = cam.render(scene2, T2, noise=False)
    assert float(np.nanmax(np.abs(exact[cam.rows // 2] - 3.0))) < 1e-6


def test_render_is_reproducible_for_a_seed() -> None:
    cam = DepthCamera(stride=4)
    scene, T = wall_scene(2.0)
    T = camera_pose(1.0, 6.0, 1.0, yaw=0.3, pitch=math.radians(20))
    a = cam.render(scene, T, np.random.default_rng(9))
    b = cam.render(scene, T, np.random.default_rng(9))
    np.testing.assert_array_equal(a, b)
