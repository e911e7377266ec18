"""``wheelgrid map INPUT --out DIR``: build the levelled 3D map offline.

INPUT is a rosbag2 folder (sqlite3/mcap), a ROS 1 ``.bag`` or a Stray Scanner export folder.
Writes DIR/map.ply (map frame, metres), DIR/trajectory.tum (sensor pose per registered frame,
map frame) and DIR/report.json. Exit codes: 0 ok, 2 bad input (one clear line on stderr),
1 mapping failed (e.g. no floor found, every frame failed to register).
"""

from __future__ import annotations

import argparse
import contextlib
import itertools
import sys
import time
from collections.abc import Iterator, Mapping
from pathlib import Path
from typing import Any

import numpy as np

from wheelgrid_common.fileio import folder_problem, out_folder
from wheelgrid_common.frames import other_frame
from wheelgrid_common.progress import Progress

from .pipeline import (
    DEFAULT_FRAME_ID,
    FrameOutcome,
    Mapper,
    check_keyframe_interval,
    load_configs,
)
from .prefetch import FramePipeline
from .registration import PRIOR_SCALE_MIN_STEP
from .thin_check import check_thin_obstacles

# points, stamp, frame_id, confidence, pose prior, and when it arrived (a bag's log time; in
# a Stray export, the latest time its place in capture order allows), which tells a stamp far
# ahead from a pause (:mod:`.frame_clock`)
Frame = tuple[np.ndarray, float, str, np.ndarray | None, np.ndarray | None, float | None]


class InputError(Exception):
    """Unusable input: reported on one line, exit code 2."""


#: report.json's counts of frames skipped before registration for their stamp or frame (the
#: rest of ``skipped`` is min_frame_interval's keyframe selection)
STAMP_OR_FRAME_SKIPS = ("out_of_order", "stamped_ahead", "stamped_behind", "other_frame")


def stamp_or_frame_skips(frames: Mapping[str, Any]) -> int:
    """Frames skipped before registration for their stamp or frame, of report.json's
    ``frames`` counts (or the Mapper's counters by the same names)."""
    return sum(int(frames.get(k, 0)) for k in STAMP_OR_FRAME_SKIPS)


def is_stray(path: Path) -> bool:
    return path.is_dir() and (path / "depth").is_dir() and not (path / "metadata.yaml").exists()


def _not_a_bag_hint(path: Path) -> None:
    """``InputError`` for an input that is neither kind this command reads, where the bag
    reader's own message would speak of bags only (a Stray export's depth/ folder given, or
    the export's path mistyped)."""
    if not path.exists():
        raise InputError(
            f"{path}: no such input (a rosbag2 folder, a ROS 1 .bag file or a Stray Scanner "
            "export folder)"
        )
    if path.is_dir() and not (path / "metadata.yaml").exists():
        if any(path.glob("*.mcap")) or any(path.glob("*.db3")):
            return  # a bag cut off before its metadata.yaml: the reader names the fix
        hint = ""
        if any(path.glob("[0-9]*.png")) or any(path.glob("[0-9]*.npy")):
            hint = ": it holds frame images; a Stray export is the folder above its depth/"
        raise InputError(
            f"{path}: neither a rosbag2 bag (no metadata.yaml) nor a Stray Scanner export "
            f"(no depth/ folder){hint}"
        )


def stray_frames(
    path: Path, use_prior: bool, bad: list[str] | None = None
) -> tuple[int, Iterator[Frame]]:
    """Frames of a Stray export as optical-frame clouds (+ confidence, + ARKit pose prior).

    A frame whose images do not read is skipped with a warning, as a bag's malformed
    message is: an empty frame in its place, its cause appended to ``bad``. One bad file in
    a capture of thousands must not throw away the minutes of mapping before it.

    The prior is ARKit's pose turned into a REP-105 odom (z up), as the iPhone bridge
    publishes it: the registration rescales the prior's x, y steps only and the Mapper takes
    the prior's z as gravity, and ARKit's own world has y up (it was passed as it was until
    2026-11-27, so a rescale would have scaled the phone's climbs and left out its forward z).
    """
    from .depth import arkit_pose_to_ros, depth_to_points
    from .stray import StrayExport

    try:
        export = StrayExport(path)
    except ValueError as exc:
        raise InputError(str(exc)) from exc
    if use_prior and not export.has_poses:
        # "lacks" said of an empty file, or one of NaN rows, sent the user looking for a file
        # that is there (a review)
        have = (path / "odometry.csv").exists()
        raise InputError(
            f"{path}: --prior arkit needs odometry.csv, which this export "
            + (
                "holds, but with no usable pose (empty, or every row NaN or a zero quaternion)"
                if have
                else "lacks"
            )
        )
    note = export.missing_poses_note() if use_prior else ""
    if note:
        print(
            f"wheelgrid map: warning: {note}; once a frame has had its prior, those "
            "fail (a run with a prior places no frame by ICP alone)",
            file=sys.stderr,
        )

    def gen() -> Iterator[Frame]:
        for i in range(len(export)):
            fr = export.frame_or_warn(i)
            if fr is None:
                if bad is not None:
                    bad.append("unreadable image")
                taken_by = export.captured_by(i)
                yield np.empty((0, 3)), export.stamp(i), DEFAULT_FRAME_ID, None, None, taken_by
                continue
            # organised (H, W, 3): the pixel grid, for the mixed-pixel test
            pts = depth_to_points(fr.depth, fr.K).reshape(*fr.depth.shape, 3)
            conf = None if fr.confidence is None else fr.confidence.reshape(-1)
            yield (
                pts,
                fr.stamp,
                DEFAULT_FRAME_ID,
                conf,
                (arkit_pose_to_ros(fr.pose) if use_prior and fr.pose is not None else None),
                export.captured_by(i),
            )

    return len(export), gen()


