"""Offline loop closure: a pose graph over submaps, optimised once the whole scan is in (ROS-free).

Frame-to-map ICP (:mod:`.registration`) follows its own map: where the chair comes back to a
place it saw long ago along another row, the map it registers against already carries the
drift of the way there, and the narrow iPhone view rarely constrains enough directions to pull
it back. A pose graph is the standard cure (Open3D's multiway registration, rtabmap's graph):

* the accepted frames are cut into consecutive *submaps* of ``submap_seconds`` each (time,
  not a frame count, so a 30 fps capture does not make a graph of thousands of tiny, fully
  overlapping submaps), each a small cloud in the frame of its first sensor pose (the node);
* *odometry edges* join consecutive nodes with the online relative pose, trusted to
  ``odometry_sigma`` / ``odometry_sigma_deg`` per step;
* *loop edges* join every other pair of submaps that overlap: multi-scale point-to-plane ICP
  from the current relative pose. An edge keeps only the part of its correction that the
  overlap's geometry observes (point-to-plane information, as in
  :func:`.registration.constrain_to_observable`: two views of a floor and one wall cannot fix
  sliding along the wall), its information matrix is zero along the rest, and it is refused
  when the overlap is small or the correction larger than drift can explain. Once the map's
  up direction is known (``up``), an edge also leaves height, roll and pitch alone
  (``horizontal_only``): the online mapper levels every frame on the floor, which fixes those
  absolutely, while a loop edge between two narrow views only knows them to centimetres; and
  its overlap counts *structure* only (walls, legs, edges): two views of the same floor
  overlap by half and fix nothing a loop edge is there for;
* Open3D's Levenberg-Marquardt global optimisation with a line process (loop edges are
  "uncertain", so a wrong one is switched off instead of bending the map). The line process
  weighs a residual by the edge's information, so a weak wrong edge (one far wall, at a
  grazing angle) slips through: after each solve, the edge the solution disagrees with most,
  in metres along what it observes, is dropped while that exceeds ``max_loop_residual``, and
  the graph solved again (RTAB-Map rejects loop closures by optimisation error the same way);
* every frame's pose is corrected by its node's correction, interpolated between nodes;
* with ``up`` known, *drift passes*: a visual-inertial pose prior (ARKit) drifts mostly in two
  slow, systematic ways, a scale error and a yaw rate, both per metre travelled. Odometry edges
  with a fixed sigma per step cannot express a bias shared by every step: the graph spreads a
  loop's correction thinly and leaves half of a yaw drift in place. So the corrections the
  graph made are fitted with one scale and one yaw-per-metre term, the online trajectory is
  re-integrated without them (:func:`undrift`), and the graph is solved again on the same loop
  edges, until the estimate is negligible or ``drift_passes`` is reached;
* with the prior's poses given (``prior_drift``): a run's first leg may share no loop with
  the rest, and then no graph can see the yaw online ICP kept of the prior's drift there. The
  loops measure the prior's own drift per metre (:func:`prior_yaw_drift`: any two looped nodes
  will do, not only a loop back to the start) and how much its heading wanders beside that;
  from the next solve on, every step on which online ICP measurably kept a share of that drift
  (:func:`kept_drift`) gets a second edge, the prior's turn with the drift taken out
  (:class:`PriorYaw`, trusted to its wander), and the odometry edge's turn there is trusted
  less by the share ICP kept. Where loops reach, they still decide;
* with ``up`` known, the room's *right angles* (``manhattan``): every submap's vertical
  surfaces, read modulo 90 deg about its node, give it a yaw edge to one free right-angle
  frame node (:class:`RightAngles`); and its *walls* (``walls``) give it point-to-plane
  edges to the submap that sees the same wall best (:class:`Walls`), in one last solve after
  the drift passes.

Measured on ten simulated runs (``make bench``, README): the map share within 5 cm of a true
surface went from 74-94 % online to 81-98 % (see the README for the current figures).
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any, TypeVar

import numpy as np

from wheelgrid_common.params import check_bounds, check_finite, field

from .preprocess import MIN_VOXEL, voxel_downsample
from .se3 import exp_se3, log_se3, rotation_angle_deg, transform


@dataclass
class LoopClosureConfig:
    """Pose-graph refinement after mapping (YAML section ``loop_closure``; ``wheelgrid map``)."""

    enabled: bool = field(True, "optimise a pose graph with loop edges once all frames are in", "")
    submap_seconds: float = field(
        2.0,
        "time a submap (one pose-graph node) spans: 10 frames at 5 Hz, 60 at an iPhone's 30 fps",
        "s",
    )
    submap_voxel: float = field(
        0.04, "voxel of the submap clouds the loop ICP aligns", "m", bounds=(MIN_VOXEL, math.inf)
    )
    normal_radius: float = field(0.15, "radius of the submap normals (point-to-plane ICP)", "m")
    min_overlap: float = field(
        0.1,
        "share of a submap's points within 3 cm of the other after ICP for a loop edge; once the "
        "map's up is known, of its structure points only (normals within 60 deg of horizontal: "
        "walls, legs, table edges; the floor fixes none of x, y, yaw)",
        "",
    )
    max_correction: float = field(
        0.3, "a loop edge that moves its pair more than this is refused (not drift)", "m"
    )
    max_correction_deg: float = field(5.0, "same, for rotation", "deg")
    observable_ratio: float = field(
        0.05,
        "motion directions the overlap constrains with less than this share of the best "
        "constrained one (rotations scaled by the submap radius) get no correction and no "
        "weight",
        "",
    )
    odometry_sigma: float = field(
        0.01, "trust in the online relative pose between consecutive nodes", "m"
    )
    odometry_sigma_deg: float = field(0.1, "same, for rotation", "deg")
    loop_sigma: float = field(
        0.005,
        "a loop edge weighs like a measurement this precise along each direction it observes",
        "m",
    )
    edge_prune_threshold: float = field(
        0.25, "Open3D line-process weight under which a loop edge is dropped", ""
    )
    max_loop_residual: float = field(
        0.05,
        "a loop edge the solved graph still disagrees with by more than this, along the "
        "directions it observes (rotation taken at the submap radius), is dropped and the graph "
        "solved again, worst first (RTAB-Map's RGBD/OptimizeMaxError); 0 = keep every edge",
        "m",
    )
    horizontal_only: bool = field(
        True,
        "loop edges correct only x, y and yaw of the levelled map (the floor already fixes "
        "height, roll and pitch of every frame online)",
        "",
    )
    drift_passes: int = field(
        3,
        "pose-graph solves at most; between two, the odometry's scale and yaw-per-metre drift "
        "is estimated from the graph's corrections and removed (needs the map's up and "
        "horizontal_only; 1 = a single solve)",
        "",
    )
    drift_min_edges: int = field(
        5,
        "loop edges the first solve must keep before a drift is estimated (two numbers from one "
        "loop would fit its noise)",
        "",
    )
    max_drift_scale: float = field(
        0.05, "a larger estimated scale error is not believed: the passes stop", ""
    )
    max_drift_deg_per_m: float = field(
        2.0, "a larger estimated yaw drift is not believed: the passes stop", "deg/m"
    )
    prior_drift: bool = field(
        True,
        "with the pose prior's poses given: after the first solve, measure the prior's yaw drift "
        "per metre and its wander with the loop edges, then give every step on which online ICP "
        "measurably kept a share of that drift the prior's turn with the drift taken out, "
        "beside the odometry's (trusted less by the share kept), so stretches no loop reaches "
        "(a run's first leg) are turned right too",
        "",
    )
    manhattan: bool = field(
        True,
        "with the map's up known: read each submap's walls, legs and edges modulo 90 deg (a room's "
        "right angles) and give every submap whose reading agrees with the others' a yaw edge to "
        "one free right-angle frame, so a heading error no loop reaches (a run's first leg) is "
        "turned back too; not used where too few submaps agree (a room without right angles)",
        "",
    )
    manhattan_gate_deg: float = field(
        5.0,
        "a submap whose vertical surfaces read farther than this from the right-angle frame the "
        "submaps agree on gets no yaw edge (a wall at another angle, furniture askew)",
        "deg",
    )
    manhattan_sigma_deg: float = field(
        0.3,
        "a right-angle reading is trusted to its points' scatter and never beyond this: how far "
        "a room's walls may be from square, and the reading from its walls",
        "deg",
    )
    manhattan_odometry_sigma_deg: float = field(
        0.3,
        "with the right angles in the graph, the online turn between consecutive submaps about "
        "up is trusted to this instead of odometry_sigma_deg (roll and pitch keep that): the "
        "right angles hold the heading, and online ICP's turn over a 2 s step was 0.2-0.6 deg "
        "off on the simulated runs",
        "deg",
    )
    manhattan_min_share: float = field(
        0.5,
        "share of the submaps with a reading that must agree on one right-angle frame (within "
        "manhattan_gate_deg) before any yaw edge is used",
        "",
    )
    walls: bool = field(
        True,
        "with the right angles in use: every submap's walls (vertical planes square to them, at "
        "least a metre across and up) become point-to-plane edges to the submap that sees the "
        "same wall best, in the last solve after the drift passes, so a wall seen from the "
        "start and again from the far end of a run ties the two along its normal where no loop "
        "edge overlaps them (thirty simulated runs: Table I 9(a) under 1 % on 23 instead of 20, "
        "worst position RMSE 3.53 instead of 4.24 cm; docs/mapping-fidelity.md)",
        "",
    )
    wall_sigma: float = field(
        0.01,
        "a wall's offset in a submap is trusted to its points' scatter and never beyond this "
        "(read at the TRUE poses, one wall's offsets from different submaps disagreed by up "
        "to 0.8 cm on the simulated runs)",
        "m",
    )
    wall_min_points: int = field(
        500, "points (at submap_voxel) a plane needs in a submap to count as a wall", ""
    )
    wall_seconds: float = field(
        0.4,
        "walls are read from the frames this close to a node in time: the online poses of a "
        "whole submap's frames are centimetres off its node's",
        "s",
    )
    wall_gate: float = field(
        0.1,
        "planes of two submaps farther apart than this in the map (after a solve without the "
        "walls) are two walls",
        "m",
    )
    prior_scale_sigmas: float = field(
        3.0,
        "with a pose prior: where online ICP measured the prior's scale error (its corrections "
        "along the steps whose direction the view constrains) at least this many standard "
        "errors from 0, every kept frame is registered again with the prior's horizontal steps "
        "rescaled before the graph is built, so stretches where the view fixed no forward motion "
        "(driving along a row) lose the prior's scale error too (0 = off)",
        "",
    )

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """ValueError for settings that cannot work.

        A NaN passes every range test written as a failing comparison: ``odometry_sigma:
        .nan`` made every edge's weight NaN, and the solve then pruned every loop edge without
        a word, and a negative ``max_correction`` refused every one of them."""
        check_finite(self, "loop_closure ")
        check_bounds(self, "loop_closure ")
        for name in (
            "max_correction", "max_correction_deg", "edge_prune_threshold", "max_drift_scale",
            "max_drift_deg_per_m", "max_loop_residual",
        ):  # fmt: skip
            if getattr(self, name) < 0:
                raise ValueError(f"loop_closure {name} must be >= 0, not {getattr(self, name)}")
        if not 0.0 <= self.observable_ratio <= 1.0:
            raise ValueError(
                f"loop_closure observable_ratio must be in [0, 1], not {self.observable_ratio}"
            )
        if self.prior_scale_sigmas < 0:
            raise ValueError(
                f"loop_closure prior_scale_sigmas must be >= 0 (0 = off), not "
                f"{self.prior_scale_sigmas}"
            )
        for name in (
            "submap_seconds",
            "submap_voxel",
            "normal_radius",
            "odometry_sigma",
            "odometry_sigma_deg",
            "loop_sigma",
        ):
            if getattr(self, name) <= 0:
                raise ValueError(f"loop_closure {name} must be > 0, not {getattr(self, name)}")
        if self.drift_passes < 1:
            raise ValueError(f"loop_closure drift_passes must be >= 1, not {self.drift_passes}")
        if not 0.0 < self.manhattan_gate_deg < 45.0:
            raise ValueError(
                f"loop_closure manhattan_gate_deg must be in (0, 45), not {self.manhattan_gate_deg}"
            )
        if not self.manhattan_odometry_sigma_deg > 0.0:
            raise ValueError(
                "loop_closure manhattan_odometry_sigma_deg must be > 0, not "
                f"{self.manhattan_odometry_sigma_deg}"
            )
        if not self.manhattan_sigma_deg > 0.0:
            raise ValueError(
                f"loop_closure manhattan_sigma_deg must be > 0, not {self.manhattan_sigma_deg}"
            )
        if not 0.0 <= self.manhattan_min_share <= 1.0:
            raise ValueError(
                f"loop_closure manhattan_min_share must be in [0, 1], not "
                f"{self.manhattan_min_share}"
            )
        for name in ("wall_sigma", "wall_seconds", "wall_gate"):
            if not getattr(self, name) > 0.0:
                raise ValueError(f"loop_closure {name} must be > 0, not {getattr(self, name)}")
        if self.wall_min_points < 3:
            raise ValueError(
                f"loop_closure wall_min_points must be >= 3, not {self.wall_min_points}"
            )
        if not 0.0 < self.min_overlap <= 1.0:
            raise ValueError(f"loop_closure min_overlap must be in (0, 1], not {self.min_overlap}")


@dataclass
class LoopClosureResult:
    """Corrected poses and what the graph did (goes into report.json)."""

    poses: list[np.ndarray]
    nodes: int = 0
    candidates: int = 0
    loop_edges: int = 0
    refused: dict[str, int] = dc_field(default_factory=dict)
    pruned: int = 0
    rejected: int = 0  # loop edges dropped for disagreeing with the solved graph
    max_shift_m: float = 0.0
    max_turn_deg: float = 0.0
    passes: int = 0
    drift_scale: float = 0.0  # estimated odometry scale error removed (0.01 = 1 % too long)
    drift_deg_per_m: float = 0.0  # estimated yaw drift removed, per metre travelled
    drift_note: str = ""
    prior_drift_deg_per_m: float | None = None  # the prior's yaw drift found by its loops
    prior_walk_deg_per_sqrt_s: float | None = None  # its heading's random walk beyond that
    prior_steps: int = 0  # steps between nodes given the prior's turn (ICP kept its drift)
    prior_drift_note: str = ""
    manhattan_nodes: int = 0  # submaps given a yaw edge to the right-angle frame (last solve)
    manhattan_note: str = ""
    wall_count: int = 0  # walls seen from two submaps or more (``walls``)
    wall_edges: int = 0  # point-to-plane edges they gave
    seconds: float = 0.0
    node_frames: list[int] = dc_field(default_factory=list)  # each node's first frame
    edges: list[LoopEdge] = dc_field(default_factory=list)  # measured, in the last solve

    def summary(self) -> dict[str, Any]:
        return {
            "nodes": self.nodes,
            "candidate_pairs": self.candidates,
            "loop_edges": self.loop_edges,
            "loop_edges_pruned": self.pruned,
            "loop_edges_rejected": self.rejected,
            "loop_edges_kept": self.loop_edges - self.pruned - self.rejected,
            "refused": dict(self.refused),
            "max_pose_shift_m": round(self.max_shift_m, 4),
            "max_pose_turn_deg": round(self.max_turn_deg, 3),
            "passes": self.passes,
            "drift_scale_pct": round(100.0 * self.drift_scale, 3),
            "drift_yaw_deg_per_m": round(self.drift_deg_per_m, 4),
            **({"drift_note": self.drift_note} if self.drift_note else {}),
            **(
                {"prior_drift_deg_per_m": round(self.prior_drift_deg_per_m, 4)}
                if self.prior_drift_deg_per_m is not None
                else {}
            ),
            **(
                {"prior_walk_deg_per_sqrt_s": round(self.prior_walk_deg_per_sqrt_s, 4)}
                if self.prior_walk_deg_per_sqrt_s is not None
                else {}
            ),
            **({"prior_steps": self.prior_steps} if self.prior_steps else {}),
            **({"prior_drift_note": self.prior_drift_note} if self.prior_drift_note else {}),
            "manhattan_nodes": self.manhattan_nodes,
            **(
                {"walls": self.wall_count, "wall_edges": self.wall_edges} if self.wall_edges else {}
            ),
            **({"manhattan_note": self.manhattan_note} if self.manhattan_note else {}),
            "seconds": round(self.seconds, 3),
        }


def closed_note(lc: dict[str, Any]) -> str:
    """One line on what closing the loops did, from :meth:`.pipeline.Mapper.close_loops`'s
    summary. The mapper node's diagnostics, its log and its answer to a repeated
    ``~/close_loops`` say it, so a user watching a live scan learns there, not only from
    report.json, that its frames were registered again for the prior's scale."""
    note = (
        f"{lc['loop_edges_kept']} loop edges kept of {lc['loop_edges']} over "
        f"{lc['nodes']} submaps, poses moved <= {lc['max_pose_shift_m'] * 100:.1f} cm / "
        f"{lc['max_pose_turn_deg']:.2f} deg, {lc['seconds']:.1f} s"
    )
    if lc.get("manhattan_nodes"):
        note += f", {lc['manhattan_nodes']} submaps held to the room's right angles"
    ps = lc.get("prior_scale")
    if ps and ps["applied"]:
        note += (
            f", the prior's scale error ({ps['measured_pct']:+.2f} % as ICP measured it) removed"
        )
    return note


