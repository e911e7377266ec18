"""Which axes a frame has, read from its name as REP-103 names them (ROS-free).

The mapper reads a cloud's frame by this rule, and the planner a pose's child frame: when the
two read one frame differently, the planner took a camera looking along +z for one looking
along +x, and the chair's start heading came out 90 deg wrong (a turn the route's Table II
actions then made on the wrong side).
"""

from __future__ import annotations

CONVENTIONS = ("auto", "optical", "body")


def convention_for_frame(frame_id: str, setting: str = "auto") -> str:
    """``optical`` (z forward, x right, y down) or ``body`` (x forward, y left, z up): an
    explicit setting wins; ``auto`` follows REP-103's suffix (``*_optical``,
    ``*_optical_frame``)."""
    if setting in ("optical", "body"):
        return setting
    if setting != "auto":
        raise ValueError(f"sensor_convention must be auto, optical or body, not {setting!r}")
    return "optical" if frame_id.endswith(("optical_frame", "optical")) else "body"


def other_frame(pose_frame: str, cloud_frame: str) -> bool:
    """A pose of another frame than the cloud's, both named: no pose prior for it. With no tf
    here to chain a base_link pose to the camera, read as the camera's it was an initial guess
    off by the mount, and its vertical levelled the map by a wrong gravity."""
    return bool(pose_frame and cloud_frame and pose_frame != cloud_frame)
