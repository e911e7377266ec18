"""Levelled map frame from the floor (optical and body conventions, pitched/rolled) or a mount."""

from __future__ import annotations

import math

import numpy as np
import pytest

from wheelgrid_mapping.cli_map import axes_lines, mount_check_line
from wheelgrid_mapping.levelling import (
    FloorNotFoundError,
    convention_for_frame,
    find_floor,
    floor_of_map,
    lean_within,
    map_from_floor,
    map_from_mount,
    rpy_matrix,
)
from wheelgrid_mapping.pipeline import PRIOR_FLOOR_LEAN_DEG, Mapper, MapperConfig

# optical (x right, y down, z forward) expressed in body (x forward, y left, z up)
BODY_FROM_OPTICAL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def room_points(rng: np.random.Generator) -> np.ndarray:
    """World (z up, floor z=0): floor 6x6 m, a table top at 0.72 m, two walls."""
    floor = np.column_stack([rng.random((20000, 2)) * 6 - 3, np.zeros(20000)])
    table = np.column_stack(
        [rng.random(6000) * 1.5 + 0.5, rng.random(6000) * 1.0 - 0.5, np.full(6000, 0.72)]
    )
    wall = np.column_stack([np.full(8000, 3.0), rng.random(8000) * 6 - 3, rng.random(8000) * 2.5])
    wall2 = np.column_stack([rng.random(8000) * 6 - 3, np.full(8000, 3.0), rng.random(8000) * 2.5])
    return np.vstack([floor, table, wall, wall2]) + rng.normal(0, 0.004, (42000, 3))


def sensor_pose(yaw: float, pitch: float, roll: float, conv: str, height: float) -> np.ndarray:
    """world_from_sensor for a sensor at (0.3, -0.2, height), body rpy, in ``conv`` axes."""
    T = np.eye(4)
    R_body = rpy_matrix(roll, pitch, yaw)
    T[:3, :3] = R_body @ BODY_FROM_OPTICAL if conv == "optical" else R_body
    T[:3, 3] = [0.3, -0.2, height]
    return T


@pytest.mark.parametrize("conv", ["optical", "body"])
@pytest.mark.parametrize(
    ("pitch_deg", "roll_deg"),
    # 30 and 30 at once tilt the sensor 41.4 deg: refused while the limit was 40 deg
    [(0.0, 0.0), (25.0, 0.0), (-20.0, 10.0), (10.0, -30.0), (30.0, 30.0), (-30.0, -30.0)],
)
def test_floor_levelling_meets_the_convention(conv: str, pitch_deg: float, roll_deg: float) -> None:
    rng = np.random.default_rng(5)
    world = room_points(rng)
    yaw = 0.4
    T = sensor_pose(yaw, math.radians(pitch_deg), math.radians(roll_deg), conv, 1.1)
    inv = np.linalg.inv(T)
    pts = world @ inv[:3, :3].T + inv[:3, 3]  # sensor frame = odom at the first pose
    down = {"optical": np.array([0, 1.0, 0]), "body": np.array([0, 0, -1.0])}[conv]
    n, d = find_floor(pts, down)
    M = map_from_floor(n, d, conv)
    # The map frame of the convention: rotation about z by -yaw, origin below the sensor.
    expect = np.eye(4)
    expect[:3, :3] = rpy_matrix(0, 0, -yaw)
    expect[:3, 3] = expect[:3, :3] @ -np.array([0.3, -0.2, 0.0])
    expect = expect @ T  # map_from_sensor0
    got = M
    ang = math.degrees(
        math.acos(np.clip((np.trace(expect[:3, :3].T @ got[:3, :3]) - 1) / 2, -1, 1))
    )
    assert ang < 1.0, ang
    assert np.linalg.norm(expect[:3, 3] - got[:3, 3]) < 0.03
    levelled = pts @ M[:3, :3].T + M[:3, 3]
    floor_z = levelled[:20000, 2]
    assert abs(np.median(floor_z)) < 0.01
    # Origin is below the sensor: the sensor sits at (0, 0, 1.1) in the map.
    assert np.allclose(M[:3, 3], [0, 0, 1.1], atol=0.03)


