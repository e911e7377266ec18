"""An ARKit-like depth camera: exact ray casting against boxes plus a plausible error model.

The iPhone 12 Pro's ARKit ``sceneDepth`` is a 256 x 192 depth map (metres, z-depth along the
optical axis) valid to about 5 m. Real maps have range-dependent noise, a few wild returns,
"flying pixels" (depth mixed between foreground and background at silhouettes) and holes. The
mapping pipeline must survive all of those, so the simulator produces each of them, and each
can be switched off (``noise=False``) for exact ground-truth tests.

Optical frame convention (REP-103): z forward, x right, y down.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wheelgrid_sim.scene import Scene


@dataclass
class DepthCamera:
    """Pinhole depth camera; ``stride`` keeps every stride-th pixel in both directions."""

    width: int = 256
    height: int = 192
    hfov_deg: float = 64.0
    min_range: float = 0.2  # m, z-depth
    max_range: float = 5.0  # m, z-depth
    stride: int = 1
    noise_base: float = 0.002  # m, depth std at zero range
    noise_quad: float = 0.0015  # 1/m, std grows as noise_base + noise_quad * z^2
    outlier_fraction: float = 0.01  # share of valid pixels replaced by a uniform wild depth
    flying_threshold: float = 0.08  # m (plus 3 % of depth): a jump that makes an edge
    flying_probability: float = 0.5  # chance an edge pixel gets a mixed (flying) depth

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError("stride must be >= 1")
        if not 0 < self.min_range < self.max_range:
            raise ValueError("need 0 < min_range < max_range")

    @property
    def rows(self) -> int:
        return math.ceil(self.height / self.stride)

    @property
    def cols(self) -> int:
        return math.ceil(self.width / self.stride)

    def full_intrinsics(self) -> np.ndarray:
        """K of the full-resolution sensor (pixel centres at integer coordinates)."""
        fx = (self.width / 2.0) / math.tan(math.radians(self.hfov_deg) / 2.0)
        return np.array(
            [[fx, 0.0, (self.width - 1) / 2.0], [0.0, fx, (self.height - 1) / 2.0], [0, 0, 1.0]]
        )

    def intrinsics(self) -> np.ndarray:
        """K of the OUTPUT image (after the stride): output pixel (r, c) = sensor (r*s, c*s)."""
        k = self.full_intrinsics()
        s = float(self.stride)
        return np.array(
            [[k[0, 0] / s, 0.0, k[0, 2] / s], [0.0, k[1, 1] / s, k[1, 2] / s], [0.0, 0.0, 1.0]]
        )

    def rays(self) -> np.ndarray:
        """``(rows*cols, 3)`` optical-frame directions with z = 1 (so ray t equals depth)."""
        k = self.intrinsics()
        v, u = np.mgrid[0 : self.rows, 0 : self.cols].astype(np.float64)
        d = np.empty((self.rows * self.cols, 3))
        d[:, 0] = ((u - k[0, 2]) / k[0, 0]).ravel()
        d[:, 1] = ((v - k[1, 2]) / k[1, 1]).ravel()
        d[:, 2] = 1.0
        return d

    def sigma(self, depth: np.ndarray | float) -> np.ndarray:
        """Depth noise standard deviation (m) at ``depth`` (m)."""
        z = np.asarray(depth, dtype=np.float64)
        return self.noise_base + self.noise_quad * z * z

    def render(
        self,
        scene: Scene,
        T_room_optical: np.ndarray,
        rng: np.random.Generator | None = None,
        noise: bool = True,
    ) -> np.ndarray:
        """Depth image ``(rows, cols)`` float32 in metres, NaN where there is no return."""
        T = np.asarray(T_room_optical, dtype=np.float64)
        dirs = self.rays() @ T[:3, :3].T
        lo, hi = scene.box_arrays()
        keep = cull_boxes(self, T, lo, hi)
        depth = raycast(T[:3, 3], dirs, lo[keep], hi[keep]).reshape(self.rows, self.cols)
        if noise:
            if rng is None:
                raise ValueError("render(noise=True) needs an rng (seeded, for reproducibility)")
            depth = self._corrupt(depth, rng)
        depth = np.where(self.in_range(depth), depth, np.nan)
        return depth.astype(np.float32)

    def in_range(self, depth: np.ndarray) -> np.ndarray:
        """Pixels the sensor reports: within ``[min_range, max_range]`` (NaN and inf are not)."""
        with np.errstate(invalid="ignore"):
            return (depth >= self.min_range) & (depth <= self.max_range)

    def edges(self, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``(edge, neighbour)``: in-range pixels whose farthest-differing 4-neighbour lies more
        than ``flying_threshold`` + 3 % of the depth away (where flying pixels are), and that
        neighbour's depth (NaN where there is none). A neighbour beyond the range limit still
        counts: its light mixes in all the same. ``bench/bench_confidence.py`` applies the same
        test to real frames, to see what ARKit's confidence calls these pixels."""
        valid = self.in_range(depth)
        best_nb = np.full_like(depth, np.nan)
        best_jump = np.zeros_like(depth)
        pad = np.pad(depth, 1, constant_values=np.nan)
        for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
            nb = pad[1 + dr : 1 + dr + depth.shape[0], 1 + dc : 1 + dc + depth.shape[1]]
            with np.errstate(invalid="ignore"):
                jump = np.abs(nb - depth)
            take = np.isfinite(jump) & (jump > best_jump)
            best_jump = np.where(take, jump, best_jump)
            best_nb = np.where(take, nb, best_nb)
        edge = valid & (best_jump > self.flying_threshold + 0.03 * np.where(valid, depth, 0.0))
        return edge, best_nb

    def _corrupt(self, depth: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Flying pixels at depth edges, Gaussian range noise, then ~1 % wild outliers."""
        depth = np.where(np.isfinite(depth), depth, np.nan)  # misses (inf) -> NaN
        z = depth.copy()
        valid = self.in_range(z)
        zv = np.where(valid, z, 0.0)
        # Flying pixels: mix with the farthest-differing 4-neighbour where the jump is large.
        edge, best_nb = self.edges(depth)
        fly = edge & (rng.random(z.shape) < self.flying_probability)
        w = rng.uniform(0.15, 0.85, z.shape)
        z = np.where(fly, zv + w * (np.nan_to_num(best_nb) - zv), z)
        # Range noise.
        noisy = z + rng.standard_normal(z.shape) * self.sigma(np.where(valid, z, 0.0))
        z = np.where(valid, noisy, z)
        # Outliers: wild but in-range values, as real sensors report them.
        out = valid & (rng.random(z.shape) < self.outlier_fraction)
        z = np.where(out, rng.uniform(self.min_range, self.max_range, z.shape), z)
        return z


def raycast(origin: np.ndarray, dirs: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """Ray parameter of the first hit of rays ``origin + t * dirs`` on any box; inf if none.

    Vectorised slab test over all rays x all boxes, one axis at a time so peak memory is a
    few ``(N, M)`` arrays. The search runs in float32 (half the memory traffic), then the
    winning box's entry parameter is recomputed in float64, so ground truth stays exact to
    far below a millimetre. Boxes that contain the origin are ignored (a camera inside an
    obstacle sees out of it, rather than returning depth 0).
    """
    o = np.asarray(origin, dtype=np.float64).reshape(3)
    d = np.asarray(dirs, dtype=np.float64).reshape(-1, 3)
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    n, m = d.shape[0], lo.shape[0]
    if m == 0 or n == 0:
        return np.full(n, np.inf)
    tiny = 1e-12
    d = np.where(np.abs(d) < tiny, np.where(d < 0, -tiny, tiny), d)
    inv = 1.0 / d
    inv32 = inv.astype(np.float32)
    tnear = tfar = None
    for k in range(3):
        ta = np.multiply.outer(inv32[:, k], (lo[:, k] - o[k]).astype(np.float32))
        tb = np.multiply.outer(inv32[:, k], (hi[:, k] - o[k]).astype(np.float32))
        lo_t = np.minimum(ta, tb)
        hi_t = np.maximum(ta, tb, out=ta)
        if tnear is None or tfar is None:  # (the first axis: both None together)
            tnear, tfar = lo_t, hi_t
        else:
            np.maximum(tnear, lo_t, out=tnear)
            np.minimum(tfar, hi_t, out=tfar)
    assert tnear is not None and tfar is not None
    miss = (tnear > tfar) | (tnear <= 0.0)
    tnear[miss] = np.inf
    idx = np.argmin(tnear, axis=1)
    hit = np.isfinite(tnear[np.arange(n), idx])
    t = np.full(n, np.inf)
    if hit.any():
        b = idx[hit]
        ta64 = (lo[b] - o) * inv[hit]
        tb64 = (hi[b] - o) * inv[hit]
        t[hit] = np.max(np.minimum(ta64, tb64), axis=1)
    return t


def cull_boxes(
    cam: DepthCamera, T_room_optical: np.ndarray, lo: np.ndarray, hi: np.ndarray
) -> np.ndarray:
    """Indices of boxes that may be hit within range: the others are behind the camera,
    wholly outside one side of the view frustum, or farther than any in-range return."""
    T = np.asarray(T_room_optical, dtype=np.float64)
    corners = np.stack(
        [
            np.stack(
                [
                    np.where(c & 1, hi[:, 0], lo[:, 0]),
                    np.where(c & 2, hi[:, 1], lo[:, 1]),
                    np.where(c & 4, hi[:, 2], lo[:, 2]),
                ],
                axis=1,
            )
            for c in range(8)
        ],
        axis=1,
    )  # (M, 8, 3)
    p = (corners - T[:3, 3]) @ T[:3, :3]  # optical frame
    k = cam.intrinsics()
    tx = max(k[0, 2], (cam.cols - 1) - k[0, 2]) / k[0, 0] * 1.02 + 1e-6
    ty = max(k[1, 2], (cam.rows - 1) - k[1, 2]) / k[1, 1] * 1.02 + 1e-6
    x, y, z = p[..., 0], p[..., 1], p[..., 2]
    outside = (
        (z <= 0).all(axis=1)
        | (x - tx * z > 0).all(axis=1)
        | (-x - tx * z > 0).all(axis=1)
        | (y - ty * z > 0).all(axis=1)
        | (-y - ty * z > 0).all(axis=1)
    )
    # Nearest point of each box to the camera vs the longest in-range ray (+20 % for noise).
    gap = np.maximum(np.maximum(lo - T[:3, 3], T[:3, 3] - hi), 0.0)
    far = np.linalg.norm(gap, axis=1) > 1.2 * cam.max_range * math.sqrt(1 + tx * tx + ty * ty)
    return np.nonzero(~(outside | far))[0]


def depth_to_points(depth: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Organised depth ``(H, W)`` -> ``(H*W, 3)`` optical-frame points; NaN depth stays NaN."""
    z = np.asarray(depth, dtype=np.float64)
    h, w = z.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    pts = np.empty((h * w, 3))
    pts[:, 0] = ((u - K[0, 2]) / K[0, 0] * z).ravel()
    pts[:, 1] = ((v - K[1, 2]) / K[1, 1] * z).ravel()
    pts[:, 2] = z.ravel()
    return pts
