"""PointCloud2 <-> numpy without sensor_msgs_py (the ROS wheels do not ship it).

Works on rclpy messages and on messages deserialised by ``rosbags`` alike: both expose
``fields`` (name, offset, datatype, count), ``point_step``, ``row_step``, ``height``, ``width``,
``is_bigendian``, ``is_dense`` and ``data``. Every way a cloud can be malformed raises
:class:`CloudError` with a short machine-readable ``cause`` so that nodes can log each cause once.
"""

from __future__ import annotations

import array
import itertools
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

# sensor_msgs/PointField datatype constants.
INT8, UINT8, INT16, UINT16, INT32, UINT32, FLOAT32, FLOAT64 = 1, 2, 3, 4, 5, 6, 7, 8
_DTYPES: dict[int, str] = {
    INT8: "i1",
    UINT8: "u1",
    INT16: "i2",
    UINT16: "u2",
    INT32: "i4",
    UINT32: "u4",
    FLOAT32: "f4",
    FLOAT64: "f8",
}
_NUMPY_TO_DATATYPE: dict[str, int] = {v: k for k, v in _DTYPES.items()}


class CloudError(ValueError):
    """A PointCloud2 that cannot be read; ``cause`` names why (stable, for log-once)."""

    def __init__(self, cause: str, detail: str) -> None:
        super().__init__(f"{cause}: {detail}")
        self.cause = cause
        self.detail = detail


@dataclass(frozen=True)
class FieldSpec:
    """One PointField, decoupled from any message class."""

    name: str
    offset: int
    datatype: int
    count: int = 1


def _field_specs(msg: Any) -> list[FieldSpec]:
    return [FieldSpec(f.name, int(f.offset), int(f.datatype), int(f.count)) for f in msg.fields]


def _raw_bytes(msg: Any) -> np.ndarray:
    data = msg.data
    if isinstance(data, np.ndarray):
        return data.view(np.uint8).reshape(-1)
    if isinstance(data, array.array):
        return np.frombuffer(data, dtype=np.uint8)
    return np.frombuffer(bytes(data), dtype=np.uint8)


def read_fields(msg: Any, names: Iterable[str] = ("x", "y", "z")) -> np.ndarray:
    """Return an ``(height*width, len(names))`` float64 array of the named fields.

    Row padding (``row_step > width*point_step``) and big-endian data are honoured. Invalid
    points stay in place as NaN (organised clouds keep their pixel order); callers drop them.
    """
    names = tuple(names)
    height, width = int(msg.height), int(msg.width)
    point_step, row_step = int(msg.point_step), int(msg.row_step)
    if height * width == 0:
        if len(msg.data):
            # A header of no points over bytes of data does not describe its data: taken as
            # "empty", the grid node read it as the mapper's ~/reset and withdrew a good grid.
            raise CloudError(
                "excess_data",
                f"cloud has {height}x{width} points but {len(msg.data)} B of data",
            )
        raise CloudError("empty", f"cloud has {height}x{width} points")
    fields = _field_specs(msg)
    # A name given twice leaves which field holds the values to the decoder's whim (the last
    # one, silently): refused, as sensor_msgs_py's numpy dtype would. Only the names read are
    # checked: a repeated field the caller does not read cannot change what it gets.
    given = [f.name for f in fields]
    repeated = sorted({n for n in names if given.count(n) > 1})
    if repeated:
        raise CloudError("duplicate_fields", f"field(s) {repeated} defined more than once")
    specs = {f.name: f for f in fields}
    missing = [n for n in names if n not in specs]
    if missing:
        raise CloudError("missing_fields", f"no field(s) {missing}; has {sorted(specs)}")
    order = ">" if msg.is_bigendian else "<"
    spans = []  # (first byte, end, name) of each field read
    for n in names:
        spec = specs[n]
        if spec.datatype not in _DTYPES:
            raise CloudError("bad_datatype", f"field {n!r} has unknown datatype {spec.datatype}")
        # a field of count N takes N elements (the first is read): x of count 3 over y and
        # z, or z of count 2 past point_step, is a header that does not describe its data
        size = np.dtype(_DTYPES[spec.datatype]).itemsize * max(int(spec.count), 1)
        if spec.count < 1 or spec.offset < 0 or spec.offset + size > point_step:
            raise CloudError(
                "bad_point_step",
                f"field {n!r} at offset {spec.offset} (+{size} B) does not fit point_step "
                f"{point_step}",
            )
        spans.append((spec.offset, spec.offset + size, n))
    # Fields read that share bytes (x, y and z all at offset 0) decode as x = y = z, a cloud
    # on one line that the mapper took as frames: refused as the header's error it is.
    for (_, end, a), (start, _, b) in itertools.pairwise(sorted(spans)):
        if start < end:
            raise CloudError(
                "overlapping_fields", f"fields {a!r} and {b!r} share bytes (offsets overlap)"
            )
    if row_step < width * point_step:
        raise CloudError(
            "bad_row_step", f"row_step {row_step} < width {width} x point_step {point_step}"
        )
    raw = _raw_bytes(msg)
    if raw.size < row_step * height:
        raise CloudError(
            "truncated_data",
            f"data has {raw.size} B, expected row_step {row_step} x height {height}",
        )
    if raw.size > row_step * height:
        # ROS defines the data as exactly row_step x height bytes. More means the header does
        # not describe the data (a height, width or row_step too small): reading its first
        # part would drop points silently or take the rows from the wrong bytes.
        raise CloudError(
            "excess_data",
            f"data has {raw.size} B, more than row_step {row_step} x height {height}",
        )
    dtype = np.dtype(
        {
            "names": list(names),
            "formats": [order + _DTYPES[specs[n].datatype] for n in names],
            "offsets": [specs[n].offset for n in names],
            "itemsize": point_step,
        }
    )
    rows = raw[: row_step * height].reshape(height, row_step)[:, : width * point_step]
    structured = np.ascontiguousarray(rows).view(dtype).reshape(-1)
    out = np.empty((structured.shape[0], len(names)), dtype=np.float64)
    for i, n in enumerate(names):
        out[:, i] = structured[n]
    return out