ODOMETRY = "nav_msgs/msg/Odometry"


def _odometry_poses(reader: object, topic: str) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(stamps, 4x4 poses, child frames) of an Odometry topic: the pose prior for bags."""
    from wheelgrid_common.bagio import BagError
    from wheelgrid_common.fileio import pose_or_nan

    stamps, poses, children = [], [], []
    unreadable = 0
    # one damaged Odometry message costs the frames near it their prior, as a NaN pose does;
    # it ended the whole run before the first frame
    try:
        for _, t_ns, msg in reader.messages(  # type: ignore[attr-defined]
            [topic], damaged_as_none=True, msgtype=ODOMETRY
        ):
            if msg is None:
                unreadable += 1
                continue
            p = msg.pose.pose
            T = pose_or_nan(p.position, p.orientation)  # the Mapper refuses and counts NaN poses
            st = msg.header.stamp
            stamps.append(st.sec + st.nanosec * 1e-9 if (st.sec or st.nanosec) else t_ns * 1e-9)
            poses.append(T)
            children.append(msg.child_frame_id)
    except BagError as exc:
        # storage damaged part-way (a bad MCAP chunk): the poses before it are the prior of
        # the frames before it, which the clouds' own read maps up to the same place; ending
        # here threw away every frame of the bag
        print(f"wheelgrid map: warning: {exc}; the pose prior ends there", file=sys.stderr)
    if unreadable:
        print(
            f"wheelgrid map: warning: {unreadable} message(s) on {topic} do not deserialise; "
            "frames without a prior pose within 0.1 s fail once one frame has had it",
            file=sys.stderr,
        )
    return np.asarray(stamps), np.asarray(poses).reshape(-1, 4, 4), children


class PriorMatch:
    """Which frames found no odometry message within 0.1 s of their stamp (``--prior arkit``
    on a bag): such a frame fails once a frame before it had a prior (before that it
    registers without one), and when that is every frame (clouds
    and odometry stamped on different clocks) the map was made geometry-only, without a word."""

    def __init__(self) -> None:
        self.odom_stamps: np.ndarray | None = None  # set where the bag gave a prior topic
        self.frames = 0  # readable frames the prior was looked up for
        self.missing: list[float] = []  # their stamps where none was found
        # (pose's child frame, cloud's frame) -> frames whose nearest pose was of another frame
        self.other_frame: dict[tuple[str, str], int] = {}

    def other_frame_warning(self) -> str:
        """One line for stderr, or '': the frames whose prior was the pose of another frame
        than theirs (a base_link odometry), which is not used: read as the camera's, a pose
        one mount away doubled the map's surfaces and levelled it 6 deg off, exit 0 (a
        review). There is no tf here to chain them (docs/CONVENTIONS.md)."""
        if not self.other_frame:
            return ""
        (child, cloud), _ = max(self.other_frame.items(), key=lambda kv: kv[1])
        return (
            f"{sum(self.other_frame.values())} of {self.frames} frames' odometry poses are of "
            f"frame {child!r}, the clouds of {cloud!r}: the prior is not used for them (no tf "
            "here to chain the two); record the sensor's own pose as the prior"
        )

    def warning(self) -> str:
        """One line for stderr, or '' when every frame found its prior."""
        if not self.missing:
            return ""
        line = (
            f"{len(self.missing)} of {self.frames} frames had no odometry message within 0.1 s "
            "of their stamp: those after the first with a prior failed (no pose prior), those "
            "before it registered without one"
        )
        if len(self.missing) == self.frames and self.frames:
            stamps = self.odom_stamps
            odom = (
                f"{stamps.min():.3f} .. {stamps.max():.3f} s"
                if stamps is not None and stamps.size
                else "none"
            )
            line += (
                f" (frames stamped {min(self.missing):.3f} .. {max(self.missing):.3f} s, the "
                f"odometry {odom}: is one on another clock?)"
            )
        return line


NO_FRAME_ID = "no frame_id (axes unknown under sensor_convention auto)"


def bag_frames(
    path: Path,
    topic: str | None,
    prior: bool = False,
    prior_topic: str | None = None,
    match: PriorMatch | None = None,
    damage: list[str] | None = None,
    guess_axes: bool = True,
) -> tuple[int, Iterator[Frame], list[str]]:
    """PointCloud2 frames of a bag; malformed messages are skipped and counted by cause.

    With ``guess_axes`` (``sensor_convention: auto``) a cloud without a frame_id is one: its
    axes are unknown.

    Storage that turns out damaged part-way through ends the frames there; with ``damage``
    given its error is appended to it (the caller maps the frames before it), else it is an
    :class:`InputError`.

    With ``prior`` the nav_msgs/Odometry topic ``prior_topic``, or the bag's only one (the
    bridge's /iphone/odometry, i.e. ARKit), gives each frame a pose prior: the odometry message
    nearest in time (<= 0.1 s), and ``match`` counts the frames without one.
    """
    from wheelgrid_common.bagio import POINTCLOUD2, BagError, BagReader
    from wheelgrid_common.pointcloud2 import CloudError, has_field, organised, read_fields

    bad: list[str] = []
    holder = BagReader(path)
    try:
        reader = holder.__enter__()
        name = reader.pick_topic(topic)
        total = reader.count([name], POINTCLOUD2)
        prior_stamps, prior_poses = np.empty(0), np.empty((0, 4, 4))
        prior_children: list[str] = []
        if prior:
            try:
                odom = reader.pick_topic(prior_topic, ODOMETRY, "--prior-topic")
            except BagError as exc:
                # the hint belongs to this error only: appended to every BagError, it told a
                # user whose bag did not open that the bag lacked an Odometry topic
                raise BagError(f"{exc} (--prior arkit needs one nav_msgs/Odometry topic)") from exc
            prior_stamps, prior_poses, prior_children = _odometry_poses(reader, odom)
            if match is not None:
                match.odom_stamps = prior_stamps
        elif any(t.msgtype == ODOMETRY for t in reader.topics()):
            print(
                "wheelgrid map: hint: the bag has a nav_msgs/Odometry topic; --prior arkit uses "
                "it as the pose prior (geometry-only registration drifts on floor-dominated views)",
                file=sys.stderr,
            )
    except BagError as exc:
        # BagReader.__exit__ raises when open() itself failed (common bug): ignore that.
        with contextlib.suppress(Exception):
            holder.__exit__()
        raise InputError(str(exc)) from exc

    def prior_for(stamp: float, frame_id: str) -> np.ndarray | None:
        """The odometry pose nearest ``stamp`` (within 0.1 s) if it is of the cloud's own
        frame; ``match`` counts the frames without one, and why."""
        if not prior:
            return None
        if match is not None:
            match.frames += 1
        i = int(np.argmin(np.abs(prior_stamps - stamp))) if prior_stamps.size else -1
        if i < 0 or abs(prior_stamps[i] - stamp) > 0.1:
            if match is not None:
                match.missing.append(stamp)
            return None
        if other_frame(prior_children[i], frame_id):
            if match is not None:
                key = (prior_children[i], frame_id)
                match.other_frame[key] = match.other_frame.get(key, 0) + 1
            return None
        return prior_poses[i]

    if total == 0:
        # metadata.yaml's count, not the storage's: a bag whose metadata lists none was
        # refused as empty while it held every frame. The storage is asked.
        try:
            held = next(iter(reader.raw([name], POINTCLOUD2)), None) is not None
        except BagError:
            held = False
        if not held:
            reader.__exit__()
            raise InputError(f"{path}: topic {name} has no messages")
        print(
            f"wheelgrid map: warning: {path}: metadata.yaml lists no messages on {name}, but "
            "the bag holds some: all it holds is read",
            file=sys.stderr,
        )

    def gen() -> Iterator[Frame]:
        try:
            # one message that does not deserialise ended the whole run with exit 2 and threw
            # away every frame mapped before it; it is skipped and counted like any other
            # malformed frame
            for _, t_ns, msg in reader.messages([name], damaged_as_none=True, msgtype=POINTCLOUD2):
                if msg is None:
                    bad.append("undeserialisable")
                    yield np.empty((0, 3)), t_ns * 1e-9, "", None, None, None
                    continue
                try:
                    pts = read_fields(msg)
                    # a broken confidence field is the frame's fault too (it raised a traceback)
                    conf = (
                        read_fields(msg, ("confidence",))[:, 0]
                        if has_field(msg, "confidence")
                        else None
                    )
                except CloudError as exc:
                    bad.append(exc.cause)
                    yield np.empty((0, 3)), t_ns * 1e-9, "", None, None, None
                    continue
                st = msg.header.stamp
                stamp = st.sec + st.nanosec * 1e-9 if (st.sec or st.nanosec) else t_ns * 1e-9
                if not msg.header.frame_id and guess_axes:
                    # the frame_id is what says optical or body (REP-103): read as the phone's
                    # optical frame, a body-frame bag levelled its map on a wall (the mapper
                    # node skips such clouds too)
                    bad.append(NO_FRAME_ID)
                    yield np.empty((0, 3)), stamp, "", None, None, None
                    continue
                pose = prior_for(stamp, msg.header.frame_id)
                # the pixel grid, for the mixed-pixel test
                yield organised(pts, msg), stamp, msg.header.frame_id, conf, pose, t_ns * 1e-9
        except BagError as exc:
            if damage is None:
                raise InputError(str(exc)) from exc
            damage.append(str(exc))
        finally:
            reader.__exit__()

    return total, gen(), bad


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="wheelgrid map",
        description="Filter and register iPhone-LiDAR frames into a levelled 3D map "
        "(map frame: z up, z=0 on the floor, origin below the first sensor pose, "
        "x = first viewing direction on the floor).",
    )
    p.add_argument("input", type=Path, help="rosbag2 folder, ROS 1 .bag, or Stray export folder")
    p.add_argument("--out", type=out_folder, required=True, help="output folder")
    p.add_argument("--topic", help="PointCloud2 topic (default: the only one in the bag)")
    p.add_argument(
        "--config",
        type=Path,
        help="YAML with preprocess/registration/mapper/loop_closure sections",
    )
    p.add_argument(
        "--no-loop-closure",
        action="store_true",
        help="keep the online trajectory (skip the pose-graph refinement at the end)",
    )
    p.add_argument(
        "--prior",
        choices=["none", "arkit"],
        default="none",
        help="pose prior as initial guess: arkit = a Stray export's odometry.csv, or a bag's "
        "nav_msgs/Odometry topic (the bridge's /iphone/odometry); default none",
    )
    p.add_argument(
        "--prior-topic",
        help="the bag's Odometry topic for --prior arkit (default: the only one in the bag)",
    )
    p.add_argument("--method", choices=["kiss", "open3d"], help="override registration.method")
    p.add_argument(
        "--max-frames", type=int, default=0, help="stop after this many frames (0: every frame)"
    )
    return p


def right_angle_line(lc: dict[str, Any]) -> str:
    """The summary line on the room's right angles (``loop_closure.manhattan``): how many
    submaps were turned to them, or why none was, so a user mapping a room whose walls are not
    square learns that the graph did not assume they were."""
    if lc.get("manhattan_nodes"):
        walls = (
            f"; {lc['walls']} walls seen from several submaps tie them ({lc['wall_edges']} edges)"
            if lc.get("wall_edges")
            else ""
        )
        return (
            f"loop closure: {lc['manhattan_nodes']} of {lc['nodes']} submaps held to the "
            f"room's right angles (walls, legs and edges read modulo 90 deg){walls}"
        )
    return f"loop closure: the room's right angles not used ({lc['manhattan_note']})"


def prior_scale_line(ps: dict[str, Any]) -> str:
    """One line on the pose prior's scale as online ICP measured it, and what was done."""
    if ps["stderr_pct"] is None:  # "0.00 +- ? % ..., within 3 standard errors": none known
        return (
            f"loop closure: the pose prior's scale was not measured ({ps['steps']} stretches "
            f"of >= {PRIOR_SCALE_MIN_STEP * 100:g} cm that see ahead); kept"
        )
    se = f"{ps['stderr_pct']:.2f}"
    longer = "longer" if ps["measured_pct"] >= 0 else "shorter"
    line = (
        f"loop closure: the pose prior's steps are {abs(ps['measured_pct']):.2f} +- {se} % "
        f"{longer} than ICP measures them ({ps['steps']} stretches of >= "
        f"{PRIOR_SCALE_MIN_STEP * 100:g} cm that see ahead)"
    )
    if ps["applied"]:
        return line + (
            f"; frames registered again with its horizontal steps / {ps['prior_scale']:.4f} "
            f"(left: {ps['residual_pct']:+.2f} %)"
        )
    return line + f"; {ps.get('note', 'kept')}"