def test_table_top_is_not_taken_for_the_floor() -> None:
    rng = np.random.default_rng(6)
    world = room_points(rng)
    # Much more table than floor in view.
    extra = np.column_stack(
        [rng.random(40000) * 1.5 + 0.5, rng.random(40000) - 0.5, np.full(40000, 0.72)]
    )
    world = np.vstack([world, extra])
    T = sensor_pose(0.0, math.radians(20), 0.0, "optical", 1.2)
    inv = np.linalg.inv(T)
    pts = world @ inv[:3, :3].T + inv[:3, 3]
    n, d = find_floor(pts, np.array([0, 1.0, 0]))
    assert n @ np.zeros(3) + d == pytest.approx(1.2, abs=0.02)  # sensor 1.2 m above floor


def test_no_floor_raises() -> None:
    rng = np.random.default_rng(7)
    wall = np.column_stack([np.full(5000, 3.0), rng.random(5000), rng.random(5000)])
    with pytest.raises(FloorNotFoundError):
        find_floor(wall, np.array([0, 0, -1.0]))


def test_mount_transform_gives_the_same_frame() -> None:
    # Sensor 0.9 m above the floor, body convention, pitched 20 deg down.
    M = map_from_mount([0.1, 0.0, 0.9, 0.0, math.radians(20), 0.0], "body")
    sensor_in_map = M[:3, 3]
    assert np.allclose(sensor_in_map, [0, 0, 0.9], atol=1e-9)
    # A floor point straight ahead of the sensor lands on z = 0.
    ahead = np.array([0.9 / math.tan(math.radians(20)), 0, 0])
    R = rpy_matrix(0, math.radians(20), 0)
    p_sensor = R.T @ (ahead - np.array([0, 0, 0.9]))
    assert (M[:3, :3] @ p_sensor + M[:3, 3])[2] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError):
        map_from_mount([1, 2, 3], "body")


def test_convention_from_frame_id() -> None:
    assert convention_for_frame("iphone_depth_optical_frame") == "optical"
    assert convention_for_frame("base_link") == "body"
    assert convention_for_frame("base_link", "optical") == "optical"
    with pytest.raises(ValueError):
        convention_for_frame("x", "sideways")


def warped_room(rng: np.random.Generator) -> np.ndarray:
    """World (z up): a 10 x 8 m floor whose height wanders +-4 cm (the drift of an online map),
    a ceiling at 2.6 m, a table top at 0.72 m with as many points as the floor, two walls."""
    xy = rng.random((40000, 2)) * [10, 8] - [5, 4]
    floor = np.column_stack([xy, 0.04 * np.sin(xy[:, 0] / 1.3) * np.cos(xy[:, 1] / 1.7)])
    ceiling = np.column_stack([rng.random((30000, 2)) * [10, 8] - [5, 4], np.full(30000, 2.6)])
    table = np.column_stack([rng.random((40000, 2)) * [2, 1] + [1, 1], np.full(40000, 0.72)])
    wall = np.column_stack(
        [np.full(20000, 5.0), rng.random(20000) * 8 - 4, rng.random(20000) * 2.6]
    )
    wall2 = np.column_stack(
        [rng.random(20000) * 10 - 5, np.full(20000, 4.0), rng.random(20000) * 2.6]
    )
    pts = np.vstack([floor, ceiling, table, wall, wall2])
    return pts + rng.normal(0, 0.01, pts.shape)


