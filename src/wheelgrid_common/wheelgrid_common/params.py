"""One config dataclass per stage, both for the CLI (YAML) and for nodes (ROS parameters).

A field documents itself through ``metadata={"doc": ..., "unit": ...}`` (use :func:`field`);
nodes declare every field as a ROS parameter with that description, so ``--ros-args
--params-file`` and ``ros2 param describe`` work, and CLIs load the same keys from YAML.
"""

from __future__ import annotations

import argparse
import collections.abc
import copy
import dataclasses
import functools
import math
import re
import typing
from pathlib import Path
from typing import Any, TypeVar

import yaml

T = TypeVar("T")

INT64_MAX = 2**63 - 1  # an IntegerRange's ends are int64
INT64_MIN = -(2**63)


def field(default: Any, doc: str, unit: str = "", bounds: tuple[float, float] | None = None) -> Any:
    """A dataclass field with a description (and unit) that becomes the ROS parameter's.

    ``bounds`` (lo, hi), closed, ``math.inf`` for none, become the parameter descriptor's
    range, so ``ros2 param describe`` shows them, rqt's reconfigure draws a slider and rclpy
    refuses a value outside before the node sees it. A config checks them too
    (:func:`check_bounds`): the CLIs read the same fields from YAML, without rclpy. The bounds
    are the hull of the valid values; an open end or a bound that depends on another field
    stays the config's own check."""
    meta: dict[str, Any] = {"doc": doc, "unit": unit}
    if bounds is not None:
        meta["bounds"] = bounds
    if isinstance(default, list | dict):
        # a copy per instance: a default list shared by every config was changed through one
        return dataclasses.field(
            default_factory=functools.partial(copy.copy, default), metadata=meta
        )
    return dataclasses.field(default=default, metadata=meta)


def bounds_of(cls: type) -> dict[str, tuple[float, float]]:
    """Field name -> its declared (lo, hi), for the fields that have them."""
    return {
        f.name: f.metadata["bounds"]
        for f in dataclasses.fields(cls)
        if f.metadata.get("bounds") is not None
    }


def check_bounds(cfg: Any, prefix: str = "") -> None:
    """``ValueError`` naming the first field of ``cfg`` outside its declared bounds."""
    for name, (lo, hi) in bounds_of(type(cfg)).items():
        value = getattr(cfg, name)
        if not lo <= value <= hi:
            unit = {f.name: f.metadata.get("unit", "") for f in dataclasses.fields(cfg)}[name]
            where = f"[{lo:g}, {hi:g}]" + (f" {unit}" if unit else "")
            raise ValueError(f"{prefix}{name} must be in {where}, not {value}")


def describe(cls: type) -> dict[str, str]:
    """Field name -> human description with unit, for --help texts and parameter descriptors."""
    out = {}
    for f in dataclasses.fields(cls):
        doc = f.metadata.get("doc", "")
        unit = f.metadata.get("unit", "")
        out[f.name] = f"{doc} [{unit}]" if unit else doc
    return out


def cli_help(cls: type) -> dict[str, str]:
    """``describe`` with each field's default, for --help: a CLI leaves its options unset so
    that a --config file can set them, and argparse then has no default to show."""
    out = describe(cls)
    for f in dataclasses.fields(cls):
        if f.default is not dataclasses.MISSING:
            value = f"{f.default:g}" if isinstance(f.default, float) else str(f.default)
            out[f.name] += f" (default {value})"
    return out


