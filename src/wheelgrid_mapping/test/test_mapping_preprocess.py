"""Preprocessing against hand-made clouds: each step, and that thin obstacles survive."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wheelgrid_mapping.preprocess import (
    PreprocessConfig,
    PreprocessStats,
    cell_for_target,
    col_max,
    col_min,
    grid_knn,
    plane_fit_criterion,
    preprocess,
    smallest_eigenvector,
    statistical_outlier_mask,
    subdivision_cell,
    valid_mask,
    voxel_downsample,
)
from wheelgrid_mapping.thin_check import (
    near,
    plane,
    room_with_thin_obstacles,
    stretch_centres,
    thin_obstacle_coverage,
)


def test_valid_mask_drops_nan_inf_range_and_low_confidence() -> None:
    pts = np.array(
        [[0, 0, 1.0], [np.nan, 0, 1], [0, np.inf, 1], [0, 0, 0.1], [0, 0, 9.0], [0, 0, 2.0]]
    )
    conf = np.array([2, 2, 2, 2, 2, 0], dtype=np.uint8)
    assert valid_mask(pts, 0.2, 5.0).tolist() == [True, False, False, False, False, True]
    assert valid_mask(pts, 0.2, 5.0, conf, 1).tolist() == [True] + [False] * 5
    with pytest.raises(ValueError):
        valid_mask(pts, confidence=conf[:3])


def test_subdivision_cell_is_equation_5() -> None:
    # 1000 points in a 2 x 4 x 1 m box, 8 points per cell: L = cbrt(8/1000 * 8) = 0.4 m.
    assert subdivision_cell(1000, np.array([2.0, 4.0, 1.0]), 8) == pytest.approx(0.4)
    # A flat cloud still gets a finite cell.
    assert subdivision_cell(1000, np.array([2.0, 2.0, 0.0]), 8) > 0


def test_voxel_downsample_keeps_centroids() -> None:
    pts = np.array([[0.01, 0.01, 0.01], [0.03, 0.03, 0.03], [0.51, 0.01, 0.01]])
    out = voxel_downsample(pts, 0.1)
    assert out.shape == (2, 3)
    assert np.allclose(sorted(out[:, 0]), [0.02, 0.51])


def test_cell_for_target_hits_target_count() -> None:
    rng = np.random.default_rng(1)
    pts = plane(200_000, rng, (4.0, 4.0))
    cell = cell_for_target(pts, 20_000)
    n = voxel_downsample(pts, cell).shape[0]
    assert abs(n - 20_000) / 20_000 < 0.1
    # a room of walls on the axes, whose count jumps with the lattice's phase: the search
    # counted a lattice anchored at the cloud's minimum, voxel_downsample one anchored at 0,
    # and 100 k became 190 k (a review); within a few % now (it stops within 2 %, or takes
    # the closest of the cells it tried)
    faces = []
    for axis, at, size in ((2, 0.0, (9.6, 6)), (2, 2.7, (9.6, 6)), (1, 0.0, (9.6, 2.7)),
                           (1, 6.0, (9.6, 2.7)), (0, 0.0, (6, 2.7)), (0, 9.6, (6, 2.7))):  # fmt: skip
        uv = rng.random((100_000, 2)) * size
        face = np.zeros((100_000, 3))
        face[:, [i for i in range(3) if i != axis]] = uv
        face[:, axis] = at
        faces.append(face + rng.normal(0, 0.005, face.shape))
    room = np.vstack(faces)
    for target in (25_000, 50_000, 100_000):
        n = voxel_downsample(room, cell_for_target(room, target)).shape[0]
        assert abs(n - target) <= 0.04 * target, (target, n)


def test_grid_knn_matches_brute_force_within_one_cell() -> None:
    rng = np.random.default_rng(2)
    cell = 0.05
    pts = voxel_downsample(rng.random((5000, 3)) * [1.0, 1.0, 0.2], cell)
    idx, dist = grid_knn(pts, 6, cell)
    full = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(full, np.inf)
    brute = np.sort(full, axis=1)[:, :6]
    close = brute <= cell  # the guaranteed-exact radius
    assert close.sum() > 1000
    assert np.allclose(dist[close], brute[close])
    assert (idx != np.arange(len(pts))[:, None]).all()  # self excluded
    # An isolated point far from everything gets no neighbours.
    lonely = np.vstack([pts, [[5.0, 5.0, 5.0]]])
    idx2, dist2 = grid_knn(lonely, 3, cell)
    assert (idx2[-1] == -1).all() and np.isinf(dist2[-1]).all()


def test_grid_knn_shell_search_merges_with_the_inner_cells() -> None:
    # A sparse row of points 1.5 cells apart: the 3x3x3 search finds 2 neighbours, the 5x5x5
    # shell adds the next ones; together they must be the brute-force nearest.
    cell = 0.1
    pts = np.column_stack([np.arange(12) * 0.15 + 0.01, np.full(12, 0.05), np.full(12, 0.05)])
    idx, dist = grid_knn(pts, 4, cell)
    full = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(full, np.inf)
    brute = np.sort(full, axis=1)[:, :4]
    reach = brute <= 2 * cell  # all within the 5x5x5 block
    assert np.allclose(dist[reach], brute[reach])
    assert np.isinf(dist[~reach]).all() and (idx[~reach] == -1).all()


def test_grid_knn_crowded_cells_and_a_huge_lattice_agree_with_brute_force() -> None:
    # Several points a cell (not voxel_downsample output) take the per-slot table; two clusters
    # 30 m apart make the lattice (600^3 cells) too big for the dense lookup, so cells are
    # binary-searched. Distances are float32 offsets: 2e-6 m at 30 m.
    rng = np.random.default_rng(5)
    cell = 0.05
    # 1-3 points in each of 500 cells of a 20 x 20 x 3 lattice (a cell keeps its first 4).
    ijk = np.argwhere(np.ones((20, 20, 3), dtype=bool))[rng.permutation(1200)[:500]]
    ijk = np.repeat(ijk, rng.integers(1, 4, size=500), axis=0)
    blob = (ijk + rng.uniform(0.01, 0.99, size=ijk.shape)) * cell
    for pts in (blob, np.vstack([blob, blob + np.full(3, 30.0)])):
        idx, dist = grid_knn(pts, 5, cell)
        full = np.linalg.norm(pts[:, None] - pts[None], axis=2)
        np.fill_diagonal(full, np.inf)
        brute = np.sort(full, axis=1)[:, :5]
        close = brute <= cell
        assert close.sum() > 1000
        assert np.allclose(dist[close], brute[close], rtol=0, atol=1e-5)
        found = idx >= 0
        assert np.allclose(np.linalg.norm(pts[idx[found]] - pts[np.nonzero(found)[0]], axis=1),
                           dist[found], rtol=0, atol=1e-5)  # fmt: skip
        assert (np.diff(dist, axis=1) >= 0).all()  # sorted, inf last
        assert (idx != np.arange(len(pts))[:, None]).all()


def test_col_min_and_col_max_are_numpys_axis_0_reductions() -> None:
    rng = np.random.default_rng(6)
    for a in (rng.normal(size=(1000, 3)), rng.integers(-50, 50, size=(1000, 3)).astype(np.int32)):
        for ours, ref in ((col_min(a), a.min(axis=0)), (col_max(a), a.max(axis=0))):
            assert ours.dtype == ref.dtype and np.array_equal(ours, ref)
    with_nan = rng.normal(size=(10, 3))
    with_nan[4, 1] = np.nan  # propagates, as numpy's does
    assert np.array_equal(col_min(with_nan), with_nan.min(axis=0), equal_nan=True)


def test_smallest_eigenvector_matches_eigh() -> None:
    rng = np.random.default_rng(4)
    a = rng.normal(size=(2000, 3, 3))
    mats = np.einsum("nij,nkj->nik", a, a)  # symmetric positive semi-definite
    # Plane-like (one tiny eigenvalue), line-like and exactly flat neighbourhoods too.
    flat = rng.normal(size=(200, 10, 3)) * [1.0, 0.5, 1e-9]
    mats = np.vstack([mats, np.einsum("nki,nkj->nij", flat, flat)])
    cov = {(i, j): mats[:, i, j] for i in range(3) for j in range(i, 3)}
    v = smallest_eigenvector(cov)
    vals, vecs = np.linalg.eigh(mats)
    assert np.allclose(np.linalg.norm(v, axis=1), 1.0)
    separated = (vals[:, 1] - vals[:, 0]) > 1e-6 * vals[:, 2]
    dots = np.abs(np.einsum("ni,ni->n", v, vecs[:, :, 0]))
    assert separated.sum() > 2000 and np.all(dots[separated] > 1 - 1e-6)
    # Wherever it is, it is an eigenvector of the smallest eigenvalue: |A v| ~ lambda_min.
    av = np.linalg.norm(np.einsum("nij,nj->ni", mats, v), axis=1)
    assert np.all(av <= vals[:, 0] + 1e-6 * vals[:, 2])


def test_statistical_outlier_mask_is_equations_1_to_4() -> None:
    dist = np.array([[1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [1.0, 1.0], [5.0, 5.0]])
    mu_i = dist.mean(axis=1)
    t = mu_i.mean() + 1.0 * mu_i.std(ddof=1)
    keep = statistical_outlier_mask(dist, 1.0)
    assert keep.tolist() == (mu_i < t).tolist() == [True, True, True, True, False]
    # Missing neighbours count as far away: an isolated point is an outlier.
    d2 = np.vstack([np.ones((20, 3)) * 0.02, [[np.inf] * 3]])
    assert not statistical_outlier_mask(d2, 2.0, missing_distance=0.1)[-1]


def test_statistical_outlier_mask_keeps_a_cloud_whose_mu_i_are_all_equal() -> None:
    # Equal mu_i: sigma is 0 in exact arithmetic, ~1e-17 in floating point, where mu_i >= t
    # (eq. 4) held for every point and the whole cloud was removed.
    for v, n, k, m in ((0.007899523325820048, 1375, 1, 0.5), (0.1, 7, 8, 2.5), (0.03, 500, 4, 0.0)):
        assert statistical_outlier_mask(np.full((n, k), v), m).all(), (v, n, k, m)
    rng = np.random.default_rng(0)
    for _ in range(2000):
        n, k = int(rng.integers(3, 2000)), int(rng.integers(1, 12))
        d = np.full((n, k), rng.uniform(0.005, 0.2))
        assert statistical_outlier_mask(d, float(rng.choice([0.5, 1.0, 2.5]))).all()
    # A real spread still follows eqs. 1-4 (the outlier goes, exactly at t is an outlier).
    mu = np.array([1.0, 1.0, 1.0, 3.0])
    m = (3.0 - mu.mean()) / mu.std(ddof=1)
    assert mu.mean() + m * mu.std(ddof=1) == 3.0
    assert statistical_outlier_mask(mu[:, None], m).tolist() == [True, True, True, False]


@pytest.mark.parametrize("key", ["sor_m", "voxel_size", "pfc_threshold", "pfc_min_offset"])
@pytest.mark.parametrize("value", [math.nan, math.inf])
def test_a_non_finite_preprocess_setting_is_refused(key: str, value: float) -> None:
    # sor_m NaN made t NaN: every frame lost every point to eq. 4, without a word.
    with pytest.raises(ValueError, match=f"{key} must be finite"):
        PreprocessConfig(**{key: value})


@pytest.mark.parametrize("value", [-1, 3])
def test_a_min_confidence_outside_arkits_levels_is_refused(value: int) -> None:
    """``preprocess: {min_confidence: 3}`` passed, and every point of every frame was dropped
    (ARKit's levels are 0, 1, 2): the map came out empty, frame after frame, without a word."""
    pts = np.array([[0.0, 0.0, 1.0], [0.1, 0.0, 1.0]])
    assert preprocess(pts, PreprocessConfig(min_confidence=2), confidence=[2, 2]).shape[0] > 0
    with pytest.raises(ValueError, match="min_confidence must be 0, 1 or 2"):
        PreprocessConfig(min_confidence=value)


def test_a_voxel_too_fine_for_the_range_is_refused() -> None:
    """``voxel_size: 1e-6`` passed, and every frame then raised "cloud too large for cell"
    (21 bits a axis): no frame was mapped. The finest cell that fits still works."""
    with pytest.raises(ValueError, match="voxel_size 1e-06 m is too fine for max_range"):
        PreprocessConfig(voxel_size=1e-6)
    cfg = PreprocessConfig(voxel_size=6e-6, enable_sor=False, enable_pfc=False)
    pts = np.array([[-4.2, -4.2, -0.1], [4.2, 4.2, 0.1], [0.0, 0.0, 1.0]])
    assert preprocess(pts, cfg).shape == (3, 3)


def test_pfc_flags_a_point_off_a_flat_neighbourhood() -> None:
    rng = np.random.default_rng(3)
    pts = np.vstack([plane(400, rng, (0.3, 0.3)), [[0.15, 0.15, 0.045]]])
    idx, _ = grid_knn(pts, 10, 0.03)
    pfc, d_p = plane_fit_criterion(pts, idx)
    assert pfc[-1] > 0.9 and d_p[-1] > 0.035
    assert np.median(pfc[:-1]) < 0.7


@pytest.mark.parametrize("sor_m", [2.5, 0.0])
def test_filters_keep_thin_obstacles_and_remove_floating_noise(sor_m: float) -> None:
    """At the default m and at the smallest m allowed: a negative m (t below the mean) kept
    470 of 17798 points here and not one of the table's front edge, so it is refused."""
    with pytest.raises(ValueError, match="sor_m must be >= 0"):
        PreprocessConfig(sor_m=-1.0)
    rng = np.random.default_rng(4)
    parts = room_with_thin_obstacles(rng)
    cloud = np.vstack(list(parts.values()))
    stats = PreprocessStats()
    cfg = PreprocessConfig(min_range=0.0, max_range=100.0, sor_m=sor_m)
    out = preprocess(cloud, cfg, stats=stats)
    assert stats.input == len(cloud) and stats.after_pfc == len(out)
    # Every 10 cm of the bar, of the leg, and of the table's front edge still has points.
    for name, samples in stretch_centres().items():
        kept = near(out, samples, 0.05)
        assert kept.all(), f"{name} lost at {samples[~kept]}"
    # and the start-up check (thin_check), the same room and measure, agrees
    assert thin_obstacle_coverage(cfg).kept == {"bar": 1.0, "leg": 1.0, "edge": 1.0}
    # Most floating outliers are gone (those that happen to touch a surface may stay).
    gone = ~near(out, parts["outliers"], 0.005)
    assert gone.mean() > 0.8


def _iphone_frame(eye: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A 256 x 192 depth frame (64 deg wide, noise-free) of axis-aligned boxes, seen level along
    world +y from ``eye``: ``(optical-frame points (H, W, 3), world <- optical rotation)``."""
    from wheelgrid_sim.camera import DepthCamera, raycast

    K = DepthCamera().full_intrinsics()
    u, v = np.meshgrid(np.arange(256.0), np.arange(192.0))
    rays = np.stack([(u - K[0, 2]) / K[0, 0], (v - K[1, 2]) / K[1, 1], np.ones_like(u)], -1)
    R = np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])  # optical x right, y down, z ahead
    t = raycast(eye, rays.reshape(-1, 3) @ R.T, lo, hi).reshape(192, 256)
    pts = rays * t[..., None]  # the rays' z is 1: t is the depth
    pts[~np.isfinite(t)] = np.nan
    return pts, R


@pytest.mark.parametrize(
    ("what", "eye_z", "obstacle", "along"),
    [
        # a 3 cm leg 1.5 m and 2.5 m ahead: one cell wide once downsampled
        ("leg", 1.0, ([-0.015, 1.485, 0.0], [0.015, 1.515, 0.72]), 2),
        ("leg", 1.0, ([-0.015, 2.485, 0.0], [0.015, 2.515, 0.72]), 2),
        # a table top 2.5 cm thick seen from a chair-mounted sensor at its own height
        ("edge", 0.70, ([-0.7, 2.0, 0.695], [0.7, 2.8, 0.72]), 0),
    ],
)
def test_a_one_cell_wide_obstacle_survives_the_outlier_removal_at_every_lattice_phase(
    what: str, eye_z: float, obstacle: tuple[list[float], list[float]], along: int
) -> None:
    """Eqs. 1-4 run after the downsampling: a thin leg or a table's edge seen from chair height
    is then one cell wide, half of its K = 8 neighbours are out of reach, and eq. 4 flagged it
    whole: this 3 cm leg lost a stretch on 6 of 36 lattice phases (all of it on the worst),
    the table a third of its length (a reviewer's ray cast). Slid through one 3 cm cell in 5 mm
    steps, each 10 cm stretch of it that the frame sees keeps a point; floating returns still
    go."""
    lo = np.array([[-5.0, -1.0, -0.1], [-5.0, 4.5, 0.0], obstacle[0]])
    hi = np.array([[5.0, 10.0, 0.0], [5.0, 4.6, 3.0], obstacle[1]])
    cfg = PreprocessConfig()
    steps = np.arange(0.0, 0.03, 0.005)
    flagged_kept = 0
    for dx in steps:
        for dz in steps:
            eye = np.array([dx, 0.0, eye_z + dz])
            pts, R = _iphone_frame(eye, lo, hi)
            stats = PreprocessStats()
            out = preprocess(pts, cfg, stats=stats)
            flagged_kept += stats.sor_kept_on_lines

            def stretches(p: np.ndarray, R: np.ndarray = R, eye: np.ndarray = eye) -> np.ndarray:
                w = p[np.isfinite(p).all(axis=1)] @ R.T + eye
                on = ((w > np.add(obstacle[0], -0.01)) & (w < np.add(obstacle[1], 0.01))).all(
                    axis=1
                )
                a = w[on, along]
                edges = np.arange(obstacle[0][along] + 0.05, obstacle[1][along] - 0.05, 0.1)
                return np.array([((a >= e) & (a < e + 0.1)).any() for e in edges])

            seen, kept = stretches(pts.reshape(-1, 3)), stretches(out)
            assert seen.sum() >= 4, (what, dx, dz, seen)
            assert kept[seen].all(), f"{what}: stretches {np.flatnonzero(seen & ~kept)} lost"
    assert flagged_kept > 0  # eq. 4 did flag it: the line rule, not luck, kept it
    # floating returns among the boxes still go
    rng = np.random.default_rng(9)
    pts, _ = _iphone_frame(np.array([0.0, 0.0, eye_z]), lo, hi)
    flat = pts.reshape(-1, 3)
    wild = np.flatnonzero(np.isfinite(flat).all(axis=1))[::997]
    flat[wild] *= rng.uniform(0.3, 0.8, (wild.size, 1))
    out = preprocess(flat, cfg)
    assert (~near(out, flat[wild], 0.005)).mean() > 0.8


def test_an_exact_neighbour_search_serves_a_cloud_that_was_not_downsampled() -> None:
    """``voxel_size 0``: the grid search takes a cell's first 4 points, not its nearest (22 % of
    the true 8 nearest on a dense plane), and eq. 4 removed 429 points of a flat, noise-free
    plane. Now the K nearest are the nearest."""
    from wheelgrid_mapping.preprocess import exact_knn

    rng = np.random.default_rng(12)
    pts = plane(20_000, rng, (0.3, 0.3))
    idx, dist = exact_knn(pts, 8)
    d = np.linalg.norm(pts[:500, None] - pts[None], axis=2)
    d[np.arange(500), np.arange(500)] = np.inf
    np.testing.assert_allclose(dist[:500], np.sort(d, axis=1)[:, :8], atol=1e-12)
    assert (idx[:500] != np.arange(500)[:, None]).all()
    dup = np.vstack([pts[:3], pts[:3]])  # duplicates: self is never its own neighbour
    idx, dist = exact_knn(dup, 8)  # and fewer points than K: the rest are missing
    assert (idx != np.arange(6)[:, None]).all() and (idx[:, 5:] == -1).all()
    assert np.isinf(dist[:, 5:]).all() and (dist[:, 0] == 0.0).all()
    assert (idx[:, 0] == (np.arange(6) + 3) % 6).all()
    # eq. 4 on the exact neighbours keeps what Open3D's statistical outlier removal (the same
    # mean distance to K neighbours, t = mean + m std) keeps, point for point
    import open3d as o3d

    pts[:50, 2] += rng.uniform(0.05, 0.2, 50)  # some wild returns above the plane
    cfg = PreprocessConfig(voxel_size=0.0, min_range=0.0, enable_pfc=False)
    stats = PreprocessStats()
    out = preprocess(pts, cfg, stats=stats)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    _, kept = cloud.remove_statistical_outlier(cfg.sor_k, cfg.sor_m)
    assert stats.downsampled == len(pts) and len(out) == len(kept) <= len(pts) - 50, stats
    np.testing.assert_array_equal(np.sort(out, axis=0), np.sort(pts[kept], axis=0))


def test_all_nan_frame_gives_empty_result() -> None:
    stats = PreprocessStats()
    out = preprocess(np.full((100, 3), np.nan), PreprocessConfig(), stats=stats)
    assert out.shape == (0, 3) and stats.valid == 0


def test_voxel_downsample_sorted_and_bitmap_paths_agree() -> None:
    """A frame (few points in a big, mostly empty box) is grouped by sorting, a dense cloud by a
    bitmap over its lattice: the same cells, centroids and order either way."""
    rng = np.random.default_rng(5)
    sparse = rng.uniform(-3, 3, (2000, 3))  # 8 M cells at 3 cm: the sorted path
    dense = rng.uniform(0, 0.5, (200_000, 3))  # 4.6 k cells: the bitmap path
    for pts in (sparse, dense):
        got = voxel_downsample(pts, 0.03)
        keys = np.floor((pts - np.floor(pts.min(axis=0) / 0.03) * 0.03) / 0.03).astype(np.int64)
        _, inv = np.unique(keys, axis=0, return_inverse=True)
        want = np.stack([np.bincount(inv.ravel(), weights=pts[:, a]) for a in range(3)], axis=1)
        want /= np.bincount(inv.ravel())[:, None]
        np.testing.assert_allclose(got, want, rtol=0, atol=1e-12)


def test_points_that_are_not_xyz_triples_are_refused() -> None:
    """An (N, 4) cloud (x y z intensity) was reshaped to (-1, 3) whenever 4 N divides by 3:
    every point's coordinates came from parts of two points, and the map was garbage without
    a word. (N, 3), (H, W, 3) and an empty cloud are still read."""
    cfg = PreprocessConfig()
    rng = np.random.default_rng(3)
    xyz = rng.uniform(0.5, 3.0, (600, 3))
    with pytest.raises(ValueError, match=r"\(N, 3\).*\(600, 4\)"):
        preprocess(np.column_stack([xyz, np.ones(600)]), cfg)
    assert preprocess(xyz, cfg).shape[1] == 3
    assert preprocess(xyz.reshape(20, 30, 3), cfg).shape[1] == 3
    assert preprocess(np.empty((0, 3)), cfg).shape == (0, 3)
