"""Wheelchair-like camera trajectories: drive along free aisles, turn in place, sweep the phone.

A person scanning a room from a wheelchair holds the phone at about 1 m, pitched down, and
sweeps it left and right while the chair drives at walking pace (the paper: 3 km/h, ~0.8 m/s).
The path is a list of segments (drive to a point, turn in place, drive backwards out of a dead
end) built on a *nominal* timeline at that speed; ``make_trajectory`` then samples the whole
path with the requested number of frames, so every frame count covers the whole room (fewer
frames = faster apparent motion). The yaw sweep only runs while driving, so in-place turns stay
slow enough for scan registration.

Poses are ``room_from_optical`` 4x4 matrices (optical frame: z forward, x right, y down).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from wheelgrid_sim.scene import Scene

SPEED = 0.8  # m/s, nominal driving speed
TURN_RATE = math.radians(45.0)  # rad/s, in-place turns
SWEEP_AMPLITUDE = math.radians(35.0)
SWEEP_PERIOD = 6.0  # s of driving per left-right-left sweep
STAMP_EPOCH = 1_700_000_000  # s, first message stamp


@dataclass(frozen=True)
class Segment:
    """One piece of the path: ``drive`` (to x, y; reverse keeps the heading) or ``turn``."""

    kind: str  # "drive" | "reverse" | "turn"
    x: float = 0.0
    y: float = 0.0
    heading: float = 0.0  # rad, for "turn": the heading to turn to


def paper_path(back_to_start: bool = False) -> tuple[tuple[float, float, float], list[Segment]]:
    """Start (x, y, heading) and segments for the paper scene (see ``paper_scene``).

    Start at the centre of cell (2,0) looking +x; glance north-west (the corner the eastward
    drive never sees); drive east along row 2; down column 5; into the aisle between the two
    rows of tables (north of Barrier 2's post) and reverse out; down column 5 again, under
    Barrier 2; then west along row 6. Every segment keeps >= 0.35 m from obstacles below 1.3 m.
    ``back_to_start``: then the way back, east along row 6, up column 5 and west along row 2,
    ending where it began, its heading as it began (a scan that closes its loop: 74 s, not 42);
    :func:`make_trajectory`'s sweep and height wander on, so the last view is not the first.
    """
    d = math.radians
    segs = [
        Segment("turn", heading=d(100)),
        Segment("turn", heading=d(0)),
        Segment("drive", 6.6, 6.6),
        Segment("turn", heading=d(-90)),
        Segment("drive", 6.6, 4.65),
        Segment("turn", heading=d(-180)),
        Segment("drive", 4.3, 4.65),
        Segment("drive", 2.9, 4.2),
        Segment("reverse", 4.3, 4.65),
        Segment("reverse", 6.6, 4.65),
        Segment("turn", heading=d(-90)),
        Segment("drive", 6.6, 1.8),
        Segment("turn", heading=d(-180)),
        Segment("drive", 1.2, 1.8),
    ]
    if back_to_start:
        segs += [
            Segment("turn", heading=d(0)),
            Segment("drive", 6.6, 1.8),
            Segment("turn", heading=d(90)),
            Segment("drive", 6.6, 6.6),
            Segment("turn", heading=d(180)),
            Segment("drive", 0.6, 6.6),
            Segment("turn", heading=d(360)),
        ]
    return (0.6, 6.6, 0.0), segs


def ring_path(
    scene: Scene, inset: float = 0.6, back_to_start: bool = False
) -> tuple[tuple[float, float, float], list[Segment]]:
    """Counter-clockwise lap ``inset`` from the walls (random scenes keep that ring free);
    ``back_to_start``: on to the start, facing as it began."""
    x0, y0, x1, y1 = scene.room
    a, b, c, e = x0 + inset, y0 + inset, x1 - inset, y1 - inset
    h = math.pi / 2
    segs = [
        Segment("drive", c, b),
        Segment("turn", heading=h),
        Segment("drive", c, e),
        Segment("turn", heading=2 * h),
        Segment("drive", a, e),
        Segment("turn", heading=3 * h),
        Segment("drive", a, b + inset),
    ]
    if back_to_start:
        segs += [Segment("drive", a, b), Segment("turn", heading=4 * h)]
    return (a, b, 0.0), segs


def scene_path(
    scene: Scene, back_to_start: bool = False
) -> tuple[tuple[float, float, float], list[Segment]]:
    """The paper scene's :func:`paper_path`, any other scene's :func:`ring_path`."""
    if scene.name == "paper":
        return paper_path(back_to_start)
    return ring_path(scene, back_to_start=back_to_start)


@dataclass
class _Knot:
    t: float
    x: float
    y: float
    heading: float
    sweep_time: float  # driving time so far (the sweep's clock)


def _knots(start: tuple[float, float, float], segs: list[Segment]) -> list[_Knot]:
    x, y, hd = start
    t = sweep = 0.0
    out = [_Knot(t, x, y, hd, sweep)]
    for s in segs:
        if s.kind == "turn":
            dt = abs(s.heading - hd) / TURN_RATE
            hd = s.heading
        elif s.kind in ("drive", "reverse"):
            dist = math.hypot(s.x - x, s.y - y)
            dt = dist / SPEED
            if s.kind == "drive" and dist > 0:
                new = math.atan2(s.y - y, s.x - x)
                # unwrap to the nearest equivalent of the current heading
                new = hd + (new - hd + math.pi) % (2 * math.pi) - math.pi
                if abs(new - hd) > math.radians(30.0):
                    raise ValueError(f"drive segment to ({s.x}, {s.y}) needs a turn first")
                hd = new  # small bends are steered while driving (heading interpolates)
            x, y = s.x, s.y
            sweep += dt
        else:
            raise ValueError(f"unknown segment kind {s.kind!r}")
        t += dt
        out.append(_Knot(t, x, y, hd, sweep))
    return out


def camera_pose(
    x: float, y: float, z: float, yaw: float, pitch: float, roll: float = 0.0
) -> np.ndarray:
    """``room_from_optical`` for a camera at (x, y, z) looking along ``yaw`` (from +x, CCW),
    pitched DOWN by ``pitch`` and rolled by ``roll`` about its viewing axis (radians)."""
    cp = math.cos(pitch)
    fwd = np.array([cp * math.cos(yaw), cp * math.sin(yaw), -math.sin(pitch)])
    right = np.array([math.sin(yaw), -math.cos(yaw), 0.0])
    down = np.cross(fwd, right)
    if roll:
        c, s = math.cos(roll), math.sin(roll)
        right, down = c * right + s * down, -s * right + c * down
    T = np.eye(4)
    T[:3, 0], T[:3, 1], T[:3, 2], T[:3, 3] = right, down, fwd, (x, y, z)
    return T


def make_trajectory(
    scene: Scene, frames: int, rate: float, seed: int = 0, back_to_start: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """``(stamps (N,) s, poses (N, 4, 4) room_from_optical)`` covering the scene's whole path.

    The paper scene uses :func:`paper_path`, any other scene :func:`ring_path` (either with
    ``back_to_start``). Camera height
    wanders in 0.9-1.2 m and pitch in 15-25 deg down (so bars above the camera come into view);
    the seed sets those phases and a +-1 deg hand tremor in roll.
    """
    if frames < 1:
        raise ValueError("frames must be >= 1")
    if rate <= 0:
        raise ValueError("rate must be > 0")
    knots = _knots(*scene_path(scene, back_to_start))
    ts = np.array([k.t for k in knots])
    total = ts[-1]
    rng = np.random.default_rng(seed)
    ph_h, ph_p = rng.uniform(0, 2 * math.pi, 2)
    roll_noise = rng.uniform(-1.0, 1.0, frames) * math.radians(1.0)
    bias = 0.0 if scene.name == "paper" else math.radians(40.0)  # ring laps look inwards
    tau = np.linspace(0.0, total, frames) if frames > 1 else np.zeros(1)
    xs = np.interp(tau, ts, [k.x for k in knots])
    ys = np.interp(tau, ts, [k.y for k in knots])
    hs = np.interp(tau, ts, [k.heading for k in knots])
    sw = np.interp(tau, ts, [k.sweep_time for k in knots])
    poses = np.empty((frames, 4, 4))
    for i in range(frames):
        yaw = hs[i] + bias + SWEEP_AMPLITUDE * math.sin(2 * math.pi * sw[i] / SWEEP_PERIOD)
        z = 1.05 + 0.15 * math.sin(2 * math.pi * tau[i] / 11.0 + ph_h)
        pitch = math.radians(20.0 + 5.0 * math.sin(2 * math.pi * tau[i] / 7.0 + ph_p))
        poses[i] = camera_pose(xs[i], ys[i], z, yaw, pitch, float(roll_noise[i]))
    stamps = STAMP_EPOCH + np.arange(frames) / float(rate)
    return stamps, poses


def nominal_duration(scene: Scene, back_to_start: bool = False) -> float:
    """Seconds the scene's path takes at the nominal speed (frames = duration * rate + 1)."""
    return _knots(*scene_path(scene, back_to_start))[-1].t


def nominal_frames(duration: float, rate: float) -> int:
    """Frames at ``rate`` Hz that drive a path of ``duration`` s (:func:`nominal_duration`) at
    the nominal speed: one frame stands at the start."""
    return round(duration * rate) + 1


def stamp_ns(stamps: np.ndarray) -> np.ndarray:
    """Stamps (s) as integer nanoseconds, exact for the epoch + i / rate form."""
    return np.round(np.asarray(stamps, dtype=np.float64) * 1e9).astype(np.int64)