# A loop edge: source and target node, ICP result, its information and the horizontal projector.
Edge = tuple[int, int, np.ndarray, np.ndarray, np.ndarray | None]


@dataclass(frozen=True)
class LoopEdge:
    """A loop edge as the last solve saw it: what its ICP measured and whether the graph kept
    it. Nothing downstream needs it; it is there so that a benchmark with the true poses can
    tell an edge's own error from the graph's (``bench_mapping.py --loop-edges``)."""

    source: int  # node
    target: int  # node
    transformation: np.ndarray  # 4x4: the ICP result, source node frame -> target node frame
    information: np.ndarray  # 6x6, [omega, t], source frame (horizontal part with ``up``)
    projector: np.ndarray | None  # 6x6 onto yaw and horizontal translation, or None
    radius: float  # m, RMS distance of the source submap's points from its node
    kept: bool  # the line process and the residual test left it in the graph

    def observed_error(self, T: np.ndarray, true: np.ndarray, ratio: float) -> float:
        """How far (m) a relative pose ``T`` of the edge's nodes lies from the ``true`` one
        along the directions the edge observes, its rotation taken at the submap radius."""
        return _observed_distance(
            np.linalg.inv(true) @ T, self.information, self.projector, self.radius, ratio
        )


def observable_part(
    H: np.ndarray, x: np.ndarray, radius: float, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """Project a ``[omega, t]`` correction onto the directions information ``H`` constrains.

    ``H`` (6x6, rotation first like Open3D's pose graph) is normalised by the submap radius so
    that a rotation and a translation that move the points equally compare equally; returns the
    projected correction and ``H`` with its unobserved directions zeroed.
    """
    s = np.r_[np.full(3, radius), np.ones(3)]
    Hn = H / np.outer(s, s)
    vals, vecs = np.linalg.eigh(Hn)
    keep = vals >= ratio * max(float(vals.max()), 1e-12)
    x_kept = (vecs @ (keep * (vecs.T @ (x * s)))) / s
    H_kept = (vecs * (vals * keep)) @ vecs.T * np.outer(s, s)
    return x_kept, H_kept


def _point_to_plane_information(
    src: Any, tgt: Any, T: np.ndarray, dist: float, up: np.ndarray | None = None
) -> tuple:
    """Point-to-plane information of ``src`` aligned onto ``tgt`` by ``T``, in ``src``'s frame,
    and the overlap: the share of ``src``'s points within ``dist`` of ``tgt``.

    Open3D's pose graph linearises an edge's misalignment as ``X^-1 Tt^-1 Ts``, a motion of the
    *source* node, so its information matrix must be expressed in the source frame: Jacobian
    rows ``[p x n, n]`` with ``p`` a source point and ``n`` its target normal rotated into the
    source frame. (In the target frame, the lever arm between two submaps metres apart leaks a
    zeroed direction's weight into others.)

    With ``up`` (the source frame's up), only *structure* counts for the overlap: surfaces whose
    normal is within 60 deg of horizontal, the walls, legs and table edges that fix x, y and
    yaw. The overlap is then the correspondences onto such a target surface (the ones that
    carry that information) per structure point of the source, and under 50 of them make no
    edge. Two views of the same floor overlap by half and constrain none of those; two views
    of one table row from its two ends overlap by a tenth and fix them well.
    """
    import open3d as o3d

    ev = o3d.pipelines.registration.evaluate_registration(src, tgt, dist, T)
    c = np.asarray(ev.correspondence_set)
    if c.shape[0] < 50:
        return None, ev.fitness
    p = np.asarray(src.points)[c[:, 0]]
    n = np.asarray(tgt.normals)[c[:, 1]] @ T[:3, :3]
    overlap = ev.fitness
    if up is not None:
        structure = np.abs(np.asarray(src.normals) @ up) < 0.5
        matched = np.abs(n @ up) < 0.5
        if int(matched.sum()) < 50:
            return None, 0.0
        overlap = float(matched.sum()) / max(int(structure.sum()), 1)
    J = np.hstack([np.cross(p, n), n])
    return J.T @ J / c.shape[0], overlap


def submap_groups(stamps: Sequence[float], seconds: float) -> list[list[int]]:
    """Consecutive frame indices, a new group once ``seconds`` have passed since its first."""
    groups: list[list[int]] = []
    for i, t in enumerate(stamps):
        if not groups or t - stamps[groups[-1][0]] >= seconds:
            groups.append([])
        groups[-1].append(i)
    return groups


def submap(
    frames: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    group: Sequence[int],
    cfg: LoopClosureConfig,
    origin: int | None = None,
) -> tuple[Any, float]:
    """The submap of frames ``group`` placed at ``poses``, in the frame of its first pose
    (the node; or of frame ``origin``): an Open3D cloud on ``cfg.submap_voxel`` with normals
    for point-to-plane ICP, and its points' RMS distance from the node (m; 1 for an empty
    one), which scales rotation against translation in the edge's information."""
    import open3d as o3d

    a_inv = np.linalg.inv(poses[group[0] if origin is None else origin])
    pts = np.vstack([transform(np.asarray(frames[i], np.float64), a_inv @ poses[i]) for i in group])
    pts = voxel_downsample(pts, cfg.submap_voxel)
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    pc.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(cfg.normal_radius, 30))
    radius = float(np.sqrt((pts**2).sum(axis=1).mean())) if pts.size else 1.0
    return pc, radius