def read_xyz(msg: Any, *, drop_invalid: bool = True) -> np.ndarray:
    """Return the cloud's points as ``(N, 3)`` float64; drops NaN/inf rows unless told not to."""
    xyz = read_fields(msg, ("x", "y", "z"))
    if drop_invalid:
        xyz = xyz[np.isfinite(xyz).all(axis=1)]
    return xyz


def organised(points: np.ndarray, msg: Any) -> np.ndarray:
    """``read_fields``' rows laid back on the cloud's pixel grid, ``(height, width, k)``, when
    the cloud is organised (height > 1): per-pixel filters need each point's neighbours.
    An unorganised cloud's rows are returned as they are."""
    if int(msg.height) > 1:
        return points.reshape(int(msg.height), int(msg.width), -1)
    return points


def has_field(msg: Any, name: str) -> bool:
    return any(f.name == name for f in msg.fields)


def pack_points(
    points: np.ndarray, extra: Mapping[str, np.ndarray] | None = None
) -> tuple[list[FieldSpec], int, bytes]:
    """Pack ``(N, 3)`` xyz (stored as float32) plus optional per-point scalar fields.

    Returns the field list, the point step and the little-endian payload, ready for either an
    rclpy or a rosbags PointCloud2.
    """
    pts = np.asarray(points)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be (N, 3), got {pts.shape}")
    columns: list[tuple[str, np.ndarray]] = [
        ("x", pts[:, 0].astype("<f4")),
        ("y", pts[:, 1].astype("<f4")),
        ("z", pts[:, 2].astype("<f4")),
    ]
    for name, values in (extra or {}).items():
        v = np.asarray(values)
        if v.shape != (pts.shape[0],):
            raise ValueError(f"field {name!r} must have shape ({pts.shape[0]},), got {v.shape}")
        columns.append((name, v.astype(v.dtype.newbyteorder("<"))))
    specs: list[FieldSpec] = []
    offset = 0
    for name, col in columns:
        key = col.dtype.str.lstrip("<>|=")
        if key not in _NUMPY_TO_DATATYPE:
            raise ValueError(f"field {name!r}: dtype {col.dtype} has no PointField datatype")
        specs.append(FieldSpec(name, offset, _NUMPY_TO_DATATYPE[key], 1))
        offset += col.dtype.itemsize
    point_step = offset
    dtype = np.dtype(
        {
            "names": [n for n, _ in columns],
            "formats": [c.dtype for _, c in columns],
            "offsets": [s.offset for s in specs],
            "itemsize": point_step,
        }
    )
    packed = np.empty(pts.shape[0], dtype=dtype)
    for name, col in columns:
        packed[name] = col
    return specs, point_step, packed.tobytes()


def to_pointcloud2(
    points: np.ndarray,
    frame_id: str,
    stamp: Any = None,
    *,
    height: int = 1,
    extra: Mapping[str, np.ndarray] | None = None,
) -> Any:
    """Build an rclpy ``sensor_msgs/PointCloud2``.

    ``height > 1`` makes an organised cloud (``width = N / height``); organised clouds keep NaN
    points and are marked ``is_dense = False``.
    """
    from sensor_msgs.msg import PointCloud2, PointField

    n = int(np.asarray(points).shape[0])
    if height < 1 or n % height:
        raise ValueError(f"{n} points cannot form {height} rows")
    specs, point_step, payload = pack_points(points, extra)
    msg = PointCloud2()
    msg.header.frame_id = frame_id
    if stamp is not None:
        msg.header.stamp = stamp
    msg.height = height
    msg.width = n // height
    msg.fields = [
        PointField(name=s.name, offset=s.offset, datatype=s.datatype, count=s.count) for s in specs
    ]
    msg.is_bigendian = False
    msg.point_step = point_step
    msg.row_step = point_step * msg.width
    msg.data = array.array("B", payload)
    msg.is_dense = bool(np.isfinite(np.asarray(points)).all())
    return msg
