"""Frame evidence keeps what is seen again and again (walls, a 5 cm bar) and drops what lands
somewhere new in every frame (wild returns, flying pixels)."""

import numpy as np
import pytest

from wheelgrid_mapping.evidence import EvidenceMap, voxel_keys


def _bar(rng, n=200):
    """A 5 cm thick horizontal bar at 0.77 m, 2 m long."""
    x = rng.uniform(0, 2, n)
    y = 1.0 + rng.uniform(-0.025, 0.025, n)
    z = 0.77 + rng.uniform(-0.025, 0.025, n)
    return np.c_[x, y, z]


def test_repeated_surfaces_stay_and_one_frame_noise_goes():
    rng = np.random.default_rng(0)
    m = EvidenceMap(voxel=0.02, evidence_voxel=0.1, min_frames=3)
    wild = []
    for _ in range(6):
        wall = np.c_[rng.uniform(0, 3, 500), np.full(500, 2.0), rng.uniform(0, 2, 500)]
        noise = rng.uniform([0, 0, 0], [3, 2, 2], (20, 3))
        wild.append(noise)
        m.add(np.vstack([wall + rng.normal(0, 0.003, wall.shape), _bar(rng, 60), noise]))
    kept = m.points()
    assert m.frames == 6
    near_wall = np.abs(kept[:, 1] - 2.0) < 0.1  # within its evidence voxels
    near_bar = (np.abs(kept[:, 1] - 1.0) < 0.1) & (np.abs(kept[:, 2] - 0.77) < 0.1)
    assert near_bar.sum() >= 30  # the thin bar survives
    assert near_wall.sum() >= 400
    stray = kept[~near_wall & ~near_bar]
    assert stray.shape[0] <= 2  # 120 wild points in, (almost) none out
    assert m.all_points().shape[0] > kept.shape[0]


def test_min_frames_one_keeps_every_voxel_and_bad_input_is_refused():
    m = EvidenceMap(0.05, 0.1, 1)
    m.add(np.array([[0.0, 0.0, 0.0], [np.nan, 1.0, 1.0], [1.0, 1.0, 1.0]]))
    m.add(np.empty((0, 3)))
    assert m.points().shape == (2, 3)
    with pytest.raises(ValueError):
        EvidenceMap(0.0, 0.1, 1)
    with pytest.raises(ValueError, match="too far"):
        voxel_keys(np.array([[1e9, 0.0, 0.0]]), 0.01)


def test_floor_correction_levels_a_slightly_tilted_floor_and_keeps_the_origin():
    from wheelgrid_mapping.pipeline import floor_correction

    rng = np.random.default_rng(1)
    xy = rng.uniform(-1, 9, (20000, 2))
    tilt = np.radians(0.4)
    floor = np.c_[xy, np.tan(tilt) * xy[:, 0] + 0.01 + rng.normal(0, 0.005, len(xy))]
    table = np.c_[rng.uniform(2, 3, (3000, 2)), np.full(3000, 0.75)]
    corr = floor_correction(np.vstack([floor, table]))
    assert corr is not None
    fixed = floor @ corr[:3, :3].T + corr[:3, 3]
    assert abs(np.median(fixed[:, 2])) < 0.002
    assert np.percentile(np.abs(fixed[:, 2]), 99) < 0.02  # the far end is no longer 6 cm high
    assert np.linalg.norm(corr[:2, 3]) < 1e-9  # no sideways shift of the origin
    steep = np.c_[xy, np.tan(np.radians(10)) * xy[:, 0]]
    assert floor_correction(steep) is None  # not a small refinement: leave it alone


_POST = (np.array([1.0, 2.0, 0.0]), np.array([1.1, 2.1, 1.0]))  # a 10 cm square post


def _shadowed(origin, pts):
    """Points whose ray from ``origin`` passes through the post (slab test)."""
    d = pts - origin
    with np.errstate(divide="ignore", invalid="ignore"):
        t0 = (_POST[0] - origin) / d
        t1 = (_POST[1] - origin) / d
    near = np.nanmax(np.minimum(t0, t1), axis=1)
    far = np.nanmin(np.maximum(t0, t1), axis=1)
    return (near <= far) & (far > 0) & (near < 0.999)


def _frame(rng, origin, front, sigma=0.01):
    """What a camera at ``origin`` sees: from the front (y < 2) the post's face at y = 2.0 (on
    an evidence-voxel boundary) and a wall at y = 3; from the side a wall at x = 0. Range noise
    along the ray."""
    if front:
        face = np.c_[rng.uniform(1.0, 1.1, 400), np.full(400, 2.0), rng.uniform(0, 1, 400)]
        wall = np.c_[rng.uniform(0, 3, 3000), np.full(3000, 3.0), rng.uniform(0, 1, 3000)]
        pts = np.vstack([face, wall[~_shadowed(origin, wall)]])
    else:
        wall = np.c_[np.zeros(3000), rng.uniform(1.0, 2.6, 3000), rng.uniform(0, 1, 3000)]
        pts = wall[~_shadowed(origin, wall)]
    ray = pts - origin
    ray /= np.linalg.norm(ray, axis=1, keepdims=True)
    return pts + ray * rng.normal(0, sigma, (pts.shape[0], 1))