def test_the_floor_of_a_whole_map_is_found_from_a_vertical_a_few_degrees_off() -> None:
    """The check on the first floor fit: the map's z axis 4 deg off the true vertical and 20 cm
    under the floor (the real capture's first fit was 3.3-4.6 deg off, 17-21 cm from the
    floor). The floor comes back within a fraction of a degree and a centimetre, though the
    table top holds as many points and the floor wanders +-4 cm; and twice the same."""
    rng = np.random.default_rng(31)
    world = warped_room(rng)
    tilt = rpy_matrix(math.radians(3.0), math.radians(-2.65), 0.3)  # 4.0 deg off vertical
    T = np.eye(4)
    T[:3, :3] = tilt
    T[:3, 3] = [0.0, 0.0, 0.2]  # the map's z = 0 lies 20 cm under the floor at the origin
    pts = world @ T[:3, :3].T + T[:3, 3]
    sensor = T[:3, :3] @ np.array([0.0, 0.0, 1.4]) + T[:3, 3]
    n, d = floor_of_map(pts, np.array([0.0, 0.0, 1.0]), sensor)
    true_up = T[:3, :3] @ np.array([0.0, 0.0, 1.0])
    assert math.degrees(math.acos(min(1.0, float(n @ true_up)))) < 0.2
    assert float(n @ sensor + d) == pytest.approx(1.4, abs=0.01)  # the sensor above the floor
    n2, d2 = floor_of_map(pts, np.array([0.0, 0.0, 1.0]), sensor)
    assert np.array_equal(n, n2) and d == d2


def test_a_map_with_nothing_level_below_the_sensor_has_no_floor_to_check() -> None:
    rng = np.random.default_rng(32)
    world = warped_room(rng)
    high = world[world[:, 2] > 0.5]  # no floor: the table top is below the sensor at 1.4 m
    n, d = floor_of_map(high, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.4]))
    assert float(n @ np.array([0.0, 0.0, 1.4]) + d) == pytest.approx(0.68, abs=0.01)
    walls = world[(np.abs(world[:, 0]) > 4.9) | (world[:, 1] > 3.9)]
    walls = walls[(walls[:, 2] > 0.1) & (walls[:, 2] < 2.5)]
    with pytest.raises(FloorNotFoundError):
        floor_of_map(walls, np.array([0.0, 0.0, 1.0]), np.array([0.0, 0.0, 1.4]))


def leaning_patch_view(rng: np.random.Generator, lean_deg: float) -> np.ndarray:
    """What the real capture's first frames saw, in the body convention (z up, sensor 1.6 m up):
    two walls and a table, and of the floor only a 1 x 1 m patch 3 m ahead whose points lean
    ``lean_deg`` (range noise and lens distortion at a grazing view)."""
    walls = np.vstack(
        [
            np.column_stack(
                [np.full(6000, 5.0), rng.random(6000) * 6 - 3, rng.random(6000) * 2.5 - 1.6]
            ),
            np.column_stack(
                [rng.random(4000) * 5, np.full(4000, 3.0), rng.random(4000) * 2.5 - 1.6]
            ),
            np.column_stack(
                [1 + rng.random(3000), -1 + rng.random(3000), np.full(3000, 0.75 - 1.6)]
            ),
        ]
    )
    xy = rng.random((1500, 2)) + np.array([2.5, -0.5])
    patch = np.column_stack([xy, -1.6 + math.tan(math.radians(lean_deg)) * (xy[:, 0] - 3.0)])
    pts = np.vstack([walls, patch])
    return pts + rng.normal(0, 0.003, pts.shape)


def test_a_known_vertical_fits_only_the_floors_height() -> None:
    """With gravity known (a gravity-aligned pose prior), a floor patch that leans 3.3 deg no
    longer tilts the floor: fitted as a plane it puts z = 0 16 cm off under the sensor, 3 m
    away (the real capture's first fit: 17-21 cm); along the known vertical it is right."""
    rng = np.random.default_rng(33)
    pts = leaning_patch_view(rng, 3.3)
    down = np.array([0.0, 0.0, -1.0])
    n, d = find_floor(pts, down)
    assert math.degrees(math.acos(float(n[2]))) > 2.5 and abs(d - 1.6) > 0.12
    n, d = find_floor(pts, down, vertical=True)
    assert np.array_equal(n, np.array([0.0, 0.0, 1.0]))
    assert d == pytest.approx(1.6, abs=0.005)
    # the table top, 85 cm under the sensor, is still not the floor
    assert find_floor(pts[pts[:, 2] > -1.0], down, vertical=True)[1] == pytest.approx(
        0.85, abs=0.005
    )