def _about_node(
    frames: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    stamps: Sequence[float],
    node: int,
    half: float,
    cfg: LoopClosureConfig,
) -> Any:
    """The submap of the frames within ``half`` seconds either side of frame ``node``, in its
    frame: what a node's own heading and walls are read from. No farther than the run goes on
    both sides, so the errors about the node stay balanced (the first node, with frames on one
    side only, reads from its own frame)."""
    t = np.asarray(stamps, dtype=np.float64)
    half = min(half, t[node] - t[0], t[-1] - t[node])
    near = np.flatnonzero(np.abs(t - t[node]) <= half + 1e-9)
    return submap(frames, poses, list(near), cfg, origin=node)[0]


def _yaw_and_horizontal(g: np.ndarray) -> np.ndarray:
    """Projector (6 x 6, rotation then translation, in a node's frame) onto the rotation about
    ``g`` (up in that frame) and the translation normal to it: what an edge may correct once
    the floor fixes height, roll and pitch of every frame."""
    S = np.zeros((6, 6))
    S[:3, :3] = np.outer(g, g)
    S[3:, 3:] = np.eye(3) - np.outer(g, g)
    return S


def loop_icp(src: Any, tgt: Any, init: np.ndarray) -> np.ndarray:
    """Multi-scale (20, 10, 5 cm) point-to-plane ICP of submap ``src`` onto ``tgt`` from
    ``init``: the loop edge's measurement, before its unobserved part is dropped."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    est = reg.TransformationEstimationPointToPlane()
    crit = reg.ICPConvergenceCriteria(max_iteration=30)
    T = np.asarray(init, dtype=np.float64)
    for d in (0.2, 0.1, 0.05):
        T = reg.registration_icp(src, tgt, d, T, est, crit).transformation
    return np.asarray(T)


def close_loops(
    frames: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    stamps: Sequence[float],
    cfg: LoopClosureConfig | None = None,
    progress: Callable[[int, int], None] | None = None,
    up: np.ndarray | None = None,
    priors: Sequence[np.ndarray] | None = None,
) -> LoopClosureResult:
    """Corrected sensor poses for ``frames`` (sensor-frame points) registered at ``poses`` at
    times ``stamps`` (seconds).

    ``poses[0]`` stays where it is (the graph's reference node), so the levelled map frame found
    from it keeps its meaning. ``up`` is the levelled map's z axis in the poses' frame; with it
    (and ``cfg.horizontal_only``) loop edges correct only x, y and yaw, and up to
    ``cfg.drift_passes`` solves remove the odometry's scale and yaw drift. ``priors`` are the
    pose prior's poses of the same frames (any fixed frame, e.g. ARKit's world): with them
    (and ``cfg.prior_drift``) the loops measure the prior's yaw drift per metre after the
    first solve, and later solves give the prior's drift-corrected turn to every step on which
    online ICP measurably kept that drift. ``progress(done, total)`` is called once per submap
    whose loop edges are done, and with the count so far before each submap is built and each
    loop ICP: the mapper node cancels by raising from it (~/reset, Ctrl-C), and called only
    per node it came after every submap was built and every ICP of the first node (11 s on
    the bundled 210-frame bag, minutes on a long scan), and a node stopped meanwhile exited
    without saving its map.
    """
    import open3d as o3d

    cfg = cfg or LoopClosureConfig()
    cfg.validate()
    t0 = time.perf_counter()
    reg = o3d.pipelines.registration
    P = [np.asarray(p, dtype=np.float64) for p in poses]
    n = len(P)
    out = LoopClosureResult(poses=[p.copy() for p in P])
    if len(stamps) != n or len(frames) != n:
        raise ValueError("close_loops: frames, poses and stamps differ in length")
    if priors is not None and len(priors) != n:
        raise ValueError("close_loops: priors and poses differ in length")
    groups = submap_groups([float(t) for t in stamps], cfg.submap_seconds)
    out.nodes = len(groups)
    out.node_frames = [g[0] for g in groups]
    if len(groups) < 3:
        out.seconds = time.perf_counter() - t0
        return out
    anchors = [P[g[0]] for g in groups]
    g_up = None
    if up is not None and cfg.horizontal_only:
        g_up = np.asarray(up, dtype=np.float64) / float(np.linalg.norm(up))
    subs, radii, boxes = [], [], []
    for g, a in zip(groups, anchors, strict=True):
        if progress is not None:  # a cancel point
            progress(0, len(groups))
        pc, radius = submap(frames, P, g, cfg)
        pts = np.asarray(pc.points)
        subs.append(pc)
        radii.append(radius)
        world = transform(pts, a) if pts.size else np.zeros((1, 3))
        boxes.append((world.min(axis=0), world.max(axis=0)))
    right = None
    if g_up is not None and cfg.manhattan:
        readings = []
        for g, a in zip(groups, anchors, strict=True):
            if progress is not None:  # a cancel point
                progress(0, len(groups))
            # the frames within half a submap either side of the node: their headings' errors
            # about the node's average out, so the reading is the node's own, not its
            # submap's, which runs a node ahead of it
            pc = _about_node(frames, P, stamps, g[0], 0.5 * cfg.submap_seconds, cfg)
            readings.append(right_angle_reading(wide_normals(pc), a[:3, :3].T @ g_up))
        right = RightAngles(
            readings,
            math.radians(cfg.manhattan_gate_deg),
            cfg.manhattan_min_share,
            math.radians(cfg.manhattan_sigma_deg) ** 2,
        )
        if not right.frame(anchors, g_up)[1]:
            out.manhattan_note, right = right.note, None
    # Loop edges: ICP between overlapping submaps, once. ``T`` is the ICP result, ``H`` its
    # information (source frame, horizontal part only when ``up`` is known), ``S`` that
    # projector: later passes re-read the same measurement against the undrifted guess.
    edges: list[Edge] = []
    refused = out.refused
    for i in range(len(groups)):
        for j in range(i + 2, len(groups)):
            lo = np.maximum(boxes[i][0], boxes[j][0])
            hi = np.minimum(boxes[i][1], boxes[j][1])
            if np.any(hi - lo < 0.2):
                continue
            init = np.linalg.inv(anchors[j]) @ anchors[i]
            pre = reg.evaluate_registration(subs[i], subs[j], 0.1, init)
            if pre.fitness < 0.5 * cfg.min_overlap:
                continue
            out.candidates += 1
            if progress is not None:  # a cancel point
                progress(i, len(groups))
            T = loop_icp(subs[i], subs[j], init)
            g_i = anchors[i][:3, :3].T @ g_up if g_up is not None else None
            H, fitness = _point_to_plane_information(subs[i], subs[j], T, 0.03, g_i)
            if H is None or fitness < cfg.min_overlap:
                refused["low overlap"] = refused.get("low overlap", 0) + 1
                continue
            S = None
            if g_i is not None:
                # the graph then keeps the online height, roll and pitch
                S = _yaw_and_horizontal(g_i)
                H = S @ H @ S
            xo, _, _ = _edge_measurement(init, T, H, S, radii[i], cfg.observable_ratio)
            shift = float(np.linalg.norm(xo[3:]))
            turn = math.degrees(float(np.linalg.norm(xo[:3])))
            if shift > cfg.max_correction or turn > cfg.max_correction_deg:
                refused["correction too large"] = refused.get("correction too large", 0) + 1
                continue
            edges.append((i, j, np.asarray(T), H, S))
        if progress is not None:
            progress(i + 1, len(groups))
    out.loop_edges = len(edges)
    if not edges:
        out.seconds = time.perf_counter() - t0
        return out

    # Every submap's walls, read about its node at its online pose, once there are loop edges
    # to solve with (the walls join the last solve only, after the passes below).
    walls = None
    if right is not None and cfg.walls and g_up is not None:  # (right needs g_up: for mypy)
        planes: list[list[WallPlane]] = []
        for k, g in enumerate(groups):
            r = right.readings[k]
            if r is None:
                planes.append([])
                continue
            if progress is not None:  # a cancel point
                progress(len(groups), len(groups))
            a = P[g[0]]
            pc = _about_node(frames, P, stamps, g[0], cfg.wall_seconds, cfg)
            planes.append(
                wall_planes(pc, a[:3, :3].T @ g_up, r[0], cfg.wall_min_points, cfg.wall_sigma)
            )
        walls = Walls(planes, cfg.wall_gate, cfg.manhattan_gate_deg)

    current = P
    length = float(path_length(P, g_up)[-1]) if g_up is not None else 0.0
    prior_yaw: PriorYaw | None = None
    for k in range(cfg.drift_passes):
        anchors = [current[g[0]] for g in groups]
        nodes, kept, rejected = solve_rejecting(anchors, edges, radii, cfg, prior_yaw, g_up, right)
        out.rejected += rejected
        out.pruned = len(edges) - len(kept)
        out.passes = k + 1
        corrected = _interpolate(groups, anchors, nodes, current)
        if k + 1 == cfg.drift_passes or g_up is None:
            break
        if k == 0 and priors is not None and cfg.prior_drift:
            measured = [(i, j, T) for i, j, T, _, _ in edges if (i, j) in kept]
            prior_yaw = _prior_yaw(
                out, cfg, groups, measured, priors, current, stamps, g_up, right is not None
            )
            if prior_yaw is not None:
                continue  # solve again with the prior's turns beside the odometry's
        if len(kept) < cfg.drift_min_edges:
            out.drift_note = (
                f"{len(kept)} loop edges kept, < {cfg.drift_min_edges}: no drift estimate"
            )
            break
        scale, yaw = estimate_drift(anchors, nodes, g_up)
        if abs(scale) > cfg.max_drift_scale or abs(math.degrees(yaw)) > cfg.max_drift_deg_per_m:
            out.drift_note = (
                f"drift estimate not believed ({100 * scale:+.2f} % scale, "
                f"{math.degrees(yaw):+.3f} deg/m): passes stopped"
            )
            break
        if abs(scale) * length < 0.005 and abs(yaw) * length < math.radians(0.05):
            break  # re-integrating would move the last pose by < 5 mm and 0.05 deg
        current = undrift(current, scale, yaw, g_up)
        out.drift_scale = (1.0 + out.drift_scale) * (1.0 + scale) - 1.0
        out.drift_deg_per_m += math.degrees(yaw)
    if walls is not None:
        # The walls join the last solve only, on the undrifted anchors, grouped on that graph
        # solved without them. Online headings can be degrees off (one simulated run's last
        # nodes: 4 deg), which moves a wall 4 m away by decimetres; and in every pass they pull
        # the drift fit between passes (on one run its scale read 0.022 % instead of 0.105 %)
        # and the map went wrong by 4 cm (docs/mapping-fidelity.md).
        walls.associate(nodes)
        nodes, kept, rejected = solve_rejecting(
            anchors, edges, radii, cfg, prior_yaw, g_up, right, walls
        )
        out.rejected += rejected
        out.pruned = len(edges) - len(kept)
        corrected = _interpolate(groups, anchors, nodes, current)
    out.poses = corrected
    if right is not None:
        out.manhattan_nodes, out.manhattan_note = right.used, right.note
    if walls is not None:
        out.wall_count, out.wall_edges = walls.used, walls.edges_used
    out.edges = [LoopEdge(i, j, T, H, S, radii[i], (i, j) in kept) for i, j, T, H, S in edges]
    for p, q in zip(P, corrected, strict=True):
        out.max_shift_m = max(out.max_shift_m, float(np.linalg.norm(q[:3, 3] - p[:3, 3])))
        out.max_turn_deg = max(out.max_turn_deg, rotation_angle_deg(np.linalg.inv(p) @ q))
    out.seconds = time.perf_counter() - t0
    return out


@dataclass
class PriorYaw:
    """The pose prior's turn between consecutive nodes, its drift measured by the loops: a
    second measurement of each step's heading change, independent of online ICP's.

    A visual-inertial prior's heading error is a drift per metre plus a random walk
    (:mod:`wheelgrid_sim.odometry` models ARKit so). With the drift known, the prior's turn
    from node i to i+1, less ``rate`` times the distance between them, is right to within the
    walk over that time. Online ICP starts from the prior and, where the view constrains yaw
    weakly, keeps part of its drift: its turn over the same step is off by up to ``rate`` times
    the distance, a bias no loop sees on a stretch no loop reaches (a run's first leg). So the
    graph gets both, each weighted by what can be wrong with it."""

    nodes: list[np.ndarray]  # the prior's poses at the nodes
    travelled: np.ndarray  # m, distance travelled to each node
    times: np.ndarray  # s, each node's stamp
    rate: float  # rad/m the prior turns too far
    rate_stderr: float  # rad/m
    walk: float  # rad^2/s: variance its heading gains per second beyond the drift
    kept: np.ndarray | None = None  # per step: share of the drift online ICP kept (None: all)

    def used(self, i: int) -> bool:
        """Whether step i gets the prior's turn: where ICP kept a measurable share of the
        drift (:func:`kept_drift`). Elsewhere the prior's wander would only add noise to a
        turn ICP already got right."""
        return self.kept is None or bool(self.kept[i] > 0.0)

    def turn_variance(self, i: int) -> float:
        """rad^2: how far the drift-corrected prior's turn from node i to i+1 can be wrong."""
        dt = float(self.times[i + 1] - self.times[i])
        dd = float(self.travelled[i + 1] - self.travelled[i])
        return self.walk * dt + (self.rate_stderr * dd) ** 2 + _MIN_TURN_VARIANCE

    def odometry_bias(self, i: int) -> float:
        """rad: how much of the prior's drift online ICP kept from node i to i+1."""
        share = 1.0 if self.kept is None else float(np.clip(self.kept[i], 0.0, 1.0))
        return share * abs(self.rate) * float(self.travelled[i + 1] - self.travelled[i])

    def turn_gap(self, i: int, anchors: Sequence[np.ndarray], up: np.ndarray) -> float:
        """rad: the corrected prior's turn from node i to i+1 less the ``anchors``' own."""
        return self._gap(i, anchors, up)[0]

    def _gap(
        self, i: int, anchors: Sequence[np.ndarray], up: np.ndarray
    ) -> tuple[float, np.ndarray, np.ndarray]:
        g = anchors[i][:3, :3].T @ up
        prior = np.linalg.inv(self.nodes[i + 1]) @ self.nodes[i]
        dd = float(self.travelled[i] - self.travelled[i + 1])
        # prior_yaw_drift: the prior's relative pose is the true one turned by rate (D_i - D_j)
        # about up in node i's frame; undo that, then keep only the turn about up.
        corrected = prior @ exp_se3(np.r_[0.0, 0.0, 0.0, -self.rate * dd * g])
        init = np.linalg.inv(anchors[i + 1]) @ anchors[i]
        return float(log_se3(np.linalg.inv(init) @ corrected)[3:] @ g), init, g

    def edge(self, i: int, anchors: Sequence[np.ndarray], up: np.ndarray) -> PriorEdge:
        """``(T, information)`` of the graph edge from node i to i+1 that turns it as the
        corrected prior does; only the turn about up carries information."""
        turn, init, g = self._gap(i, anchors, up)
        info = np.zeros((6, 6))
        info[:3, :3] = np.outer(g, g) / self.turn_variance(i)
        return init @ exp_se3(np.r_[0.0, 0.0, 0.0, turn * g]), info


#: Radius (m) of the normals a submap's heading is read from (:func:`wide_normals`).
_RIGHT_ANGLE_NORMAL_RADIUS = 0.3
#: Vertical surfaces: normals within this of horizontal (|n . up| below it) carry a heading.
_VERTICAL = 0.2
#: A submap's reading needs this many vertical points agreeing within the window below.
_MIN_RIGHT_ANGLE_POINTS = 100
#: Window (deg) about a submap's right-angle frame in which its points' normals count.
_RIGHT_ANGLE_WINDOW_DEG = 4.0
#: Neighbouring normals share most of their neighbours (Open3D's 30): the points' scatter is
#: worth about one independent reading per this many points.
_NORMALS_PER_READING = 30


def wide_normals(pc: Any) -> np.ndarray:
    """Normals of a submap's points from their neighbours within
    :data:`_RIGHT_ANGLE_NORMAL_RADIUS` (at most 100): for reading headings, not for ICP.

    The loop ICP's 15 cm normals lean with the range noise: a wall seen at a slant, its
    returns scattered 1-3 cm along the rays, tilts a 15 cm patch's normal towards the rays, and
    a submap seen from one side reads its walls 0.1-0.2 deg turned (at the simulated runs' TRUE
    poses; up to 1 deg on some submaps). Over 30 cm the wall's own extent outweighs the noise:
    median 0.03 deg, no mean lean."""
    import open3d as o3d

    wide = o3d.geometry.PointCloud(pc.points)
    wide.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(_RIGHT_ANGLE_NORMAL_RADIUS, 100))
    return np.asarray(wide.normals)