@pytest.mark.parametrize(("margin", "up"), [(0.0, "z"), (0.04, "z"), (0.04, "y"), (0.04, None)])
def test_margin_keeps_both_sides_of_a_surfaces_noise(margin, up):
    """Frames from the side see through the voxel just in front of the post's face and call it
    free; without a margin the face's noise on that side is dropped and the face moves away
    from the sensor that saw it. The margin grows sideways only: with y up (the face a ceiling)
    or no vertical known, the face is carved as without it."""
    rng = np.random.default_rng(3)
    m = EvidenceMap(0.02, 0.1, 2, hit_fraction=0.5, margin=margin)
    for k in range(8):
        origin = np.array([0.4 + 0.2 * k, 0.0, 0.5])
        m.add(_frame(rng, origin, True), origin)
    for k in range(12):
        origin = np.array([2.5, 2.3 + 0.02 * k, 0.5])
        m.add(_frame(rng, origin, False), origin)
    m.add(np.array([[1.05, 1.5, 0.5]]), np.array([1.0, 0.0, 0.5]))  # a wild return, free space
    kept = m.points(up=None if up is None else np.eye(3)["xyz".index(up)])
    face = kept[(np.abs(kept[:, 0] - 1.05) < 0.05) & (np.abs(kept[:, 1] - 2.0) < 0.1)]
    assert face.shape[0] > 20
    offset = float(np.mean(face[:, 1]) - 2.0)  # + = behind the face, away from the sensor
    if margin == 0.0 or up != "z":
        assert offset > 0.002  # measured: 3.2 mm
    else:
        assert abs(offset) < 0.0015  # measured: 0.5 mm
    assert not (np.linalg.norm(kept - [1.05, 1.5, 0.5], axis=1) < 0.2).any()  # still free
    assert m.all_points().shape[0] >= kept.shape[0]


def test_margin_is_checked():
    with pytest.raises(ValueError, match="margin"):
        EvidenceMap(0.02, 0.1, 2, margin=0.2)
    assert EvidenceMap(0.02, 0.1, 2, margin=0.04).rings == 2
    assert EvidenceMap(0.02, 0.1, 2, margin=0.03).rings == 2
    assert EvidenceMap(0.02, 0.1, 2).rings == 0


def test_ray_misses_are_every_voxel_a_ray_crosses_short_of_its_hit():
    """The ray samples are built per ray and deduplicated by a bitmap (3x faster); they must be
    exactly the voxels of the plain definition: samples every half voxel along each ray, up to
    two evidence voxels short of its hit, sensor anywhere, rays of any length."""
    rng = np.random.default_rng(3)
    for trial in range(4):
        origin = rng.normal(0, 3, 3)
        pts = origin + rng.normal(0, 1, (3000, 3)) * rng.uniform(0.1, 6.0, (3000, 1))
        m = EvidenceMap(voxel=0.02, evidence_voxel=0.1, min_frames=3, max_rays=10_000)
        got = m._ray_misses(pts, origin)
        d = pts - origin
        length = np.linalg.norm(d, axis=1)
        reach = length - 0.2
        t = np.arange(1, int(np.ceil(max(reach.max(), 0.0) / 0.05)) + 1) * 0.05
        samples = origin + (d / length[:, None])[:, None, :] * t[None, :, None]
        want = np.unique(voxel_keys(samples[t[None, :] < reach[:, None]], 0.1))
        assert want.size > 1000, trial
        np.testing.assert_array_equal(got, want)


def test_keys_or_invalid_agree_with_voxel_keys_inside_and_mark_the_edge_and_beyond() -> None:
    from wheelgrid_mapping.evidence import INVALID_KEY, NEIGHBOUR_KEYS, voxel_keys_or_invalid

    rng = np.random.default_rng(4)
    pts = rng.uniform(-50.0, 50.0, (500, 3))
    assert np.array_equal(voxel_keys_or_invalid(pts, 0.05), voxel_keys(pts, 0.05))
    edge = (2**20 - 0.5) * 0.05  # the last voxel inside: a neighbour step would leave the space
    odd = np.array([[edge, 0.0, 0.0], [0.0, -edge - 0.05, 0.0], [0.0, 0.0, 1e9], [np.inf] * 3])
    keys = voxel_keys_or_invalid(odd, 0.05)
    assert np.all(keys == INVALID_KEY)
    valid_max = voxel_keys(np.array([[edge - 0.05] * 3]), 0.05)[0]
    assert INVALID_KEY + NEIGHBOUR_KEYS.max() < 0 <= voxel_keys(np.zeros((1, 3)), 0.05)[0]
    assert valid_max + NEIGHBOUR_KEYS.max() < 2**63


def test_frames_are_merged_as_they_come_and_the_map_is_the_same(monkeypatch):
    """Loop closure's rebuild added every kept frame before the first merge: 0.9 MB a frame at
    its peak (932 MB for 588 frames, ~5 GB at max_kept_frames; a review). Frames are merged
    once PENDING_POINTS are waiting, into the same map."""
    from wheelgrid_mapping import evidence

    rng = np.random.default_rng(5)
    frames = [rng.uniform(-2.0, 2.0, (400, 3)) for _ in range(30)]
    origins = [rng.uniform(-0.5, 0.5, 3) for _ in range(30)]

    def build() -> tuple[np.ndarray, int]:
        ev = evidence.EvidenceMap(0.02, 0.1, 2, hit_fraction=0.3, seed=1)
        most = 0
        for pts, origin in zip(frames, origins, strict=True):
            ev.add(pts, origin)
            most = max(most, sum(p.shape[0] for p in ev._pending))
        return ev.points(), most

    at_once, waited = build()
    assert at_once.shape[0] > 100  # a map to compare
    assert waited == 30 * 400  # the default bound is far above this scan
    monkeypatch.setattr(evidence, "PENDING_POINTS", 1000)
    merged, waited = build()
    assert waited < 1000 + 400
    order = np.lexsort(at_once.T), np.lexsort(merged.T)
    np.testing.assert_allclose(at_once[order[0]], merged[order[1]], atol=1e-12)
