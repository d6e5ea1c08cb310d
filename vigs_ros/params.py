"""Node parameters: declared in the node with a default and a description, loaded from ``params/*.yaml``.

YAML layout (the ROS 2 parameter-file layout, read by rcl itself from ``--ros-args --params-file F``)::

    <node name>:            # or /** for every node
      ros__parameters:
        name: value

Several files may be given; later ones override earlier ones. :func:`load_params_file` reads the same
layout in Python, for checks and for tools that run without rcl.
"""
from __future__ import annotations

import dataclasses
import functools
import inspect
import math
import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from vigs_core.ranges import Range, field_range

PARAMS_DIR = Path(__file__).resolve().parent.parent / "params"
_ENTRY = re.compile(r"([A-Za-z_]\w*(?:,\s*[A-Za-z_]\w*)*):\s*(.*)")


@dataclass(frozen=True)
class ParamSpec:
    """One declared parameter: ``name``, ``default`` (its type is the parameter's type), ``description``;
    ``dynamic_typing`` accepts values of another type (e.g. an integer YAML value for a float field); ``range``:
    the valid values of a number (:func:`vigs_core.ranges.bounded`), None for any."""

    name: str
    default: Any
    description: str
    dynamic_typing: bool = False
    range: Range | None = None


def declare(node, specs: list[ParamSpec]) -> dict[str, Any]:
    """Declare ``specs`` on an rclpy ``node`` and return ``{name: value}`` (overrides applied by rcl).

    A spec with a range: the declared value (default or override) is checked here, a ValueError naming the node,
    the parameter, the range and the value (rclpy checks a range only on a value of its type, and a dynamically
    typed float parameter may hold an int, ``gravity: 10``; nor can a descriptor express a ``lo_open`` end). Then
    the range goes into the parameter's descriptor (``floating_point_range`` / ``integer_range``, by the default's
    type), so rcl refuses later out-of-range sets and ``ros2 param describe`` shows it.
    """
    from rcl_interfaces.msg import ParameterDescriptor

    values = {}
    for spec in specs:
        if node.has_parameter(spec.name):
            values[spec.name] = node.get_parameter(spec.name).value
            continue
        descriptor = ParameterDescriptor(description=spec.description, dynamic_typing=spec.dynamic_typing)
        param = node.declare_parameter(spec.name, spec.default, descriptor)
        value = param.value
        if spec.range is not None:
            if isinstance(value, (int, float)) and not isinstance(value, bool) and value not in spec.range:
                raise ValueError(f"node {node.get_name()}: parameter {spec.name}: expected a value in {spec.range}, "
                                 f"got {value!r}")
            node.set_descriptor(spec.name, _with_range(descriptor, spec))
        if isinstance(spec.default, (list, tuple)) and value is not None:
            value = list(value)
        values[spec.name] = value
    return values


def _with_range(descriptor, spec: ParamSpec):
    """``descriptor`` with ``spec.range`` as a closed range of the default's type (any value between: float step 0,
    int step 1; an open end is unbounded, inf or the int64 limit)."""
    from rcl_interfaces.msg import FloatingPointRange, IntegerRange

    lo, hi = spec.range.lo, spec.range.hi
    if isinstance(spec.default, float):
        descriptor.floating_point_range = [FloatingPointRange(
            from_value=-math.inf if lo is None else float(lo), to_value=math.inf if hi is None else float(hi))]
    else:
        int64 = 2 ** 63 - 1
        descriptor.integer_range = [IntegerRange(from_value=-int64 - 1 if lo is None else math.ceil(lo),
                                                 to_value=int64 if hi is None else math.floor(hi), step=1)]
    return descriptor


def dataclass_specs(config, prefix: str = "", skip: tuple[str, ...] = ()) -> list[ParamSpec]:
    """ParamSpecs ``<prefix><field>`` for the fields of a config dataclass (class or instance; defaults from it),
    recursing into nested dataclasses with dotted names (``odometry.flow.preset``), as rcl flattens nested
    YAML mappings.

    Fields named in ``skip`` (dotted, without the prefix), fields without a default, and fields whose value
    is not a bool, int, float, str or a non-empty list/tuple of numbers (e.g. ``None``) are left out: they are
    not expressible as ROS parameters. Numbers are declared with dynamic typing (``10`` for a float field) and
    the field's range (:func:`vigs_core.ranges.field_range`).
    """
    specs = []
    cls = config if isinstance(config, type) else type(config)
    for f in dataclasses.fields(config):
        if f.name in skip:
            continue
        if not isinstance(config, type):
            default = getattr(config, f.name)
        elif f.default is not dataclasses.MISSING:
            default = f.default
        elif f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = f.default_factory()  # type: ignore[misc]
        else:
            continue
        if dataclasses.is_dataclass(default):
            inner_skip = tuple(s[len(f.name) + 1:] for s in skip if s.startswith(f.name + "."))
            specs += dataclass_specs(default, f"{prefix}{f.name}.", inner_skip)
            continue
        if isinstance(default, tuple):
            default = list(default)
        ok_list = isinstance(default, list) and default and all(isinstance(v, (int, float)) for v in default)
        if not (isinstance(default, (bool, int, float, str)) or ok_list):
            continue
        description = field_descriptions(cls).get(f.name) or f"{cls.__name__}.{f.name}"
        number = isinstance(default, (int, float)) and not isinstance(default, bool)
        specs.append(ParamSpec(prefix + f.name, default, description,
                               dynamic_typing=not isinstance(default, (bool, str)),
                               range=field_range(f) if number else None))
    return specs