def horizontal_basis(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors that span the plane normal to ``up``: where headings are read."""
    up = np.asarray(up, dtype=np.float64)
    a = np.array([1.0, 0.0, 0.0]) if abs(up[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(up, a)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def _fold(angle: np.ndarray | float) -> np.ndarray | float:
    """An angle modulo 90 deg, in (-45, 45] deg (rad in, rad out): a right-angle frame's."""
    return np.angle(np.exp(4j * np.asarray(angle))) / 4.0


def right_angle_reading(normals: np.ndarray, up: np.ndarray) -> tuple[float, float] | None:
    """``(angle, standard error)`` in rad: the heading, modulo 90 deg, of a submap's vertical
    surfaces in its own frame (about ``up``, from :func:`horizontal_basis`), or None where too
    few of them agree.

    Indoors, walls meet at right angles and furniture mostly stands square to them: the
    normals of a submap's vertical surfaces, folded modulo 90 deg, pile up at one angle. Its
    robust mean (the normals within a few degrees of it) is a heading measurement that does
    not drift: the same wall read from the start and from the far end of a run gives the same
    angle in the map, whatever the odometry did in between. A diagonal wall, a chair askew or
    a leg's noisy normals fall outside the window and do not move it."""
    n = np.asarray(normals, dtype=np.float64)
    n = n[np.abs(n @ up) < _VERTICAL]
    if n.shape[0] < _MIN_RIGHT_ANGLE_POINTS:
        return None
    e1, e2 = horizontal_basis(up)
    z = np.exp(4j * np.arctan2(n @ e2, n @ e1))
    window = math.radians(_RIGHT_ANGLE_WINDOW_DEG)
    m = float(np.angle(z.mean())) / 4.0
    dev = np.zeros(0)
    for _ in range(10):
        dev = np.angle(z * np.exp(-4j * m)) / 4.0
        dev = dev[np.abs(dev) < window]
        if dev.shape[0] < _MIN_RIGHT_ANGLE_POINTS:
            return None
        step = float(dev.mean())
        m += step
        if abs(step) < 1e-6:
            break
    mad = 1.4826 * float(np.median(np.abs(dev - dev.mean())))
    return float(_fold(m)), mad / math.sqrt(dev.shape[0] / _NORMALS_PER_READING)


_T = TypeVar("_T")


def _known(value: _T | None) -> _T:
    """``value``, where the caller has already kept only the submaps that have one."""
    assert value is not None
    return value


@dataclass
class RightAngles:
    """Each submap's right-angle reading (:func:`right_angle_reading`, in its node frame), and
    how they enter the graph: one extra, free node holds the room's right-angle frame, and
    every submap whose reading agrees with it gets a yaw edge to it, weighted by the reading's
    standard error. The frame is a node, not a fixed heading, so the reference node keeps its
    place and the readings decide only how the submaps turn relative to one another: a yaw no
    loop edge reaches (a run's first leg, turned 0.4 deg by the odometry) is turned back."""

    readings: list[tuple[float, float] | None]
    gate: float  # rad
    min_share: float
    floor: float  # rad^2, added to every reading's variance (``manhattan_sigma_deg``)
    used: int = 0  # submaps given an edge in the last solve
    note: str = ""

    def world_angles(self, anchors: Sequence[np.ndarray], up: np.ndarray) -> list[float | None]:
        """Each reading as the heading (rad, about ``up`` in the anchors' frame) it has there."""
        e1, e2 = horizontal_basis(up)
        out: list[float | None] = []
        for a, r in zip(anchors, self.readings, strict=True):
            if r is None:
                out.append(None)
                continue
            g = a[:3, :3].T @ up
            f1, f2 = horizontal_basis(g)
            w = a[:3, :3] @ (math.cos(r[0]) * f1 + math.sin(r[0]) * f2)
            out.append(math.atan2(float(w @ e2), float(w @ e1)))
        return out

    def frame(self, anchors: Sequence[np.ndarray], up: np.ndarray) -> tuple[float, list[int]]:
        """The heading (rad) the readings agree on at ``anchors``, and the submaps within the
        gate of it (weighted robust mean; empty where fewer than ``min_share`` agree)."""
        angles = self.world_angles(anchors, up)
        idx = [k for k, a in enumerate(angles) if a is not None]
        if len(idx) < 3:
            self.note = f"{len(idx)} submaps read their vertical surfaces' heading, < 3"
            return 0.0, []
        a = np.array([angles[k] for k in idx])
        w = np.array([1.0 / (_known(self.readings[k])[1] ** 2 + self.floor) for k in idx])
        # start from the heading most readings lie near (a coarse vote), then refine on those
        votes = [int((np.abs(_fold(a - c)) < self.gate).sum()) for c in a]
        psi = float(a[int(np.argmax(votes))])
        inside = np.zeros(len(a), dtype=bool)
        for _ in range(10):
            inside = np.abs(_fold(a - psi)) < self.gate
            step = float((w[inside] * _fold(a[inside] - psi)).sum() / w[inside].sum())
            psi += step
            if abs(step) < 1e-9:
                break
        share = float(inside.mean())
        if share < self.min_share:
            self.note = (
                f"only {int(inside.sum())} of {len(a)} submaps agree on a right-angle frame "
                f"(< {100 * self.min_share:.0f} %): not used"
            )
            return psi, []
        self.note = ""
        return psi, [k for k, ok in zip(idx, inside, strict=True) if ok]

    def edges(
        self, anchors: Sequence[np.ndarray], up: np.ndarray, rot_var: float, trans_var: float
    ) -> tuple[np.ndarray, list[tuple[int, np.ndarray, np.ndarray]]] | None:
        """The free frame node's starting pose and the graph edges ``(source node, T,
        information)`` to it: its pin to node 0 in everything but yaw (``rot_var``,
        ``trans_var``: the odometry's), then one yaw edge per agreeing submap. None where the
        submaps do not agree."""
        psi, agree = self.frame(anchors, up)
        self.used = len(agree)
        if not agree:
            return None
        frame = exp_se3(np.r_[0.0, 0.0, 0.0, psi * up])
        angles = self.world_angles(anchors, up)
        out = []
        g0 = anchors[0][:3, :3].T @ up
        pin = np.zeros((6, 6))
        pin[:3, :3] = (np.eye(3) - np.outer(g0, g0)) / rot_var
        pin[3:, 3:] = np.eye(3) / trans_var
        out.append((0, np.linalg.inv(frame) @ anchors[0], pin))
        for k in agree:
            rel = np.linalg.inv(frame) @ anchors[k]
            turn = -float(_fold(_known(angles[k]) - psi))  # the frame's axes are e1, e2 too
            target = exp_se3(np.r_[0.0, 0.0, 0.0, turn * up]) @ rel
            g = anchors[k][:3, :3].T @ up
            info = np.zeros((6, 6))
            info[:3, :3] = np.outer(g, g) / (_known(self.readings[k])[1] ** 2 + self.floor)
            out.append((k, target, info))
        return frame, out


_WALL_BIN = 0.02  # m, histogram bin of wall offsets along a right-angle axis
_WALL_HALF_WIDTH = 0.04  # m, points this close to a peak's offset are its candidates
_WALL_COS = math.cos(math.radians(10.0))  # normals within 10 deg of the axis
_WALL_CLEAR = 0.2  # m, no second wall this close to a wall's offset
_WALL_MIN_EXTENT = 1.0  # m, a wall spans at least this across and up


@dataclass(frozen=True)
class WallPlane:
    """A large vertical plane square to the room, seen in one submap (its node frame): unit
    ``normal`` facing the node, ``offset`` (normal . p on the plane, m), the ``centroid`` of its
    points, their count, and the offset's standard error (m)."""

    normal: np.ndarray
    offset: float
    centroid: np.ndarray
    points: int
    sigma: float


def wall_planes(
    pc: Any, up: np.ndarray, angle: float, min_points: int, sigma_floor: float
) -> list[WallPlane]:
    """The walls of a submap: planes square to its right-angle reading ``angle`` (rad, about
    ``up`` in the node frame, :func:`right_angle_reading`) that span at least a metre across
    and up and hold ``min_points``. Found by histogram along the two right-angle axes, each
    side of the node apart (a wall's face towards the node), so no random sampling decides."""
    pts = np.asarray(pc.points, dtype=np.float64)
    nrm = np.asarray(pc.normals, dtype=np.float64)
    if pts.shape[0] < min_points:
        return []
    e1, e2 = horizontal_basis(up)
    a = math.cos(angle) * e1 + math.sin(angle) * e2
    out: list[WallPlane] = []
    for axis in (a, np.cross(up, a)):
        along = np.abs(nrm @ axis) > _WALL_COS
        s_all = pts @ axis
        for side in (1.0, -1.0):
            # a wall stands at least 30 cm from the sensor; its face is the one towards it
            cand = np.flatnonzero(along & (side * s_all > 0.3))
            while cand.shape[0] >= min_points:
                s = s_all[cand]
                lo = float(s.min())
                bins = np.floor((s - lo) / _WALL_BIN).astype(np.int64)
                counts = np.bincount(bins)
                # the densest 8 cm window
                window = np.convolve(counts, np.ones(4, dtype=np.int64), mode="valid")
                if window.size == 0:
                    break
                k = int(np.argmax(window))
                centre = lo + (k + 2) * _WALL_BIN
                near = np.abs(s - centre) <= _WALL_HALF_WIDTH
                if near.sum() < min_points:
                    break
                plane = _fit_wall(pts[cand[near]], up, side * axis, sigma_floor, min_points)
                if plane is None:
                    cand = cand[~near]
                    continue
                out.append(plane)
                # the wall's own scattered returns (range noise at a slant) must not make a
                # second, parallel wall a few centimetres off it
                cand = cand[np.abs(s - float(plane.centroid @ axis)) > _WALL_CLEAR]
    return out


def _fit_wall(
    p: np.ndarray, up: np.ndarray, towards: np.ndarray, sigma_floor: float, min_points: int
) -> WallPlane | None:
    """A least-squares plane through ``p`` (twice, dropping points 2.5 cm off), as a
    :class:`WallPlane` facing against ``towards`` (the side the node is on), or None where it
    is too small, too few points or not vertical."""
    for _ in range(2):
        c = p.mean(axis=0)
        _, _, vt = np.linalg.svd(p - c, full_matrices=False)
        n = vt[2]
        d = (p - c) @ n
        keep = np.abs(d) < 0.025
        if keep.sum() < min_points:
            return None
        p = p[keep]
    c = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - c, full_matrices=False)
    n = vt[2]
    if n @ towards > 0:
        n = -n
    if abs(float(n @ up)) > math.sin(math.radians(3.0)):
        return None
    h = np.cross(up, n)
    span_h = np.percentile(p @ h, [5, 95])
    span_v = np.percentile(p @ up, [5, 95])
    if span_h[1] - span_h[0] < _WALL_MIN_EXTENT or span_v[1] - span_v[0] < _WALL_MIN_EXTENT:
        return None
    d = (p - c) @ n
    se = float(d.std()) / math.sqrt(p.shape[0])
    return WallPlane(n, float(n @ c), c, int(p.shape[0]), math.hypot(se, sigma_floor))