def test_nan_points_do_not_move_the_floor_of_a_map() -> None:
    """A map is filtered before it is checked, but NaN or inf points (a bad frame, a bad
    file) must not change the floor found, nor raise."""
    rng = np.random.default_rng(34)
    world = warped_room(rng)
    sensor = np.array([0.0, 0.0, 1.4])
    up = np.array([0.0, 0.0, 1.0])
    bad = world.copy()
    bad[::7] = np.nan
    bad[1::11, 2] = np.inf
    clean = bad[np.isfinite(bad).all(axis=1)]
    n, d = floor_of_map(bad, up, sensor)
    n2, d2 = floor_of_map(clean, up, sensor)
    assert np.array_equal(n, n2) and d == d2
    assert float(n @ sensor + d) == pytest.approx(1.4, abs=0.01)


@pytest.mark.parametrize("prior", ["gravity", "gravity, ignored", "y-up VIO"])
def test_the_mapper_takes_its_first_vertical_from_a_gravity_aligned_prior(prior: str) -> None:
    """The Mapper's first fit on the leaning patch: with a prior whose z is gravity (ARKit
    through the Stray adapter or the bridge, REP-105 odom) z = 0 is right under the sensor and
    the report gives the map frame's angle to the prior's gravity; with ``prior_gravity`` off,
    or a prior whose frame is not gravity-aligned (its z 90 deg from this upright sensor's
    up), the floor's own plane, as before, and the report says why."""
    rng = np.random.default_rng(35)
    m = Mapper(cfg=MapperConfig(level_min_frames=2, prior_gravity=prior != "gravity, ignored"))
    pose = np.eye(4)  # the sensor stands still, level: its body frame's z is up
    if prior == "y-up VIO":
        pose[:3, :3] = rpy_matrix(math.pi / 2, 0.0, 0.0)  # the prior's world y is up
    for i in range(2):
        out = m.add_frame(leaning_patch_view(rng, 3.3), i * 0.2, "base_link", prior=pose)
        assert out.status == "used"
    assert m.T_map_odom is not None
    info = m.report()["levelling"]
    height = info["sensor_height_m"]
    if prior == "gravity":
        assert info["vertical"] == "pose prior's gravity"
        assert height == pytest.approx(1.6, abs=0.01)
        assert info["prior_gravity_deg"] < 0.05
        assert "prior_not_gravity_deg" not in info
        # the relevelling fits the map's floor, the patch, but leans at most 1.5 deg from
        # gravity (the live node relevels each map it publishes, from the first frames on)
        m.map_points()
        info = m.report()["levelling"]
        assert info["relevelled_tilt_deg"] > 1.0
        # the height reported is the map frame's as written (it stayed the first fit's)
        first_z = float(m.trajectory()[1][0][2, 3])
        assert info["sensor_height_m"] == pytest.approx(first_z, abs=1e-9)
        assert info["first_fit_sensor_height_m"] == pytest.approx(height, abs=1e-9)
        assert info["prior_gravity_deg"] == pytest.approx(PRIOR_FLOOR_LEAN_DEG, abs=0.01)
    else:
        # the patch's lean, halved by the level surfaces' vote (12 cm and more without it)
        assert info["vertical"] == "floor plane" and abs(height - 1.6) > 0.03
        assert "prior_gravity_deg" not in info
        if prior == "y-up VIO":
            assert info["prior_not_gravity_deg"] == pytest.approx(90.0, abs=0.5)