def floor_refound_line(level: dict[str, Any]) -> str | None:
    """One line when the map frame was taken from the floor found on the whole map (the first
    fit, on the first frames, was another plane): a user comparing two maps of one room, or
    a grid with an earlier one, must know the frame moved. None when it did not."""
    got = level.get("floor_refound")
    refused = (level.get("floor_check") or {}).get("refused")
    if not got:
        return f"levelling: warning: {refused}" if refused else None
    moved = got["moved_m"]
    return (
        f"levelling: the floor the first frames gave was not the whole map's: z = 0 moved to "
        f"the floor found at {got['at_frames']} frames, turned {got['turn_deg']:.2f} deg; the "
        f"first pose is {level.get('sensor_height_m', float('nan')):.2f} m above it, "
        f"{100 * abs(moved):.1f} cm {'less' if moved < 0 else 'more'} than above the old z = 0 "
        f"({got['points_on_floor_found']} map points on it against {got['points_on_z0']} on "
        f"the old z = 0)"
    )


def mount_check_line(level: dict[str, Any]) -> str | None:
    """One line when the floor the frames show disagrees with an explicit mount transform
    (:meth:`Mapper._mount_floor_check`); None when it agrees or nothing was checked."""
    warning = (level.get("mount_floor_check") or {}).get("warning")
    return f"levelling: warning: {warning}" if warning else None