@dataclass
class Walls:
    """Every submap's walls (:func:`wall_planes`), and how they enter the graph: the same
    wall seen from two submaps must lie at one offset in the map, so each submap that sees
    a wall gets an edge to the one that sees it best, along that wall's normal only (a
    point-to-plane constraint at its points' centroid). A wall seen from the start and again
    from the far end of a run ties the two along its normal whatever the odometry did in
    between, where a loop edge needs the two views to overlap."""

    planes: list[list[WallPlane]]
    gate: float  # m
    gate_deg: float
    used: int = 0  # walls seen from more than one submap in the last solve
    edges_used: int = 0
    groups: list[list[tuple[int, WallPlane]]] | None = None  # fixed by associate()

    def associate(self, anchors: Sequence[np.ndarray]) -> None:
        """Decide once which observations are one wall, at node poses already solved without
        the walls (online poses can be turned by degrees, which moves a wall 4 m away by
        decimetres)."""
        self.groups = self.clusters(anchors)

    def clusters(self, anchors: Sequence[np.ndarray]) -> list[list[tuple[int, WallPlane]]]:
        """The observations grouped by wall in the map (normal within ``gate_deg``, offset
        within ``gate``; the best-seen first), only those seen from two submaps or more."""
        obs = [(k, w) for k, ws in enumerate(self.planes) for w in ws]
        obs.sort(key=lambda kw: -kw[1].points)
        cos_gate = math.cos(math.radians(self.gate_deg))
        groups: list[tuple[np.ndarray, float, list[tuple[int, WallPlane]]]] = []
        for k, w in obs:
            R, t = anchors[k][:3, :3], anchors[k][:3, 3]
            n = R @ w.normal
            c = w.offset + float(n @ t)
            for ref_n, ref_c, members in groups:
                if float(n @ ref_n) > cos_gate and abs(c - ref_c) < self.gate:
                    members.append((k, w))
                    break
            else:
                groups.append((n, c, [(k, w)]))
        out = []
        for _, _, members in groups:
            best: dict[int, WallPlane] = {}
            for k, w in members:  # best seen first: each submap keeps its best
                best.setdefault(k, w)
            if len(best) >= 2:
                out.append(list(best.items()))
        return out

    def edges(
        self, anchors: Sequence[np.ndarray], up: np.ndarray | None
    ) -> list[tuple[int, int, np.ndarray, np.ndarray]]:
        """Graph edges ``(source, target, T, information)``: each wall's observers to its
        best observer, exact along the wall's normal at the observer's centroid."""
        out = []
        groups = self.groups if self.groups is not None else self.clusters(anchors)
        self.used = len(groups)
        for members in groups:
            r, wr = members[0]
            for i, wi in members[1:]:
                X = np.linalg.inv(anchors[r]) @ anchors[i]
                d = wr.offset - float(wr.normal @ (X[:3, :3] @ wi.centroid + X[:3, 3]))
                X = X.copy()
                X[:3, 3] += d * wr.normal
                u = X[:3, :3].T @ wr.normal
                J = np.r_[np.cross(wi.centroid, u), u]
                if up is not None:
                    J = _yaw_and_horizontal(anchors[i][:3, :3].T @ up) @ J
                info = np.outer(J, J) / (wi.sigma**2 + wr.sigma**2)
                out.append((i, r, X, info))
        self.edges_used = len(out)
        return out