def test_axes_read_against_the_frame_name_or_a_prior_that_is_no_vertical_are_said() -> None:
    """``sensor_convention: body`` on clouds whose frame is named ``*_optical_frame`` levelled
    a map on a wall with exit 0 and no word, and the gravity prior it threw out was in no
    report when the first levelling had come short of floor points (a review). Both are in
    the levelling report now, and each is a warning line of `wheelgrid map` and the node."""
    rng = np.random.default_rng(38)
    m = Mapper(cfg=MapperConfig(level_min_frames=2, sensor_convention="body"))
    y_up = np.eye(4)
    y_up[:3, :3] = rpy_matrix(math.pi / 2, 0.0, 0.0)  # the prior's world y is up
    name = "camera_depth_optical_frame"
    assert m.add_frame(leaning_patch_view(rng, 3.3), 0.0, name, prior=y_up).status == "used"
    assert not m.try_level()  # one frame: nothing in the map yet, no floor
    assert m.level_info["method"] == "none"
    assert m.add_frame(leaning_patch_view(rng, 3.3), 0.2, name, prior=y_up).status == "used"
    info = m.report()["levelling"]
    assert info["vertical"] == "floor plane"
    assert info["prior_not_gravity_deg"] == pytest.approx(90.0, abs=0.5)
    assert info["body_named_optical"] == name
    lines = axes_lines(info)
    assert len(lines) == 2
    assert f"the clouds' frame {name!r} is optical by its name" in lines[0]
    assert "the pose prior's vertical lies 90 deg" in lines[1]
    assert axes_lines({"method": "floor"}) == []


def test_lean_within_turns_toward_up_in_the_common_plane_only_as_far_as_needed() -> None:
    up = np.array([0.0, 0.0, 1.0])
    n = np.array([math.sin(math.radians(4.0)), 0.0, math.cos(math.radians(4.0))])
    kept = lean_within(n, up, 1.5)
    assert math.degrees(math.acos(float(kept @ up))) == pytest.approx(1.5, abs=1e-9)
    assert kept[1] == 0.0 and kept[0] > 0.0 and np.linalg.norm(kept) == pytest.approx(1.0)
    assert lean_within(n, up, 5.0) is n


def test_the_floor_of_a_map_leans_no_more_than_allowed_from_a_known_gravity() -> None:
    """With gravity known, the whole-map floor search keeps its normal within ``max_lean_deg``
    of it and takes the floor's height along that normal."""
    rng = np.random.default_rng(36)
    world = warped_room(rng)
    tilt = rpy_matrix(math.radians(3.0), 0.0, 0.0)
    pts = world @ tilt.T  # the map leans 3 deg against gravity (z)
    sensor = tilt @ np.array([0.0, 0.0, 1.4])
    up = np.array([0.0, 0.0, 1.0])
    free, _ = floor_of_map(pts, up, sensor)
    assert math.degrees(math.acos(float(free @ up))) == pytest.approx(3.0, abs=0.3)
    n, d = floor_of_map(pts, up, sensor, max_lean_deg=1.0)
    assert math.degrees(math.acos(float(n @ up))) == pytest.approx(1.0, abs=1e-6)
    assert float(n @ sensor + d) == pytest.approx(1.4, abs=0.02)


def test_a_prior_that_begins_later_and_is_no_vertical_does_not_tilt_the_floor() -> None:
    """The first fit came from the floor alone (no prior yet); then a y-up prior arrives. The
    later fits must not take its z (horizontal here) for up: it is refused and said, and the
    floor stays at z = 0."""
    from wheelgrid_common.testing import body_frame_room

    rng = np.random.default_rng(37)
    m = Mapper(cfg=MapperConfig(level_min_frames=2))
    for i in range(2):
        assert m.add_frame(body_frame_room(rng, True), i * 0.2, "base_link").status == "used"
    assert m.level_info["vertical"] == "floor plane"
    y_up = np.eye(4)
    y_up[:3, :3] = rpy_matrix(math.pi / 2, 0.0, 0.0)
    for i in range(2, 4):
        m.add_frame(body_frame_room(rng, True), i * 0.2, "base_link", prior=y_up)
    pts = m.map_points()
    info = m.report()["levelling"]
    assert info["prior_not_gravity_deg"] == pytest.approx(90.0, abs=0.5)
    assert "prior_gravity_deg" not in info
    assert np.mean(np.abs(pts[:, 2]) < 0.03) > 0.3  # the floor is still at z = 0