def axes_lines(level: dict[str, Any]) -> list[str]:
    """A line each when the clouds' axes or the prior's vertical may have been read wrong:
    frames whose name says optical read as body (``sensor_convention: body``), and a prior
    whose vertical was no up the sensor could have. Each levelled a map on a wall, or on the
    floor alone, with exit 0 and no word (a review)."""
    lines = []
    if name := level.get("body_named_optical"):
        lines.append(
            f"levelling: warning: the clouds' frame {name!r} is optical by its name (REP-103), "
            "read as body because mapper.sensor_convention says so: if the map's floor is a "
            "wall, set it to auto"
        )
    if (lean := level.get("prior_not_gravity_deg")) is not None:
        lines.append(
            f"levelling: warning: the pose prior's vertical lies {lean:g} deg from any up the "
            "sensor could have, as its axes are read: not used, the map is levelled on the "
            "floor alone (a prior that is not gravity-aligned, or mapper.sensor_convention "
            "wrong for these clouds?)"
        )
    return lines


# A run where this share of the frames failed registration says so as a whole: each failure
# is a warning line of its own, and hundreds of them (a scan KISS-ICP lost) drowned the fact
# that the map as a whole is not to be trusted.
FAILED_SHARE_WARNING = 0.1


def failure_verdict(frames: dict[str, int], with_prior: bool) -> str:
    """One line on a run where many frames failed registration, or ''."""
    read, failed = frames.get("read", 0), frames.get("failed", 0)
    if read == 0 or failed < FAILED_SHARE_WARNING * read:
        return ""
    hint = "" if with_prior else "; a phone's capture maps with its own poses: --prior arkit"
    return (
        f"{failed} of {read} frames ({100 * failed / read:.0f} %) failed registration: the "
        f"stretches they cover may be misplaced or missing, check the map before a grid is made "
        f"from it{hint}"
    )