class DefaultsHelpFormatter(argparse.HelpFormatter):
    """argparse's defaults formatter without its noise: no "(default: None)" or
    "(default: False)" after an option that has no default or is a flag, and nothing added to a
    help text that already says what its default is."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if (
            "default" in text
            or default is None
            or isinstance(default, bool)
            or default is argparse.SUPPRESS
            or not action.option_strings
        ):
            return text
        return f"{text} (default %(default)s)" if text else "default %(default)s"


def _coerce(value: Any, typ: Any, name: str) -> Any:
    origin = typing.get_origin(typ)
    if typ is bool:
        if isinstance(value, bool):
            return value
        raise ValueError(f"{name}: expected true/false, got {value!r}")
    if typ is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
        raise ValueError(f"{name}: expected a number, got {value!r}")
    if typ is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise ValueError(f"{name}: expected an integer, got {value!r}")
    if typ is str:
        return str(value)
    if origin in (list, tuple):
        # A sequence (a YAML list; a ROS double array arrives as array.array) or nothing:
        # ``mount_xyz_rpy: 5`` ended in a TypeError traceback and ``[a, b, c, d, e, f]`` in
        # another once used; each item is checked as its type.
        if not isinstance(value, collections.abc.Sequence) or isinstance(value, str | bytes):
            raise ValueError(f"{name}: expected a list, got {value!r}")
        args = typing.get_args(typ)
        if origin is list and len(args) == 1:
            value = [_coerce(v, args[0], f"{name}[{i}]") for i, v in enumerate(value)]
        return list(value) if origin is list else tuple(value)
    return value


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, reading ``1e-4`` as the number rcl, yaml-cpp (Nav2's map_server)
    and YAML 1.2 read it as. PyYAML follows YAML 1.1, where a float needs a dot, and read it as
    a string: ``convergence: 1e-4`` ran in the mapper node from ``--params-file`` and was
    refused by ``wheelgrid map --config`` from the same file ("expected a number").

    A key written twice in one mapping is refused: PyYAML kept the last silently, where rcl
    applies both sections of a node written twice, so the grid's ``safe_height`` in the first
    ``grid:`` was lost from what ``wheelgrid launch --namespace`` and the CLIs read."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=deep)
            try:
                twice = key in seen
            except TypeError:  # an unhashable key: PyYAML's own error follows
                continue
            if twice:
                raise yaml.constructor.ConstructorError(
                    None,
                    None,
                    f"{key!r} is written twice in one mapping (write its entries once, together)",
                    key_node.start_mark,
                )
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


_SCIENTIFIC = "tag:wheelgrid,2026:scientific"


def _scientific(loader: yaml.SafeLoader, node: yaml.ScalarNode) -> float | str:
    """A plain ``1e-4``: its number, as rcl reads it; one that overflows (``1e400``) stays the
    text rcl keeps it as, not an infinity."""
    text = str(loader.construct_scalar(node))
    value = float(text)
    return value if math.isfinite(value) else text


# digits only, no "_" (rcl reads 1_0e5 as text), a dot optional, an exponent required
_Loader.add_implicit_resolver(
    _SCIENTIFIC, re.compile(r"^[-+]?[0-9]+(?:\.[0-9]*)?[eE][-+]?[0-9]+$"), list("-+0123456789")
)
_Loader.add_constructor(_SCIENTIFIC, _scientific)


def read_yaml(path: str | Path) -> Any:
    """A YAML file's document, a syntax error turned into a ``ValueError`` that names the file
    and the line: every CLI reports ``ValueError`` as a one-line error with exit 2, and a
    user who mistyped a bracket needs the line, not PyYAML's traceback."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except UnicodeDecodeError:  # a PLY or PGM given where a YAML belongs
        raise ValueError(f"{path}: not a YAML file (binary content)") from None
    try:
        return yaml.load(text, Loader=_Loader)  # a SafeLoader: builds plain data only
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc).splitlines()[0]
        raise ValueError(f"{path}: not valid YAML{where}: {problem}") from None


def check_finite(cfg: Any, prefix: str = "") -> None:
    """``ValueError`` naming the first float field of ``cfg`` that is NaN or infinite: a NaN
    passes every range test written as a comparison that fails (``x < lo``), so a config's
    range checks start with this one."""
    for f in dataclasses.fields(cfg):
        value = getattr(cfg, f.name)
        if isinstance(value, float) and not math.isfinite(value):
            raise ValueError(f"{prefix}{f.name} must be finite, not {value}")