@pytest.mark.parametrize(
    ("height_off", "pitch_off_deg", "warned"), [(0.0, 0.0, False), (0.3, 8.0, True)]
)
def test_a_mount_transform_the_seen_floor_contradicts_is_used_and_said(
    height_off: float, pitch_off_deg: float, warned: bool
) -> None:
    """An explicit mount is taken as given (the floor may be hidden from the sensor), but a
    floor the first frames plainly show 30 cm and 8 deg off it made a map leaning 3.4 deg,
    with exit 0 and nothing said: the report now carries the floor against the mount, and a
    warning where they disagree."""
    rng = np.random.default_rng(41)
    T = sensor_pose(0.0, math.radians(15), 0.0, "body", 1.0)
    inv = np.linalg.inv(T)
    pts = room_points(rng) @ inv[:3, :3].T + inv[:3, 3]
    mount = [0.3, -0.2, 1.0 + height_off, 0.0, math.radians(15 + pitch_off_deg), 0.0]
    m = Mapper(cfg=MapperConfig(level_min_frames=2, mount_xyz_rpy=mount))
    for i in range(2):
        assert m.add_frame(pts, i * 0.2, "base_link", prior=np.eye(4)).status == "used"
    assert m.T_map_odom is not None
    level = m.report()["levelling"]
    check = level["mount_floor_check"]
    assert check["floor_seen"]
    line = mount_check_line(level)  # what wheelgrid map prints, and the node logs
    assert (line is not None and line.startswith("levelling: warning: ")) == warned
    if warned:
        assert check["tilt_deg"] == pytest.approx(pitch_off_deg, abs=0.3)
        assert check["height_off_m"] == pytest.approx(-height_off, abs=0.05)
        assert "check the mount transform" in check["warning"]
        assert "above the floor mount_xyz_rpy gives" in check["warning"]
    else:
        assert check["tilt_deg"] < 0.3 and abs(check["height_off_m"]) < 0.01
        assert "warning" not in check
    # the map frame is the mount's either way
    assert np.allclose(m.T_map_odom, map_from_mount(mount, "body"))


def _mount_check(world: np.ndarray, T: np.ndarray, mount: list[float]) -> dict:
    inv = np.linalg.inv(T)
    pts = world @ inv[:3, :3].T + inv[:3, 3]
    m = Mapper(cfg=MapperConfig(level_min_frames=2, mount_xyz_rpy=mount))
    for i in range(2):
        assert m.add_frame(pts, i * 0.2, "base_link", prior=np.eye(4)).status == "used"
    return m.report()["levelling"]["mount_floor_check"]


