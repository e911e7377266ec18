"""The mixed-pixel test on organised clouds, against the simulator's own depth camera.

The simulator corrupts depth the way a time-of-flight sensor does: half the pixels at a depth
edge return a range mixed between the foreground's and the background's. Those points fill the
shadow behind a thin post, where no ray of that view passes to carve them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from wheelgrid_mapping.pipeline import Mapper, MapperConfig, prepare_frame
from wheelgrid_mapping.preprocess import (
    PreprocessConfig,
    median_angle,
    mixed_pixel_mask,
    preprocess,
    preprocess_for_map,
)
from wheelgrid_mapping.registration import RegistrationConfig
from wheelgrid_mapping.se3 import transform
from wheelgrid_sim.camera import DepthCamera, depth_to_points
from wheelgrid_sim.scene import Box, Scene
from wheelgrid_sim.trajectory import camera_pose

POST = ((1.50, -0.025, 0.0), (1.55, 0.025, 1.5))  # a 5 cm post, 2.5 m in front of the wall
BAR = ((3.0, 0.4, 0.72), (3.05, 1.4, 0.77))  # a 5 cm bar across the view, Barrier 1's height


def scene() -> Scene:
    return Scene(
        room=(0.0, -1.5, 4.0, 1.5),
        boxes=[
            Box("floor", "floor", (-0.2, -1.7, -0.2), (4.2, 1.7, 0.0)),
            Box("wall", "wall", (4.0, -1.7, 0.0), (4.2, 1.7, 2.7)),
            Box("post", "post", *POST),
            Box("bar", "bar", *BAR),
        ],
    )


def inside(pts: np.ndarray, box: tuple, pad: float) -> np.ndarray:
    lo, hi = np.asarray(box[0]) - pad, np.asarray(box[1]) + pad
    return (pts >= lo).all(axis=1) & (pts <= hi).all(axis=1)


@pytest.fixture(scope="module")
def views() -> list[tuple[np.ndarray, np.ndarray]]:
    """Organised (H, W, 3) optical-frame clouds and their room_from_optical poses, from the
    simulator's noisy camera (flying pixels, range noise, wild returns)."""
    cam, sc, rng = DepthCamera(), scene(), np.random.default_rng(5)
    out = []
    for y in (-0.3, -0.1, 0.1, 0.3):
        T = camera_pose(0.0, y, 1.0, 0.0, math.radians(15))
        depth = cam.render(sc, T, rng)
        pts = depth_to_points(depth, cam.intrinsics()).reshape(cam.rows, cam.cols, 3)
        out.append((pts, T))
    return out


def test_mixed_pixels_leave_the_posts_shadow_and_keep_the_post_bar_and_floor(views) -> None:
    shadow = ((1.6, -0.04, 0.05), (3.9, 0.04, 1.4))  # behind the post, nothing real there
    counts = {"shadow": [0, 0], "post": [0, 0], "bar": [0, 0], "floor": [0, 0]}
    for pts, T in views:
        drop = mixed_pixel_mask(pts, 0.08, 6.0).reshape(-1)
        every = transform(pts.reshape(-1, 3), T)
        ok = np.isfinite(every).all(axis=1)
        for name, sel in (
            ("shadow", inside(every, shadow, 0.0) & ~inside(every, BAR, 0.03)),
            ("post", inside(every, POST, 0.01)),
            ("bar", inside(every, BAR, 0.01)),
            ("floor", ok & (np.abs(every[:, 2]) < 0.03) & (every[:, 0] < 3.9)),
        ):
            counts[name][0] += int(sel.sum())
            counts[name][1] += int((sel & ~drop).sum())
    before, after = counts["shadow"]
    assert before >= 40, counts  # the camera does put flying pixels there
    assert after <= 0.2 * before, counts
    for name in ("post", "bar"):  # thin obstacles keep their pixels
        assert counts[name][0] >= 100, counts
        assert counts[name][1] >= 0.99 * counts[name][0], counts
    assert counts["floor"][1] >= 0.999 * counts["floor"][0], counts


def test_a_coarse_pixel_grid_keeps_its_far_floor() -> None:
    """Strided to 86 x 64 (the bundled bag's camera), a floor 4-5 m off steps by more than
    8 cm + 3 % of the range a row; the threshold follows the frame's own pixel pitch, and
    an edge needs a surface on one side, so such a floor is not taken for mixed pixels."""
    cam, sc = DepthCamera(stride=3, noise_base=0.0, noise_quad=0.0, outlier_fraction=0.0), scene()
    T = camera_pose(0.0, 0.0, 1.1, 0.0, math.radians(5))
    depth = cam.render(sc, T, np.random.default_rng(1))
    pts = depth_to_points(depth, cam.intrinsics()).reshape(cam.rows, cam.cols, 3)
    every = transform(pts.reshape(-1, 3), T)
    far_floor = np.isfinite(every).all(axis=1) & (np.abs(every[:, 2]) < 0.03)
    far_floor &= np.linalg.norm(pts.reshape(-1, 3), axis=1) > 3.5
    r = np.linalg.norm(pts, axis=2)
    steps = np.abs(np.diff(r, axis=0))
    assert np.nanmax(steps[np.isfinite(steps) & (r[1:] > 3.5)]) > 0.08 + 0.03 * 3.5  # it does
    drop = mixed_pixel_mask(pts, 0.08, 6.0).reshape(-1)
    assert far_floor.sum() >= 100
    assert not (drop & far_floor).any()


