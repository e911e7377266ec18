"""Small geometry shared by the mapper's floor search and the grid's ``--level`` (numpy only)."""

from __future__ import annotations

import math

import numpy as np


def fit_plane(points: np.ndarray, up: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares plane ``n . p + d = 0`` through ``points``, its unit normal ``n`` kept on
    ``up``'s side (a floor's normal points up whichever way the SVD returns it)."""
    c = points.mean(axis=0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    n = vt[2]
    if n @ up < 0:
        n = -n
    return n, float(-n @ c)


def angle_deg(u: np.ndarray, v: np.ndarray) -> float:
    """The angle between unit vectors ``u`` and ``v``, in degrees."""
    return math.degrees(math.acos(float(np.clip(u @ v, -1.0, 1.0))))