def test_the_mount_check_is_not_fooled_by_a_ramp_and_sees_a_mount_far_off() -> None:
    """A correct mount at the foot of a ramp rising 6 deg ahead was warned of: the floor search
    takes the lowest level plane, and the ramp, extended back under the chair, is lower. A
    mount 50 deg off (a pitch of the wrong sign) was not: the search about its vertical found
    nothing within 45 deg, and said nothing."""
    rng = np.random.default_rng(41)
    room = room_points(rng)
    pitch = math.radians(15)
    T = sensor_pose(0.0, pitch, 0.0, "body", 1.0)
    n = 5000
    x = rng.random(n) * 1.8 + 1.0
    ramp = np.column_stack([x, rng.random(n) * 1.2 - 1.5, (x - 1.0) * math.tan(math.radians(6))])
    flat = room[:, 2] < 0.05
    under = flat & (room[:, 0] > 1.0) & (room[:, 0] < 2.8) & (room[:, 1] > -1.5)
    under &= room[:, 1] < -0.3
    ramped = np.vstack([room[~under], ramp + rng.normal(0, 0.004, (n, 3))])
    check = _mount_check(ramped, T, [0.3, -0.2, 1.0, 0.0, pitch, 0.0])
    assert check["tilt_deg"] > 5.0  # the ramp was found ...
    assert check["points_on_mount_floor"] > 2 * check["points_on_floor_found"]
    assert "warning" not in check  # ... and the mount's floor holds more: no warning
    T25 = sensor_pose(0.0, math.radians(25), 0.0, "body", 1.0)
    check = _mount_check(room, T25, [0.3, -0.2, 1.0, 0.0, math.radians(-25), 0.0])
    assert check["tilt_deg"] == pytest.approx(50.0, abs=0.5) and "warning" in check


def _map_a_room(extra: list, start: tuple[float, float], height: float, pitch_deg: float):
    """A 4.8 x 4.2 m room with three posts and ``extra`` (wheelgrid_sim Boxes), mapped without
    a prior from 20 frames of a camera ``height`` up, pitched ``pitch_deg`` down, starting at
    ``start`` and moving 3 cm forward and 1 cm left a frame, the map read every 3 frames as
    the live node publishes it (relevelled, the floor checked): (mapper, the map's tilt from
    true up in degrees, the first pose's height over z = 0)."""
    from wheelgrid_sim.camera import DepthCamera, depth_to_points
    from wheelgrid_sim.scene import Box, Scene, shell_boxes
    from wheelgrid_sim.trajectory import camera_pose

    room = (0.0, 0.0, 4.8, 4.2)
    posts = [
        Box("post", "post", (4.0, 1.8, 0.0), (4.3, 2.1, 1.8)),
        Box("p1", "post", (0.3, 0.3, 0.0), (0.5, 0.5, 1.5)),
        Box("p2", "post", (0.3, 3.6, 0.0), (0.5, 3.8, 1.5)),
    ]
    scene = Scene(room, shell_boxes(room) + posts + extra)
    cam = DepthCamera(stride=2)
    rng = np.random.default_rng(1)
    m = Mapper()
    poses = []
    for i in range(20):
        x, y = start[0] + 0.03 * i, start[1] + 0.01 * i
        poses.append(camera_pose(x, y, height, 0.0, math.radians(pitch_deg)))
        pts = depth_to_points(cam.render(scene, poses[-1], rng), cam.intrinsics())
        m.add_frame(pts.astype(np.float32), 0.1 * i, "iphone_depth_optical_frame")
        if m.T_map_odom is not None and i % 3 == 2:
            m.map_points()
    first = m.T_map_odom @ m.poses_odom[0]
    up_in_camera, true_up = first[:3, :3].T[:, 2], poses[0][:3, :3].T[:, 2]
    tilt = math.degrees(math.acos(min(1.0, float(up_in_camera @ true_up))))
    return m, tilt, float(first[2, 3])


def test_a_floor_seen_only_beside_a_large_low_table_levels_the_map_and_stays_the_floor() -> None:
    """A camera 1 m up, pitched 30 deg down at a 2.9 x 3 m table 45 cm high, the floor seen
    only beside it, no pose prior (a review): RANSAC's slab through the strip of floor leaned
    7-13 deg, the map frame came out 9.4 deg off, and the floor check on the whole map then
    moved z = 0 on to the table top (the real floor, in strips, held too few cells to be its
    peak): the first pose 0.55 m above "the floor", every obstacle lower than the table under
    the grid's band. The first fit takes its vertical from the level surfaces' vote, the
    relevelling leans no further from it than from a prior's gravity, and the check keeps z = 0
    off a plane with floor below it, and says so."""
    from wheelgrid_sim.scene import Box

    table = Box("table", "table", (1.6, 1.5, 0.40), (4.5, 4.5, 0.45))
    m, tilt, height = _map_a_room([table], (1.0, 2.6), 1.0, 30.0)
    assert tilt < 2.0 and height == pytest.approx(1.0, abs=0.05), (tilt, height)
    info = m.level_info
    assert info["first_fit_refined"]["turn_deg"] > 5.0  # RANSAC's plane, turned level
    # the check found the floor (within 5 cm of z = 0) or the table, refused
    refound = info.get("floor_refound")
    assert refound is None or abs(refound["moved_m"]) < 0.05, info