_MIN_TURN_VARIANCE = math.radians(0.01) ** 2  # no step of any prior is trusted beyond this

# The prior's turn between two nodes, corrected, as a graph edge: transformation, information.
PriorEdge = tuple[np.ndarray, np.ndarray]


def _odometry_turn_variance(cfg: LoopClosureConfig, right_angles: bool) -> float:
    """rad^2: how far the online turn about up between consecutive nodes is trusted. With the
    right angles in the graph (``right_angles``) they hold every submap's heading, so the turn
    need not be held as tightly as alone (``manhattan_odometry_sigma_deg``). The turn only:
    nothing else in the graph holds roll and pitch (loop edges move x, y and yaw), and
    loosened with the heading they let a 74 s simulated run lean 2 deg and end 28 cm off
    (docs/mapping-fidelity.md); they keep ``odometry_sigma_deg``."""
    sigma = cfg.manhattan_odometry_sigma_deg if right_angles else cfg.odometry_sigma_deg
    return math.radians(sigma) ** 2


def _prior_yaw(
    out: LoopClosureResult,
    cfg: LoopClosureConfig,
    groups: Sequence[Sequence[int]],
    measured: Sequence[tuple[int, int, np.ndarray]],
    priors: Sequence[np.ndarray],
    poses: Sequence[np.ndarray],
    stamps: Sequence[float],
    up: np.ndarray,
    right_angles: bool = False,
) -> PriorYaw | None:
    """The prior's turns as :class:`PriorYaw`, once the loops (``measured``: kept edges' ICP
    results) have measured its drift; or None, with a note saying why not. ``right_angles``:
    they are in the graph (:func:`_odometry_turn_variance`).

    The drift ``r`` is believed only when ``drift_min_edges`` loops measured it, it is within
    ``max_drift_deg_per_m`` and at least twice its standard error (a rate fitted to loops
    between nearby nodes would be their noise). The walk is what the loops disagree with the
    drift-corrected prior by, growing with the time between their nodes (it also takes in the
    loops' own noise: the prior is trusted less, never more)."""
    starts = [g[0] for g in groups]
    travelled = path_length(poses, up)[starts]
    times = np.array([float(stamps[i]) for i in starts])
    if len(measured) < cfg.drift_min_edges:
        out.prior_drift_note = f"{len(measured)} loop edges kept, < {cfg.drift_min_edges}"
        return None
    prior_nodes = [np.asarray(priors[i], dtype=np.float64) for i in starts]
    anchors = [poses[i] for i in starts]
    rate, stderr, residual = prior_yaw_drift(measured, anchors, prior_nodes, travelled, up)
    out.prior_drift_deg_per_m = math.degrees(rate)
    if abs(math.degrees(rate)) > cfg.max_drift_deg_per_m:
        out.prior_drift_note = "not believed: above max_drift_deg_per_m"
        return None
    if abs(rate) < 2.0 * stderr:
        out.prior_drift_note = (
            f"not applied: within twice its standard error ({math.degrees(stderr):.3f} deg/m)"
        )
        return None
    dt = np.array([abs(float(times[i] - times[j])) for i, j, _ in measured])
    walk = float(residual**2 @ dt) / max(float(dt @ dt), 1e-12)
    out.prior_walk_deg_per_sqrt_s = math.degrees(math.sqrt(walk))
    yaw = PriorYaw(prior_nodes, travelled, times, rate, stderr, walk)
    yaw.kept = kept_drift(yaw, anchors, up, _odometry_turn_variance(cfg, right_angles))
    out.prior_steps = int((yaw.kept > 0.0).sum())
    if out.prior_steps == 0:
        out.prior_drift_note = "online ICP kept none of the prior's drift on any stretch"
        return None
    return yaw


