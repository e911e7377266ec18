"""PointCloud2 <-> numpy: round trips, layouts ROS allows, and every malformed cloud named."""

import numpy as np
import pytest

from wheelgrid_common.pointcloud2 import (
    CloudError,
    organised,
    read_fields,
    read_xyz,
    to_pointcloud2,
)


def _field(name, offset, datatype=7):
    from sensor_msgs.msg import PointField

    return PointField(name=name, offset=offset, datatype=datatype, count=1)


def _counted(name, offset, count):
    field = _field(name, offset)
    field.count = count
    return field


def _cloud(n=12, height=3):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(n, 3))
    pts[1] = np.nan
    return pts, to_pointcloud2(
        pts, "cam", height=height, extra={"confidence": np.arange(n, dtype=np.uint8)}
    )


def test_round_trip_keeps_order_nan_and_extra_fields():
    pts, msg = _cloud()
    assert (msg.height, msg.width, msg.is_dense) == (3, 4, False)
    back = read_fields(msg, ("x", "y", "z"))
    assert np.isnan(back[1]).all()
    np.testing.assert_allclose(back[[0, 2, 3]], pts[[0, 2, 3]].astype(np.float32), rtol=0)
    assert read_fields(msg, ("confidence",))[:, 0].tolist() == list(range(12))
    assert read_xyz(msg).shape == (11, 3)


def test_organised_lays_the_rows_back_on_the_pixel_grid():
    _, msg = _cloud()
    rows = read_fields(msg, ("x", "y", "z"))
    grid = organised(rows, msg)
    assert grid.shape == (3, 4, 3)
    np.testing.assert_array_equal(grid[1, 2], rows[1 * 4 + 2])  # pixel (r, c) is row r*W + c
    _, flat = _cloud(height=1)
    assert organised(read_fields(flat), flat).shape == (12, 3)


def test_big_endian_and_row_padding_are_honoured():
    pts, msg = _cloud(6, 2)
    specs = [(f.name, f.offset) for f in msg.fields]
    raw = np.frombuffer(bytes(msg.data), dtype=np.uint8).reshape(2, -1)
    dt = np.dtype(
        {
            "names": ["x", "y", "z"],
            "formats": ["<f4"] * 3,
            "offsets": [o for _, o in specs[:3]],
            "itemsize": msg.point_step,
        }
    )
    rec = raw.copy().view(dt)
    be = np.zeros(rec.shape, dtype=dt.newbyteorder(">"))
    for k in "xyz":
        be[k] = rec[k]
    padded = np.zeros((2, msg.row_step + 8), dtype=np.uint8)
    padded[:, : msg.row_step] = be.view(np.uint8).reshape(2, -1)
    msg.is_bigendian = True
    msg.row_step += 8
    msg.data = padded.ravel().tobytes()
    np.testing.assert_allclose(read_xyz(msg), pts[np.isfinite(pts).all(1)].astype(np.float32))


@pytest.mark.parametrize(
    ("mutate", "cause"),
    [
        (lambda m: setattr(m, "fields", m.fields[:2]), "missing_fields"),
        (lambda m: setattr(m, "point_step", 8), "bad_point_step"),
        (lambda m: setattr(m, "data", bytes(m.data)[:-5]), "truncated_data"),
        (
            lambda m: (setattr(m, "width", 0), setattr(m, "height", 0), setattr(m, "data", b"")),
            "empty",
        ),
        # no points over bytes of data: not the mapper's empty map (which withdraws a grid)
        (lambda m: setattr(m, "width", 0), "excess_data"),
        (lambda m: setattr(m, "row_step", 3), "bad_row_step"),
        # a second x over the y bytes: which one is x is anyone's guess
        (lambda m: setattr(m, "fields", [*m.fields, _field("x", 4)]), "duplicate_fields"),
        # x, y and z all at offset 0: read as x = y = z, a cloud on one line, and mapped
        (
            lambda m: setattr(m, "fields", [_field("x", 0), _field("y", 0), _field("z", 0)]),
            "overlapping_fields",
        ),
        # z starting inside y
        (lambda m: setattr(m, "fields", [*m.fields[:2], _field("z", 6)]), "overlapping_fields"),
        # x of count 3 runs over y and z, z of count 2 past point_step: the count was ignored
        (
            lambda m: setattr(m, "fields", [_counted("x", 0, 3), *m.fields[1:]]),
            "overlapping_fields",
        ),
        (lambda m: setattr(m, "fields", [*m.fields[:2], _counted("z", 8, 2)]), "bad_point_step"),
        # one row more than the header says: the header does not describe the data
        (lambda m: setattr(m, "data", bytes(m.data) + bytes(m.row_step)), "excess_data"),
    ],
)
def test_malformed_clouds_raise_a_named_cause(mutate, cause):
    _, msg = _cloud()
    mutate(msg)
    with pytest.raises(CloudError) as err:
        read_xyz(msg)
    assert err.value.cause == cause


def test_a_repeated_field_is_refused_only_where_it_is_read():
    """Two fields named ``confidence`` make that field ambiguous, not x y z: the points are
    still read, the confidence is refused with a cause the node logs once."""
    pts, msg = _cloud()
    msg.fields = [*msg.fields, _field("confidence", 12, 2)]
    np.testing.assert_allclose(read_xyz(msg), pts[np.isfinite(pts).all(1)].astype(np.float32))
    with pytest.raises(CloudError) as err:
        read_fields(msg, ("confidence",))
    assert err.value.cause == "duplicate_fields" and "confidence" in str(err.value)