def lost_at_end(registration: dict[str, Any]) -> str:
    """One line where registration was still lost when the map was saved, or ''.

    Why: the frames after the last one mapped are missing from the map, and below
    :data:`FAILED_SHARE_WARNING` nothing else said so: a run that lost its way for the last
    stretch read as a map of the whole route."""
    if registration.get("state") != "relocalising":
        return ""
    n = registration.get("failed_since_used", 0)
    return (
        f"registration was still lost at the end: the last {n} frame(s) failed and the map "
        "ends at the last frame registered; the route after it is not mapped"
    )


def ensure_out_dir(out: Path) -> None:
    """The output folder made (or found writable) before the first frame is mapped: a typo in
    ``--out`` must cost a second, not a mapping run of minutes that then cannot be saved."""
    problem = folder_problem(out)
    if problem:
        raise InputError(f"--out {out}: {problem}")


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        return _run(args)
    except InputError as exc:
        print(f"wheelgrid map: {exc}", file=sys.stderr)
        return 2


def _run(args: argparse.Namespace) -> int:
    if args.max_frames < 0:
        raise InputError(f"--max-frames must be >= 0 (0: every frame), got {args.max_frames}")
    try:
        pre, reg, cfg, loop = load_configs(args.config)
        check_keyframe_interval(reg, cfg)
        thin_note = check_thin_obstacles(pre)  # a filter that erases a bar: refused here
    except (OSError, ValueError) as exc:
        raise InputError(f"config: {exc}") from exc
    if thin_note:
        print(f"WARNING {thin_note}", file=sys.stderr)
    if args.method:
        reg.method = args.method
    if args.prior_topic and args.prior != "arkit":
        raise InputError("--prior-topic names the prior's topic: give --prior arkit too")
    path: Path = args.input
    bad: list[str] = []
    damage: list[str] = []
    match = PriorMatch()
    stray = is_stray(path)
    if stray:
        if args.topic or args.prior_topic:
            raise InputError("--topic and --prior-topic apply to bags, not to a Stray export")
        total, frames = stray_frames(path, args.prior == "arkit", bad)
    else:
        _not_a_bag_hint(path)
        total, frames, bad = bag_frames(
            path,
            args.topic,
            args.prior == "arkit",
            args.prior_topic,
            match,
            damage,
            cfg.sensor_convention == "auto",
        )
    if args.max_frames > 0:
        # a bag's count is its metadata.yaml's: one that lists none (or too few) would cut
        # the run short of the frames asked for
        total = min(total, args.max_frames) if total else args.max_frames
        # islice stops before it asks for one frame more: the generators count a malformed
        # frame as they yield it, so the frame after the last one asked for, read only to
        # find the run over, was reported as skipped (and with --max-frames 1 a good first
        # frame then ended the run as 'no readable PointCloud2 frame')
        frames = itertools.islice(frames, args.max_frames)
    ensure_out_dir(args.out)
    if args.no_loop_closure:
        loop.enabled = False
    # an export's "receipt" is its capture order, on the stamps' own clock (captured_by)
    mapper = Mapper(pre, reg, cfg, keep_frames=loop.enabled, receipts_on_stamp_clock=stray)
    pipe = FramePipeline(mapper, cfg.prepare_ahead)
    t0 = time.perf_counter()
    n = 0
    causes_said: set[str] = set()

    def report(done: list[tuple[float, FrameOutcome]]) -> None:
        for _, out in done:
            k = out.number
            if out.status == "failed":
                print(
                    f"\nWARNING frame {k}: registration failed: {out.reason}; "
                    "map integration paused, relocalising",
                    file=sys.stderr,
                )
            elif out.status == "error":
                print(f"\nWARNING frame {k}: skipped, it raised {out.reason}", file=sys.stderr)
            elif out.status == "empty" and "empty" not in causes_said:
                # counted in report.json alone: 20 all-NaN clouds of 41 read "21 used, 0
                # failed" with no word of the other 20
                causes_said.add("empty")
                print(
                    f"\nWARNING frame {k} (and any like it): skipped: {out.reason}",
                    file=sys.stderr,
                )
            elif out.cause and out.cause not in causes_said:
                causes_said.add(out.cause)  # the report counts them all
                print(
                    f"\nWARNING frame {k} (and any like it): skipped: {out.reason}", file=sys.stderr
                )
            elif out.after_gap:
                print(f"\nframe {k}: after a dropout, placed against the map", file=sys.stderr)
            elif out.relocalised:
                print(f"\nframe {k}: relocalised against the map; mapping resumed", file=sys.stderr)

    with pipe, Progress(total, "mapping", "frames") as bar:
        # no stop at ``total`` here: a bag's count is its metadata.yaml's, which can list fewer
        # messages than its storage holds, and stopping there dropped the rest of the
        # recording without a word (--max-frames is the islice above)
        for pts, stamp, frame_id, conf, prior, received in frames:
            n += 1
            if pts.shape[0] == 0:
                if not stray and bad and bad[-1] not in causes_said:
                    # said once per cause, as the frames skipped for their stamps are: only
                    # the summary's count said a bag's clouds without a frame_id were dropped
                    # (an export's reader names each image it cannot read)
                    causes_said.add(bad[-1])
                    print(
                        f"\nWARNING frame {n - 1} (and any like it): unreadable, skipped: "
                        f"{bad[-1]}",
                        file=sys.stderr,
                    )
                bar.update(1)
                continue
            frame = (pts, stamp, frame_id or DEFAULT_FRAME_ID, conf, prior, received)
            report(pipe.push(*frame, number=n - 1))
            bar.update(1, postfix=f"used {mapper.registrar.counters.accepted}")
        report(pipe.flush())
        bar.finish(f"used {mapper.registrar.counters.accepted}")
    if damage and n == 0:
        raise InputError(damage[0])
    if n == 0:
        # the bag's index promised messages that its storage does not hold (a recording cut
        # off): "all 0 frames have no valid points" said the wrong thing
        raise InputError(
            f"{path}: its metadata lists {total} message(s) on the topic but none could be read: "
            "a recording cut short? `wheelgrid bag-recover` reads what such a bag holds"
        )
    if damage:
        # the frames before the damage were mapped: a whole run ended with exit 2 for it
        print(
            f"wheelgrid map: warning: {damage[0]}; the map is made from the {n} frame(s) "
            "read before it",
            file=sys.stderr,
        )
    elif n < total:
        # storage that lost messages its index lists (a zeroed MCAP chunk reads as none at
        # all): the map goes on from what was read, but those frames are missing from it, and
        # 'N frames read' alone did not say that N was less than the recording
        print(
            f"wheelgrid map: warning: {path}: its metadata lists {total} message(s) on the topic "
            f"but only {n} could be read; the other {total - n} are missing from the map "
            "(damaged storage?)",
            file=sys.stderr,
        )
    for unmatched in (match.warning(), match.other_frame_warning()):
        if unmatched:
            print(f"wheelgrid map: warning: {unmatched}", file=sys.stderr)
    if bad and len(bad) == n:
        hint = (
            f"; {NO_FRAME_ID}: set sensor_convention to optical or body in the --config "
            "file's mapper: section to say how their axes lie"
            if NO_FRAME_ID in bad
            else ""
        )
        what = "depth frame" if stray else "PointCloud2 frame"  # an export holds no clouds
        raise InputError(f"{path}: no readable {what} ({', '.join(sorted(set(bad)))}){hint}")
    if mapper.frames_empty == n - len(bad):
        if not bad:
            raise InputError(f"{path}: all {n} frames have no valid points (all NaN/out of range)")
        # "all 30 frames have no valid points" where 15 of them were unreadable
        raise InputError(
            f"{path}: no usable frame: {n - len(bad)} without valid points (all NaN/out of "
            f"range), {len(bad)} unreadable ({', '.join(sorted(set(bad)))})"
        )
    if mapper.registrar.counters.accepted == 0:
        print("wheelgrid map: no frame could be registered", file=sys.stderr)
        return 1
    if loop.enabled:
        with Progress(0, "loop closure", "submaps") as lbar:

            def tick(done: int, total: int) -> None:
                lbar.total = total
                lbar.update(done - lbar.count)

            lc = mapper.close_loops(loop, tick)
        print(
            f"loop closure: {lc['loop_edges']} loop edges over {lc['nodes']} submaps "
            f"({lc['loop_edges_rejected']} rejected, {lc['loop_edges_pruned']} pruned), "
            f"poses moved <= "
            f"{lc['max_pose_shift_m'] * 100:.1f} cm / {lc['max_pose_turn_deg']:.2f} deg, "
            f"{lc['passes']} solve(s), odometry drift removed "
            f"{lc['drift_scale_pct']:+.2f} % scale / {lc['drift_yaw_deg_per_m']:+.3f} deg/m "
            f"in {lc['seconds']:.1f} s" + (f" ({lc['drift_note']})" if "drift_note" in lc else ""),
            file=sys.stderr,
        )
        if "prior_drift_deg_per_m" in lc:
            print(
                f"loop closure: the pose prior drifts {lc['prior_drift_deg_per_m']:+.3f} deg/m"
                + (
                    f", wanders {lc['prior_walk_deg_per_sqrt_s']:.3f} deg/sqrt(s); its turns "
                    f"used on {lc.get('prior_steps', 0)} of {lc['nodes'] - 1} steps"
                    if "prior_walk_deg_per_sqrt_s" in lc
                    else ""
                )
                + (f" ({lc['prior_drift_note']})" if "prior_drift_note" in lc else ""),
                file=sys.stderr,
            )
        if lc.get("manhattan_nodes") or "manhattan_note" in lc:
            print(right_angle_line(lc), file=sys.stderr)
        if "prior_scale" in lc:
            print(prior_scale_line(lc["prior_scale"]), file=sys.stderr)
    try:
        rep = mapper.save(
            args.out,
            {
                "input": str(path),
                "malformed_frames": {c: bad.count(c) for c in sorted(set(bad))},
                # what the storage held back (said on stderr only: report.json read as a
                # complete run where 23 of 30 frames were behind a damaged chunk)
                "storage": {
                    "listed": total,
                    "read": n,
                    "damage": damage[0] if damage else None,
                },
                **(
                    {
                        "prior": {
                            "frames": match.frames,
                            "frames_without": len(match.missing),
                            "frames_of_another_frame": sum(match.other_frame.values()),
                        }
                    }
                    if match.odom_stamps is not None
                    else {}
                ),
                "wall_s": round(time.perf_counter() - t0, 3),
            },
        )
    except RuntimeError as exc:
        used = mapper.registrar.counters.accepted
        hint = (
            f" (only {used} frames registered: the map keeps a place only once "
            f"mapper.evidence_min_frames ({cfg.evidence_min_frames}) frames have seen it)"
            if used < 10
            else ""
        )
        # the counters report.json names them by (no whole report: it measures the map too)
        fr = {k: int(getattr(mapper, k)) for k in STAMP_OR_FRAME_SKIPS}
        fr["empty"] = mapper.frames_empty
        checked = stamp_or_frame_skips(fr)
        if checked + fr["empty"] > used:
            # a bag whose clouds all carry one stamp: 40 of 41 skipped as repeats, and the
            # message spoke of levelling alone
            hint += (
                f"; {checked + fr['empty']} of {n} frames were skipped before registration ("
                + ", ".join(f"{k} {fr[k]}" for k in (*STAMP_OR_FRAME_SKIPS, "empty") if fr[k])
                + "): check the clouds' header stamps and points"
            )
        print(f"wheelgrid map: cannot level the map: {exc}{hint}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"wheelgrid map: cannot write the map to {args.out}: {exc}", file=sys.stderr)
        return 1
    level = rep["levelling"]
    for line in (floor_refound_line(level), mount_check_line(level), *axes_lines(level)):
        if line:
            print(line, file=sys.stderr)
    fr = rep["frames"]
    wall = time.perf_counter() - t0
    skipped = f", {len(bad)} unreadable skipped" if bad else ""
    if fr.get("empty"):
        skipped += f", {fr['empty']} without a valid point skipped"
    checked = stamp_or_frame_skips(fr)
    if checked:
        skipped += f", {checked} skipped for their stamps or frame"
    if fr.get("skipped", 0) > checked:  # the rest: min_frame_interval's keyframe selection
        skipped += f", {fr['skipped'] - checked} between keyframes"
    missing = int(fr.get("without_confidence", 0))
    if missing and (stray or fr.get("with_confidence")):
        # an ARKit capture is expected to carry it, in every frame (a bag of another sensor,
        # none at all, is not warned of: report.json counts it)
        print(
            f"wheelgrid map: warning: {missing} of {fr['read']} frames had no ARKit confidence "
            f"(a Stray export's confidence/ images missing?): preprocess.min_confidence "
            f"({mapper.pre.min_confidence}) was not applied to them, and their low-confidence "
            "returns (most of them far, grazing or below the floor) are in the map",
            file=sys.stderr,
        )
    if fr.get("priors_refused"):
        print(
            f"wheelgrid map: warning: {fr['priors_refused']} pose priors were no rigid transform "
            "(NaN, a zero quaternion); those frames registered without one",
            file=sys.stderr,
        )
    if fr.get("prior_frozen"):
        print(
            f"wheelgrid map: warning: the pose prior stood still to the bit on "
            f"{fr['prior_frozen']} frames (its tracking lost?); ICP alone registered them where "
            "it could place them, the others failed",
            file=sys.stderr,
        )
    if fr.get("after_prior_gap"):
        print(
            f"wheelgrid map: warning: the pose prior came back after a pause of more than "
            f"{mapper.reg_cfg.max_gap:g} s {fr['after_prior_gap']} time(s); each frame it came "
            "back with was registered as after a dropout, every surface of it checked against "
            "the map",
            file=sys.stderr,
        )
    if fr.get("dropped_before_prior"):
        print(
            f"wheelgrid map: note: the map began again at the first frame with a pose prior; "
            f"{fr['dropped_before_prior']} frame mapped before it was dropped",
            file=sys.stderr,
        )
    if fr.get("after_gap"):
        print(
            f"wheelgrid map: warning: {fr['after_gap']} frame(s) came more than "
            f"{mapper.reg_cfg.max_gap:g} s after the frame before them (a dropout); each was "
            "registered as a relocalisation, every surface of it checked against the map",
            file=sys.stderr,
        )
    lost = lost_at_end(rep.get("registration", {}))
    if lost:
        print(f"wheelgrid map: warning: {lost}", file=sys.stderr)
    verdict = failure_verdict(fr, args.prior == "arkit")
    if verdict:
        print(f"wheelgrid map: warning: {verdict}", file=sys.stderr)
    # the unreadable frames are not in report.json's frames.read (the mapper never saw them)
    print(
        f"map: {fr['read'] + len(bad)} frames read{skipped}, {fr['used']} used, "
        f"{fr['failed']} failed "
        f"({fr['relocalised']} relocalised), {rep['points']['map']} points -> "
        f"{args.out / 'map.ply'} in {wall:.1f} s ({fr['read'] / max(wall, 1e-9):.1f} frames/s)"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