def kept_drift(
    yaw: PriorYaw,
    anchors: Sequence[np.ndarray],
    up: np.ndarray,
    odometry_var: float,
    half_window: int = 3,
) -> np.ndarray:
    """Per step between nodes: the share of the prior's drift the online turns kept, where it
    is measurable, else 0.

    Online ICP starts from the prior: over a step of ``D`` metres it turns ``f r D`` too far if
    it kept a share ``f`` of the prior's drift ``r``, and the drift-corrected prior differs
    from it by that plus the prior's wander. ``f`` is fitted over ``half_window`` steps either
    side (weighted least squares, each step's variance the wander over its time plus the
    odometry's own), and kept only where it is more than twice its standard error: a share
    ICP did not measurably keep is not taken out, so the prior's wander does not replace the
    turn of a well-registered stretch (on the simulated runs ICP kept anything from none to
    four fifths of the drift, varying along a run)."""
    n = len(anchors) - 1
    gap = np.array([yaw.turn_gap(i, anchors, up) for i in range(n)])
    bias = np.array([yaw.rate * float(yaw.travelled[i + 1] - yaw.travelled[i]) for i in range(n)])
    var = np.array(
        [yaw.walk * float(yaw.times[i + 1] - yaw.times[i]) + odometry_var for i in range(n)]
    )
    out = np.zeros(n)
    for i in range(n):
        w = slice(max(0, i - half_window), min(n, i + half_window + 1))
        den = float((bias[w] ** 2 / var[w]).sum())
        if den <= 0.0:
            continue
        share = float((gap[w] * bias[w] / var[w]).sum()) / den
        if share > 2.0 / math.sqrt(den):
            out[i] = share
    return out


def prior_yaw_drift(
    measured: Sequence[tuple[int, int, np.ndarray]],
    nodes: Sequence[np.ndarray],
    prior_nodes: Sequence[np.ndarray],
    travelled: np.ndarray,
    up: np.ndarray,
) -> tuple[float, float, np.ndarray]:
    """``(rate, standard error)``, rad per metre: how much farther the prior turns than the
    loops measured, per metre travelled; and per loop what is left beside that (rad), the
    prior's heading wander between the loop's nodes plus the loop's own noise.

    A visual-inertial prior's heading error grows with the distance travelled, ``e(D) = r D``.
    Between two nodes a loop joins, the prior's relative yaw then differs from the loop's
    (``measured``: ``(i, j, T)`` with ``T`` node i's pose in node j's frame, from ICP) by
    ``r (D_i - D_j)``, whatever happened before either node. So ``r`` is the least-squares
    slope of those yaw differences against the distance between the nodes, through zero.
    Unlike a fit of the graph's corrections (:func:`estimate_drift`) it needs no loop back to
    the first node, and unlike a solved graph the loops themselves carry none of the
    odometry's drift. ``nodes`` (the trajectory's) give only the direction of up at node i.
    The standard error is inf when the loops' nodes are no distance apart.
    """
    yaw = []
    for i, j, T in measured:
        prior = np.linalg.inv(prior_nodes[j]) @ prior_nodes[i]
        # the rotation that takes the loop's relative pose to the prior's, about up (node i)
        w = log_se3(np.linalg.inv(T) @ prior)[3:]
        yaw.append(float(w @ (nodes[i][:3, :3].T @ up)))
    y = np.array(yaw)
    x = np.array([float(travelled[i] - travelled[j]) for i, j, _ in measured])
    den = float(x @ x)
    if den < 1e-9:
        return 0.0, math.inf, y
    rate = float(x @ y) / den
    residual = y - rate * x
    dof = max(len(x) - 1, 1)
    return rate, math.sqrt(float((residual**2).sum()) / dof / den), residual