@pytest.mark.parametrize("scene", ["attic", "ramp"])
def test_a_sloped_ceiling_or_a_ramp_leaves_the_first_fit_as_ransac_gave_it(scene: str) -> None:
    """The vote first took every level surface: a ceiling sloping down ahead (an attic, 11
    deg) turned the frame 9.6 deg, z = 0 64 cm up, obstacles under 0.5 m near the start read as
    floor; and a 1:12 ramp's normals, bounding the relevelling, left the frame 2.4 deg off
    where it had been 1.7 (a review). Only what lies 30 cm below the sensor votes, and a fit
    the vote nearly agrees with (under 3 deg) is kept as RANSAC gave it."""
    from wheelgrid_sim.scene import Box

    post = Box("p3", "post", (3.0, 3.4, 0.0), (3.2, 3.6, 1.2))  # the review's fourth post
    if scene == "attic":
        extra = [
            Box(f"c{k}", "ceiling", (1.5 + 0.1 * k, -0.2, 2.68 - 0.02 * k), (5.0, 4.4, 2.9))
            for k in range(33)
        ]
        m, tilt, height = _map_a_room([post, *extra], (0.8, 2.4), 1.5, 0.0)
        assert tilt < 2.0 and height == pytest.approx(1.5, abs=0.05), (tilt, height)
    else:
        extra = [
            Box(f"r{k}", "ramp", (2.2 + 0.24 * k, 1.0, 0.0), (4.8, 3.4, 0.02 * (k + 1)))
            for k in range(11)
        ]
        m, tilt, height = _map_a_room([post, *extra], (0.8, 2.4), 1.0, 30.0)
        assert tilt < 2.0 and height == pytest.approx(1.0, abs=0.05), (tilt, height)
    assert "kept" in m.level_info["first_fit_refined"], m.level_info


def test_the_floor_check_does_not_lift_z0_on_to_a_table_with_floor_below_it() -> None:
    """The whole map's level peak is a 3 x 3 m table top 45 cm up, the floor beside it 100
    cells of 5 cm (too few to be a peak of its own): z = 0 stays, and the check says why
    (the review's map had z = 0 moved 54 cm up on to such a table, silently)."""
    from wheelgrid_mapping.cli_map import floor_refound_line

    rng = np.random.default_rng(3)
    table = np.column_stack([rng.random((60000, 2)) * 3 + [1.0, -1.5], np.full(60000, 0.45)])
    floor = np.column_stack([rng.random((3000, 2)) * 0.5 + [1.0, 1.8], np.zeros(3000)])
    m = Mapper()
    m.T_map_odom = np.eye(4)
    first = np.eye(4)
    first[2, 3] = 1.0
    m.poses_odom = [first]
    pts = np.vstack([table, floor]) + rng.normal(0, 0.002, (63000, 3))
    assert not m._check_floor(pts, 10)
    check = m.level_info["floor_check"]
    assert check["moved_m"] == pytest.approx(-0.45, abs=0.02), check  # it found the table
    assert "45 cm above z = 0" in check["refused"] and np.array_equal(m.T_map_odom, np.eye(4))
    assert "mount_xyz_rpy" in check["refused"]
    line = floor_refound_line(m.level_info)
    assert line is not None and line.startswith("levelling: warning: the floor found")