def from_mapping(cls: type[T], values: dict[str, Any], *, strict: bool = True) -> T:
    """Build ``cls`` from a mapping, type-checking each value; unknown keys are errors."""
    if not isinstance(values, dict):
        raise ValueError(f"{cls.__name__}: expected a mapping of parameter: value, got {values!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(typing.cast(Any, cls))}
    unknown = sorted(set(values) - names)
    if unknown and strict:
        raise ValueError(f"unknown {cls.__name__} parameter(s): {', '.join(unknown)}")
    kwargs = {k: _coerce(v, hints[k], k) for k, v in values.items() if k in names}
    return cls(**kwargs)


def load_yaml(cls: type[T], path: str | Path | None, section: str | None = None) -> T:
    """Load a config from YAML.

    Accepts a plain mapping, a ``section:`` sub-mapping, or the ROS params-file layout
    ``node_name: {ros__parameters: {...}}`` so one file serves both CLIs and nodes.
    """
    if path is None:
        return cls()
    data = read_yaml(path)
    data = {} if data is None else data  # an empty file; `false` or `0` is no mapping
    if not isinstance(data, dict):
        raise ValueError(f"{path}: expected a mapping at the top level")
    if section and section in data:
        # an empty section (``grid:`` and nothing under it) means its defaults, as in the
        # mapping YAML's sections (load_configs)
        data = data[section] if data[section] is not None else {}
        if not isinstance(data, dict):
            raise ValueError(
                f"{path}: section {section!r} must be a mapping of parameter: value, got {data!r}"
            )
    if isinstance(data, dict) and "ros__parameters" in data:
        data = data["ros__parameters"]
    elif isinstance(data, dict) and len(data) == 1:
        (only,) = data.values()
        if isinstance(only, dict) and "ros__parameters" in only:
            data = only["ros__parameters"]
    return from_mapping(cls, data)


def check_no_undeclared(node: Any) -> None:
    """``ValueError`` naming every parameter given to ``node`` (a params file's section, ``-p``)
    that it never declared. ROS 2 ignores those silently, so ``safe_hieght: 1.4`` ran with the
    default safe height and exit 0. Called once a node has declared all of its parameters. A
    ``/**`` section reaches every node: it may hold only what each of them declares."""
    import difflib

    given = getattr(node, "_parameter_overrides", None) or {}
    unknown = sorted(name for name in given if not node.has_parameter(name))
    if not unknown:
        return
    declared = list(getattr(node, "_parameters", {}))
    parts = []
    for name in unknown:
        close = difflib.get_close_matches(name, declared, n=1)
        parts.append(f"{name!r}" + (f" (did you mean {close[0]!r}?)" if close else ""))
    raise ValueError(
        f"unknown parameter(s) {', '.join(parts)} for node {node.get_name()!r}: a misspelt "
        "setting would silently keep its default (`ros2 param list` on a full ROS install, or "
        "the node's section of src/wheelgrid_bringup/config/wheelgrid.yaml, lists them)"
    )


def declare_dataclass(node: Any, cfg: T, prefix: str = "", *, read_only: bool = True) -> T:
    """Declare every field of ``cfg`` as a described ROS parameter and return the values read.

    Defaults come from ``cfg`` (so a YAML-loaded config can seed them); overrides come from the
    usual ``--ros-args -p`` / ``--params-file`` mechanisms. A node that reads its values once,
    at start-up, declares them ``read_only``: otherwise ``ros2 param set drive speed 10`` was
    answered "successful" and changed nothing (the chair stays capped at 3 km/h, but a user
    reading the parameter back saw 10). Only a node that applies and checks changes at run
    time (the grid node) passes ``read_only=False``.
    """
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
    from rclpy.exceptions import ParameterException

    docs = describe(type(cfg))
    values = {}
    for f in dataclasses.fields(typing.cast(Any, cfg)):
        name = prefix + f.name
        default = getattr(cfg, f.name)
        if isinstance(default, tuple):
            default = list(default)
        # rclpy types an empty list as a byte array, and then refuses every real value for
        # it (a mount transform could not be set at all): such a parameter takes any type,
        # and from_mapping checks what arrives.
        descriptor = ParameterDescriptor(
            description=docs[f.name],
            dynamic_typing=isinstance(default, list) and not default,
            read_only=read_only,
        )
        bounds = f.metadata.get("bounds")
        if bounds is not None and isinstance(default, float):
            descriptor.floating_point_range = [
                FloatingPointRange(from_value=float(bounds[0]), to_value=float(bounds[1]))
            ]
        elif bounds is not None and isinstance(default, int) and not isinstance(default, bool):
            # int64 ends for an open one: math.copysign gave the float 2^63, one past it, and
            # a describe request (`ros2 param describe`, rqt) killed the node sending it back
            lo, hi = (
                int(b) if math.isfinite(b) else INT64_MAX if b > 0 else INT64_MIN for b in bounds
            )
            descriptor.integer_range = [IntegerRange(from_value=lo, to_value=hi, step=1)]
        try:
            node.declare_parameter(name, default, descriptor)
        except ParameterException as exc:  # a value of the wrong type: one line, not a trace
            hint = ""
            whole = re.search(r"to '(-?\d+)' of type 'INTEGER', expecting type 'DOUBLE'", str(exc))
            if whole:  # the CLIs' --config reads 2 as 2.0; rclpy refuses it: say how to write it
                hint = f" (write a decimal point: {whole[1]}.0, not {whole[1]})"
            raise ValueError(f"parameter {name}: {exc}{hint}") from None
        values[f.name] = node.get_parameter(name).value
    _fix_use_sim_time(node)
    return from_mapping(type(cfg), values)


def _fix_use_sim_time(node: Any) -> None:
    """Describe rclpy's own ``use_sim_time`` and make it read-only, in every node: the one
    parameter a running node still took, with no description, and its stamps (the drive's
    state and pose, the bridge's receive times, the mapper's arrival check) fell to 0 at once
    where no /clock ran."""
    from rcl_interfaces.msg import ParameterDescriptor, ParameterType

    if node.describe_parameter("use_sim_time").read_only:
        return  # a node that declares two configs (the planner, the mapper): done once
    node.set_descriptor(
        "use_sim_time",
        ParameterDescriptor(
            type=ParameterType.PARAMETER_BOOL,
            description="stamp with the /clock topic's time (a bag's); set at start: -p, a "
            "params file, or `wheelgrid launch --clock`",
            read_only=True,
        ),
    )