@functools.cache
def field_descriptions(cls: type) -> dict[str, str]:
    """``{field: description}`` from the ``Args:`` / ``Attributes:`` section of a config class's docstring (the
    one source of its documentation; Google style: ``name: text`` or ``a, b: text`` at one indentation,
    continuation lines deeper, a blank line ends the section), whitespace joined."""
    out: dict[str, str] = {}
    names: list[str] = []
    indent = None
    in_section = False
    for line in inspect.cleandoc(cls.__doc__ or "").splitlines():
        text, lead = line.strip(), len(line) - len(line.lstrip())
        if text in ("Args:", "Attributes:"):
            in_section, indent, names = True, None, []
            continue
        if not in_section:
            continue
        entry = _ENTRY.fullmatch(text)
        if not text or (indent is not None and lead < indent):
            in_section = False
        elif entry and (indent is None or lead == indent):
            indent, names = lead, [n.strip() for n in entry.group(1).split(",")]
            out.update({n: entry.group(2) for n in names})
        elif names and lead > indent:
            out.update({n: f"{out[n]} {text}" for n in names})
    return out


def nested(values: dict[str, Any], prefix: str) -> dict[str, Any]:
    """The ``<prefix>a.b`` entries of ``values`` as a nested mapping ``{"a": {"b": ...}}``."""
    out: dict[str, Any] = {}
    for key, value in values.items():
        if not key.startswith(prefix):
            continue
        *parents, leaf = key[len(prefix):].split(".")
        d = out
        for p in parents:
            d = d.setdefault(p, {})
        d[leaf] = value
    return out


def build_config(default, values: dict[str, Any], prefix: str = ""):
    """``default`` (a config dataclass instance) with the ``<prefix>...`` parameters of ``values`` applied and
    type-checked (:func:`vigs_core.system.apply_overrides`; list values of tuple fields become tuples)."""
    from vigs_core.system import apply_overrides

    return apply_overrides(default, nested(values, prefix))


def load_params_file(path: str | Path, node_name: str) -> dict[str, Any]:
    """The ``ros__parameters`` of ``node_name`` in a params file (``/**`` entries first, then the node's).

    Raises:
        ValueError: the file is not a mapping of ``<node>: {ros__parameters: {...}}``
        (:func:`vigs_core.system.config.read_params_yaml`).
    """
    from vigs_core.system.config import read_params_yaml

    path = Path(path)
    data = read_params_yaml(path)
    out: dict[str, Any] = {}
    for key in ("/**", node_name, "/" + node_name):
        section = data.get(key)
        if section is not None:
            out.update(_flatten(section["ros__parameters"] or {}))
    return out


RCL_PARAMS = ("use_sim_time",)   # declared by rclpy itself on every node


def check_params_file(path: str | Path, node_specs: dict[str, list[ParamSpec]]) -> None:
    """Check a parameter file against the nodes' declared parameters ``{node name: specs}``: valid YAML, only
    known node sections (or ``/**``), only declared keys (a ``/**`` key: declared by some node) and values of the
    declared type (a float takes an int) within the declared range. ValueError naming the file, the node, the key
    and what was expected: rcl would ignore an unknown key, and a wrong type or a value out of range would stop the
    node with a traceback."""
    from vigs_core.system.config import read_params_yaml

    path = Path(path)
    data = read_params_yaml(path)
    for node, section in data.items():
        name = str(node).lstrip("/")
        if node != "/**" and name not in node_specs:
            raise ValueError(f"{path}: unknown node {node!r}; expected /** or one of {sorted(node_specs)}")
        specs = [s for v in node_specs.values() for s in v] if node == "/**" else node_specs[name]
        by_name = {s.name: s for s in specs}
        for key, value in _flatten(section.get("ros__parameters") or {}).items():
            if key in RCL_PARAMS:
                continue
            if key not in by_name:
                inner = sorted(n for n in by_name if n.startswith(key + "."))
                if inner:
                    raise ValueError(f"{path}: parameter {key!r} of {node}: expected a mapping of its fields "
                                     f"(e.g. {inner[0][len(key) + 1:]}), got {value!r}")
                raise ValueError(f"{path}: unknown parameter {key!r} of {node}")
            problem = _type_problem(by_name[key].default, value, by_name[key].range)
            if problem:
                raise ValueError(f"{path}: parameter {key!r} of {node}: {problem}")


def _type_problem(default: Any, value: Any, rng: Range | None = None) -> str | None:
    """Why ``value`` cannot set a parameter declared with ``default`` and range ``rng`` (the dataclass type and
    range check, :func:`vigs_core.system.config.checked_value`, on the default's type; a list needs a non-empty
    list), or None."""
    from vigs_core.system.config import ParameterTypeError, checked_value

    if isinstance(default, (list, tuple)):
        ok = isinstance(value, list) and len(value) > 0
        return None if ok else f"expected a non-empty list, got {value!r} ({type(value).__name__})"
    try:
        checked_value(value, type(default), "", rng)
    except ParameterTypeError as err:
        return err.problem
    return None


def _flatten(d: dict, prefix: str = "") -> dict[str, Any]:
    """Nested mappings become dotted names, as rcl does (``a: {b: 1}`` -> ``a.b``)."""
    out = {}
    for k, v in d.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def default_params_files() -> list[Path]:
    """The shipped ``params/*.yaml`` files, ``ros.yaml`` (graph-wide) first, then the nodes' in name order."""
    files = sorted(PARAMS_DIR.glob("*.yaml"))
    return sorted(files, key=lambda p: (p.name != "ros.yaml", p.name))