def _edge_measurement(
    init: np.ndarray,
    T: np.ndarray,
    H: np.ndarray,
    S: np.ndarray | None,
    radius: float,
    ratio: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(correction [omega, t], edge transformation, information)`` of a loop edge whose ICP
    result is ``T``, read against the current guess ``init``: only the directions the overlap
    observes (and, with ``S``, only yaw and horizontal translation) move away from the guess."""
    xo, H_kept = _observed_motion(np.linalg.inv(init) @ T, H, S, radius, ratio)
    return xo, init @ exp_se3(np.r_[xo[3:], xo[:3]]), H_kept


def _observed_motion(
    M: np.ndarray, H: np.ndarray, S: np.ndarray | None, radius: float, ratio: float
) -> tuple[np.ndarray, np.ndarray]:
    """The part of a source-node motion ``M`` (4x4) that an edge with information ``H`` (and
    horizontal projector ``S``) observes, as ``[omega, t]``; and ``H`` without the rest."""
    x = log_se3(M)
    xw = np.r_[x[3:], x[:3]]
    if S is not None:
        xw = S @ xw
    return observable_part(H, xw, radius, ratio)


def _observed_distance(
    M: np.ndarray, H: np.ndarray, S: np.ndarray | None, radius: float, ratio: float
) -> float:
    """How far (m) a source-node motion ``M`` moves an edge's overlap along the directions
    it observes, rotation taken at the submap ``radius``: the one size in which a loop edge's
    residual (:func:`_worst_loop_edge`) and its error against truth (:class:`LoopEdge`) are
    both read."""
    xo, _ = _observed_motion(M, H, S, radius, ratio)
    return math.hypot(float(np.linalg.norm(xo[3:])), radius * float(np.linalg.norm(xo[:3])))


def _solve(
    anchors: list[np.ndarray],
    edges: list[Edge],
    radii: list[float],
    cfg: LoopClosureConfig,
    prior_yaw: PriorYaw | None = None,
    up: np.ndarray | None = None,
    right: RightAngles | None = None,
    walls: Walls | None = None,
) -> tuple[list[np.ndarray], set[tuple[int, int]]]:
    """Optimised node poses of the graph with odometry edges from ``anchors`` and the loop
    edges; and the ``(i, j)`` of the loop edges the line process kept. With ``prior_yaw`` (and
    ``up``) every step it is used on (:meth:`PriorYaw.used`) also gets the prior's corrected
    turn, and the odometry's turn there is trusted less by the drift ICP kept. With ``right``
    (and ``up``) the odometry's turn about up is trusted less (:func:`_odometry_turn_variance`),
    its roll and pitch (and the right-angle frame's pin to node 0) as without."""
    import open3d as o3d

    reg = o3d.pipelines.registration
    graph = reg.PoseGraph()
    for a in anchors:
        graph.nodes.append(reg.PoseGraphNode(a))
    rot_var = math.radians(cfg.odometry_sigma_deg) ** 2
    turn_var = rot_var
    if up is not None:
        turn_var = _odometry_turn_variance(cfg, right is not None)
    odo_info = np.diag([1.0 / rot_var] * 3 + [1.0 / cfg.odometry_sigma**2] * 3)
    prior_edges = []
    for i in range(len(anchors) - 1):
        rel = np.linalg.inv(anchors[i + 1]) @ anchors[i]
        info = odo_info
        prior_used = prior_yaw is not None and up is not None and prior_yaw.used(i)
        if up is not None and (prior_used or turn_var != rot_var):
            g = anchors[i][:3, :3].T @ up
            yaw_var = turn_var
            if prior_yaw is not None and prior_used:
                yaw_var += prior_yaw.odometry_bias(i) ** 2
                prior_edges.append((i, *prior_yaw.edge(i, anchors, up)))
            info = odo_info.copy()
            info[:3, :3] = (np.eye(3) - np.outer(g, g)) / rot_var + np.outer(g, g) / yaw_var
        graph.edges.append(reg.PoseGraphEdge(i, i + 1, rel, info, uncertain=False))
    weight = 3.0 / cfg.loop_sigma**2
    for i, j, T, H, S in edges:
        init = np.linalg.inv(anchors[j]) @ anchors[i]
        _, Te, H_kept = _edge_measurement(init, T, H, S, radii[i], cfg.observable_ratio)
        graph.edges.append(reg.PoseGraphEdge(i, j, Te, H_kept * weight, uncertain=True))
    # Open3D sets its line-process weight from the mean information(5, 5) of all edges (the
    # correspondence count in its own information matrices); ours are weighted normalised
    # information, and (5, 5) is whatever the sensor's z axis sees. Scale the preference so
    # that a loop edge is switched off once its residual, in units of ``loop_sigma``, exceeds
    # what a 5 cm misalignment would give: the same in any frame convention, with or without
    # ``horizontal_only``.
    mean55 = float(np.mean([e.information[5, 5] for e in graph.edges]))
    preference = weight / max(mean55, 1e-12)
    for i, T, info in prior_edges:  # certain, and not in the line process's mean above
        graph.edges.append(reg.PoseGraphEdge(i, i + 1, T, info, uncertain=False))
    frame_edges = None
    if right is not None and up is not None:
        frame_edges = right.edges(anchors, up, rot_var, cfg.odometry_sigma**2)
    if frame_edges is not None:  # certain too: each reading is gated and weighted by its error
        frame, to_frame = frame_edges
        graph.nodes.append(reg.PoseGraphNode(frame))
        for i, T, info in to_frame:
            graph.edges.append(reg.PoseGraphEdge(i, len(anchors), T, info, uncertain=False))
    if walls is not None:  # certain: grouped once, each a plane fit over >= 500 points
        for i, j, T, info in walls.edges(anchors, up):
            graph.edges.append(reg.PoseGraphEdge(i, j, T, info, uncertain=False))
    level = o3d.utility.get_verbosity_level()
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    try:
        reg.global_optimization(
            graph,
            reg.GlobalOptimizationLevenbergMarquardt(),
            reg.GlobalOptimizationConvergenceCriteria(),
            reg.GlobalOptimizationOption(
                max_correspondence_distance=0.05,
                edge_prune_threshold=cfg.edge_prune_threshold,
                preference_loop_closure=preference,
                reference_node=0,
            ),
        )
    finally:
        o3d.utility.set_verbosity_level(level)
    kept = {(e.source_node_id, e.target_node_id) for e in graph.edges if e.uncertain}
    return [np.asarray(nd.pose) for nd in graph.nodes][: len(anchors)], kept


def solve_rejecting(
    anchors: list[np.ndarray],
    edges: list[Edge],
    radii: list[float],
    cfg: LoopClosureConfig,
    prior_yaw: PriorYaw | None = None,
    up: np.ndarray | None = None,
    right: RightAngles | None = None,
    walls: Walls | None = None,
) -> tuple[list[np.ndarray], set[tuple[int, int]], int]:
    """Node poses of the graph solved without the loop edges it cannot agree with; the
    ``(i, j)`` of the loop edges kept, and how many were rejected (removed from ``edges``).

    Open3D's line process switches off an edge its neighbours outvote; where few edges overlap
    (a far wall seen once from each end of the room, at a grazing angle, 5 m away) a wrong one
    has no neighbours and bends the graph instead. Every edge the solution still disagrees with
    by more than ``cfg.max_loop_residual`` goes, the worst first, and the graph is solved again
    (one at a time: the worst edge's pull is often what makes a good neighbour disagree).
    """
    nodes, kept = _solve(anchors, edges, radii, cfg, prior_yaw, up, right, walls)
    rejected = 0
    while cfg.max_loop_residual > 0 and edges:
        worst, residual = _worst_loop_edge(anchors, nodes, edges, kept, radii, cfg)
        if residual <= cfg.max_loop_residual:
            break
        del edges[worst]
        rejected += 1
        nodes, kept = _solve(anchors, edges, radii, cfg, prior_yaw, up, right, walls)
    return nodes, kept, rejected


def _worst_loop_edge(
    anchors: list[np.ndarray],
    nodes: list[np.ndarray],
    edges: list[Edge],
    kept: set[tuple[int, int]],
    radii: list[float],
    cfg: LoopClosureConfig,
) -> tuple[int, float]:
    """Index and residual (m) of the kept loop edge the solved ``nodes`` disagree with most.

    The residual is the motion of the source node between the edge's measurement and the
    solution, along the directions the edge observes, rotation taken at the submap's radius:
    how far the solution moves the overlap's points from where the edge put them. Edges the
    line process switched off are already out and do not count.
    """
    worst, worst_r = -1, 0.0
    for n, (i, j, T, H, S) in enumerate(edges):
        if (i, j) not in kept:
            continue
        init = np.linalg.inv(anchors[j]) @ anchors[i]
        _, Te, _ = _edge_measurement(init, T, H, S, radii[i], cfg.observable_ratio)
        solved = np.linalg.inv(Te) @ np.linalg.inv(nodes[j]) @ nodes[i]
        r = _observed_distance(solved, H, S, radii[i], cfg.observable_ratio)
        if r > worst_r:
            worst, worst_r = n, r
    return worst, worst_r


def _interpolate(
    groups: list[list[int]],
    anchors: list[np.ndarray],
    nodes: list[np.ndarray],
    poses: list[np.ndarray],
) -> list[np.ndarray]:
    """Every frame corrected by its node's correction, interpolated towards the next node's."""
    corr = [n @ np.linalg.inv(a) for n, a in zip(nodes, anchors, strict=True)]
    out = [p.copy() for p in poses]
    for k, g in enumerate(groups):
        step = log_se3(np.linalg.inv(corr[k]) @ corr[k + 1]) if k + 1 < len(groups) else None
        for i in g:
            C = corr[k]
            if step is not None:
                C = C @ exp_se3(step * ((i - g[0]) / len(g)))
            out[i] = C @ poses[i]
    return out


def _about(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix: ``angle`` (rad) about the unit vector ``axis``."""
    return exp_se3(np.r_[0.0, 0.0, 0.0, np.asarray(axis) * angle])[:3, :3]


def path_length(poses: Sequence[np.ndarray], up: np.ndarray) -> np.ndarray:
    """Horizontal distance travelled (m) up to each pose: what VIO drift grows with."""
    flat = np.eye(3) - np.outer(up, up)
    steps = [
        float(np.linalg.norm(flat @ (b[:3, 3] - a[:3, 3]))) for a, b in itertools.pairwise(poses)
    ]
    return np.r_[0.0, np.cumsum(steps)]


def estimate_drift(
    before: Sequence[np.ndarray], after: Sequence[np.ndarray], up: np.ndarray
) -> tuple[float, float]:
    """``(scale, yaw per metre in rad)`` that best explain how ``before`` became ``after``.

    A pose prior that measures every step ``1 + e`` times too long and turns ``r`` rad too far
    per metre is corrected by a graph that shortens its horizontal steps by ``1 / (1 + e)`` and
    turns pose ``k`` back by ``r * D_k`` (``D_k`` the distance travelled to it). Both are fitted
    by least squares through the first pose (the fixed reference): the yaw corrections against
    ``D_k``, then the steps' length changes (with the yaw correction taken out) against their
    lengths. Returns the correction to apply (:func:`undrift`), i.e. about ``-e`` and ``-r``.
    """
    flat = np.eye(3) - np.outer(up, up)
    dist = path_length(before, up)
    yaw = []
    for b, a in zip(before, after, strict=True):
        R = np.eye(4)
        R[:3, :3] = a[:3, :3] @ b[:3, :3].T
        yaw.append(float(log_se3(R)[3:] @ up))
    c = np.array(yaw)
    rate = float(c @ dist / max(float(dist @ dist), 1e-12))
    num = den = 0.0
    for k in range(len(before) - 1):
        d = flat @ (before[k + 1][:3, 3] - before[k][:3, 3])
        e = _about(up, -0.5 * (c[k] + c[k + 1])) @ (flat @ (after[k + 1][:3, 3] - after[k][:3, 3]))
        num += float((e - d) @ d)
        den += float(d @ d)
    return num / max(den, 1e-12), rate


def undrift(
    poses: Sequence[np.ndarray], scale: float, yaw_per_m: float, up: np.ndarray
) -> list[np.ndarray]:
    """The trajectory re-integrated with every horizontal step ``1 + scale`` times as long and
    turned by ``yaw_per_m`` rad per metre travelled so far; heights, roll and pitch kept (the
    turn is about ``up``), the first pose unchanged."""
    flat = np.eye(3) - np.outer(up, up)
    out = [np.asarray(poses[0], dtype=np.float64).copy()]
    travelled = 0.0
    for a, b in itertools.pairwise(poses):
        d = b[:3, 3] - a[:3, 3]
        h = flat @ d
        travelled += float(np.linalg.norm(h))
        R = _about(up, yaw_per_m * travelled)
        q = np.eye(4)
        q[:3, :3] = R @ b[:3, :3]
        q[:3, 3] = out[-1][:3, 3] + R @ ((1.0 + scale) * h + (d - h))
        out.append(q)
    return out