def test_map_mixed_pixels_leaves_registration_alone_and_the_shadow_out_of_the_map(views) -> None:
    """The map-only option: the same frame to register (points, ICP inputs), the shadow's
    cells out of the points the map may keep, and a map without them."""
    shadow = ((1.6, -0.04, 0.05), (3.9, 0.04, 1.4))
    off, only = PreprocessConfig(map_mixed_pixels=False), PreprocessConfig(map_mixed_pixels=True)
    reg = RegistrationConfig()
    in_shadow = [0, 0]
    for pts, T in views:
        a, b = prepare_frame(pts, None, off, reg), prepare_frame(pts, None, only, reg)
        assert a.map_keep is None
        assert np.array_equal(a.points, b.points)
        assert np.array_equal(a.inputs.source, b.inputs.source)
        assert b.map_keep is not None and b.map_keep.shape == (b.points.shape[0],)
        assert b.stats.mixed_out_of_map == int((~b.map_keep).sum()) > 0  # in report.json
        sel = inside(transform(b.points, T), shadow, 0.0) & ~inside(
            transform(b.points, T), BAR, 0.05
        )
        in_shadow[0] += int(sel.sum())
        in_shadow[1] += int((sel & b.map_keep).sum())
        assert b.map_keep.mean() > 0.98  # the rest of the frame stays in the map
    assert in_shadow[0] >= 10, in_shadow
    assert in_shadow[1] <= 0.5 * in_shadow[0], in_shadow  # 15 of 34: SOR took many flagged

    def mapped(pre: PreprocessConfig) -> tuple[np.ndarray, list[np.ndarray]]:
        m = Mapper(pre, reg, MapperConfig(evidence_min_frames=1, evidence_hit_fraction=0.0))
        for k in range(3):  # one view three times: registration stays at the first pose
            m.add_frame(views[0][0], float(k))
        return m._evidence.points(), m.poses_odom

    (map_off, poses_off), (map_only, poses_only) = mapped(off), mapped(only)
    # the same poses, to KISS-ICP's threads' last bits
    assert all(np.allclose(p, q, atol=1e-9) for p, q in zip(poses_off, poses_only, strict=True))
    T = views[0][1]
    behind = [int(inside(transform(m, T), shadow, 0.0).sum()) for m in (map_off, map_only)]
    assert behind[1] < behind[0], behind
    assert map_only.shape[0] >= 0.97 * map_off.shape[0]


def test_preprocess_applies_it_to_organised_clouds_only_and_only_when_asked(views) -> None:
    pts, _ = views[0]
    flat = pts.reshape(-1, 3)
    off, on = PreprocessConfig(), PreprocessConfig(mixed_pixels=True)
    # off (the default): the organised cloud gives what its flattened points give
    assert np.array_equal(preprocess(pts, off), preprocess(flat, off))
    # on: the mixed pixels are gone before the rest of the chain; a flat cloud has no
    # neighbours to compare, so nothing changes for it
    assert np.array_equal(preprocess(flat, on), preprocess(flat, off))
    drop = mixed_pixel_mask(pts, on.mixed_jump, on.mixed_jump_pitches)
    kept = preprocess(pts, PreprocessConfig(mixed_pixels=True, enable_sor=False, enable_pfc=False))
    alone = preprocess(
        flat[~drop.reshape(-1)], PreprocessConfig(enable_sor=False, enable_pfc=False)
    )
    assert drop.sum() > 0
    assert np.array_equal(kept, alone)


def test_mixed_pixel_mask_checks_its_input() -> None:
    with pytest.raises(ValueError, match="organised"):
        mixed_pixel_mask(np.zeros((10, 3)), 0.08)
    with pytest.raises(ValueError, match="mixed_jump"):
        PreprocessConfig(mixed_jump=0.0)
    with pytest.raises(ValueError, match="mixed_jump_pitches"):
        PreprocessConfig(mixed_jump_pitches=-1.0)
    # NaN pixels are no neighbours: a lone pixel between two holes is kept
    pts = np.full((1, 3, 3), np.nan)
    pts[0, 1] = (0.0, 0.0, 2.0)
    assert not mixed_pixel_mask(pts, 0.08).any()


def test_map_mixed_pixels_on_a_flat_or_an_empty_frame(views) -> None:
    """A flat cloud has no pixel grid: every point may reach the map (no mask at all). A frame
    with no valid pixel gives no points and an empty mask, not an error."""
    only = PreprocessConfig(map_mixed_pixels=True)
    pts, _ = views[0]
    flat, keep = preprocess_for_map(pts.reshape(-1, 3), only)
    assert keep is None
    assert np.array_equal(flat, preprocess(pts.reshape(-1, 3), PreprocessConfig()))
    empty, keep = preprocess_for_map(np.full((4, 5, 3), np.nan), only)
    assert empty.shape == (0, 3)
    assert keep is not None and keep.shape == (0,)


def test_median_angle_is_numpys_median_of_the_angles_bit_for_bit() -> None:
    """The mask's pixel pitch skips the arccos of every pixel: it must still be exactly the
    median of the angles (odd and even counts, NaN left out, cosines past +-1 clipped), so
    that the mask, on by default for the map, is the one every figure was measured with."""
    rng = np.random.default_rng(3)
    for n in (1, 2, 3, 4, 9, 10, 1001, 1002):
        cos = rng.uniform(-1.05, 1.05, n)
        cos[rng.random(n) < 0.1] = np.nan
        finite = cos[np.isfinite(cos)]
        want = float(np.median(np.arccos(np.clip(finite, -1.0, 1.0)))) if finite.size else 0.0
        assert median_angle(cos) == want, n
    assert median_angle(np.full(5, np.nan)) == 0.0
