"""ROS parameter declarations generated from the single definition (:mod:`mkf_ros.core.params`).

Every :class:`~mkf_ros.core.params.Param` becomes a statically typed ROS parameter whose
``ParameterDescriptor`` carries the description with unit, a ``FloatingPointRange`` /
``IntegerRange``, the allowed choices in ``additional_constraints``, and ``read_only`` where
the definition says so. Integers given for floating-point parameters (``max_dt:=1`` on the
command line, ``max_dt: 1`` in YAML) are accepted as doubles.

Parameters that would be silently ignored are named instead: start-up overrides that match
no parameter (:func:`unknown_overrides`: a typo, or another filter's parameter), and
parameter files or ``-p node:name:=value`` rules addressed to another IMU filter's node name
(:func:`foreign_filter_rules`: a parameter file of imu_filter_madgwick, keyed
``imu_filter_madgwick:`` or ``imu_filter:``, given to this node).
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import yaml
from rcl_interfaces.msg import FloatingPointRange, IntegerRange, ParameterDescriptor
from rclpy.exceptions import ParameterNotDeclaredException
from rclpy.node import Node
from rclpy.parameter import Parameter

from mkf_ros.core.params import BY_NAME, PARAMS, REMOVED, Param, removed_hint
from mkf_ros.ros import calibration

#: imu_filter_madgwick / imu_complementary_filter parameters without a same-named equivalent.
FOREIGN_HINTS: dict[str, str] = {
    "gain": "imu_filter_madgwick's gain has no equivalent: the Kalman gain follows from "
            "acc_noise, acc_disturbance and gyro_noise",
    "zeta": "imu_filter_madgwick's zeta: use estimate_gyro_bias (and gyro_bias_noise)",
    "stateless": "stateless mode is not supported",
    "use_magnetic_field_msg": "a ROS 1 parameter: imu/mag is always sensor_msgs/MagneticField",
    "gain_acc": "imu_complementary_filter's gain_acc: tune acc_noise / acc_disturbance",
    "gain_mag": "imu_complementary_filter's gain_mag: tune mag_noise / mag_disturbance",
    "do_bias_estimation": "use estimate_gyro_bias",
    "bias_alpha": "use gyro_bias_noise",
    "do_adaptive_gain": "accelerometer disturbances are modelled by acc_disturbance and "
                        "acc_magnitude_tolerance",
}


def unknown_hint(name: str) -> str:
    """Why ``name`` is not a parameter here: a foreign filter's parameter and what replaces
    it, or a typo and the closest names."""
    hint = FOREIGN_HINTS.get(name)
    if name in REMOVED:
        hint = f"removed: {removed_hint(name)}"
    elif hint is None:
        close = difflib.get_close_matches(name, list(BY_NAME), n=3, cutoff=0.6)
        hint = "not a parameter of this node" + (
            f" (did you mean {' or '.join(map(repr, close))}?)" if close else " (typo?)")
    elif name == "gain" and "madgwick_beta" in BY_NAME:
        hint += " (with algorithm madgwick: madgwick_beta)"
    return hint


class UnknownParameter(ParameterNotDeclaredException):
    """SetParameters with a name the node does not have: rclpy's own exception (its parameter
    service turns it into the refusal's reason) with a message that names the parameter and
    says why (rclpy's says "Invalid access to undeclared parameter(s): []")."""

    def __init__(self, name: str) -> None:
        Exception.__init__(self, f"unknown parameter {name!r}: {unknown_hint(name)}")


def descriptor(p: Param) -> ParameterDescriptor:
    """The ROS descriptor of one parameter."""
    d = ParameterDescriptor(name=p.name, description=p.doc(), read_only=p.read_only)
    constraints = []
    if p.range is not None:
        lo, hi = p.range
        if p.type is float:
            d.floating_point_range = [FloatingPointRange(from_value=float(lo), to_value=float(hi),
                                                         step=0.0)]
        elif p.type is int:
            d.integer_range = [IntegerRange(from_value=int(lo), to_value=int(hi), step=0)]
        else:
            constraints.append(f"each element in [{lo:g}, {hi:g}]")
    if p.choices:
        constraints.append("one of: " + ", ".join(p.choices))
    if p.type is list and p.length:
        constraints.insert(0, f"{p.length} numbers")
    d.additional_constraints = "; ".join(constraints)
    return d


def default_value(p: Param) -> Any:
    """The default as the ROS type wants it (floats for float parameters and lists)."""
    if p.type is float:
        return float(p.default)
    if p.type is list:
        return [float(x) for x in p.default]
    return p.default


def to_double(param: Parameter) -> Parameter:
    """An INTEGER(_ARRAY) value for a float (list) parameter converted to DOUBLE(_ARRAY)."""
    p = BY_NAME.get(param.name) or calibration.BY_NAME.get(param.name)
    if p is None:
        return param
    if p.type is float and param.type_ == Parameter.Type.INTEGER:
        return Parameter(param.name, Parameter.Type.DOUBLE, float(param.value))
    if p.type is list and param.type_ == Parameter.Type.INTEGER_ARRAY:
        return Parameter(param.name, Parameter.Type.DOUBLE_ARRAY, [float(x) for x in param.value])
    return param


def coerce_overrides(node: Node) -> None:
    """Apply :func:`to_double` to the node's start-up overrides (YAML, ``-p``) before they
    are declared; rclpy would otherwise reject ``max_dt: 1`` as the wrong type."""
    overrides = getattr(node, "_parameter_overrides", None)
    if isinstance(overrides, dict):
        for name, param in list(overrides.items()):
            overrides[name] = to_double(param)


def declare_all(node: Node) -> dict[str, Any]:
    """Declare every parameter of :data:`PARAMS`; return the effective values."""
    coerce_overrides(node)
    declared = node.declare_parameters(
        "", [(p.name, default_value(p), descriptor(p)) for p in PARAMS])
    return {param.name: param.value for param in declared}


def declare_calibration(node: Node) -> dict[str, Any]:
    """Declare the calibration services' parameters (:data:`calibration.CALIBRATION_PARAMS`,
    node only); return their validated values (ValueError, one line, if one is invalid)."""
    declared = node.declare_parameters("", [(p.name, default_value(p), descriptor(p))
                                            for p in calibration.CALIBRATION_PARAMS])
    return {param.name: calibration.BY_NAME[param.name].validate(param.value)
            for param in declared}


def unknown_overrides(node: Node) -> dict[str, str]:
    """Start-up overrides that match no declared parameter → a hint for each (a typo, or a
    parameter of another filter), so that they are not silently ignored."""
    overrides = getattr(node, "_parameter_overrides", None) or {}
    out = {}
    for name in overrides:
        if node.has_parameter(name):
            continue
        out[name] = unknown_hint(name)
    return out


#: Node names of other IMU filters' nodes: imu_filter_madgwick's default and the name its
#: launch files give it, imu_complementary_filter's launch name and default; with any name
#: that mentions madgwick or a complementary filter (:func:`looks_like_imu_filter`).
IMU_FILTER_NODE_NAMES = ("imu_filter_madgwick", "imu_filter", "complementary_filter_gain_node",
                         "ComplementaryFilterROS")


def looks_like_imu_filter(name: str) -> bool:
    """Whether a node name is another IMU filter's (:data:`IMU_FILTER_NODE_NAMES`)."""
    low = name.lower()
    return (name in IMU_FILTER_NODE_NAMES or "madgwick" in low
            or "complementary_filter" in low or low.startswith("imu_filter"))


def node_key_matches(key: str, fqn: str) -> bool:
    """Whether a parameter file's node key (``estimator``, ``/ns/estimator``, ``/**``,
    ``/**/estimator``, ``/ns/*``) addresses the node ``fqn`` (``/ns/name``), as rcl matches
    it: a key without a leading ``/`` is absolute all the same, ``*`` is one name, ``**`` any
    number of names."""
    pattern = ""
    for tok in key.strip("/").split("/"):
        pattern += "(/[^/]+)*" if tok == "**" else "/" + re.escape(tok).replace(r"\*", "[^/]+")
    return re.fullmatch(pattern, fqn) is not None


def _node_keys(tree: Any, path: str = "") -> Iterator[str]:
    """The node keys of a parameter file (nested namespaces joined: ``/ns: {node: ...}`` is
    ``/ns/node``)."""
    if not isinstance(tree, dict):
        return
    for key, value in tree.items():
        if key == "ros__parameters":
            yield path
        elif isinstance(value, dict):
            yield from _node_keys(value, f"{path}/{str(key).strip('/')}" if path else str(key))


def ros_parameter_sources(argv: Sequence[str]) -> tuple[list[str], list[tuple[str, str]]]:
    """The parameter files (``--params-file F``) and node-addressed rules (``-p node:name:=v``,
    as ``(node, "name:=v")``) among the ROS arguments of a command line."""
    files: list[str] = []
    rules: list[tuple[str, str]] = []
    in_ros, take = False, ""
    for arg in argv:
        if take:
            if take == "file":
                files.append(arg)
            else:
                name, sep, value = arg.partition(":=")
                if sep and ":" in name:
                    node, pname = name.split(":", 1)
                    rules.append((node, f"{pname}:={value}"))
            take = ""
        elif arg == "--ros-args":
            in_ros = True
        elif arg == "--":
            in_ros = False
        elif in_ros and arg == "--params-file":
            take = "file"
        elif in_ros and arg in ("-p", "--param"):
            take = "param"
    return files, rules


def _run_as(key: str, namespace: str) -> str:
    """How to run this node (in ``namespace``) as the node that ``key`` addresses."""
    ns, _, name = ("/" + key.strip("/")).rpartition("/")
    remaps = f"-r __node:={name}"
    if ns and ns != namespace.rstrip("/") and "*" not in ns:
        remaps += f" -r __ns:={ns}"
    return f"run this node under that name (--ros-args {remaps}; in a launch file: name='{name}')"


def foreign_filter_rules(argv: Sequence[str], node_name: str, namespace: str) -> list[str]:
    """One warning per parameter file section or ``-p node:...`` rule of ``argv`` (the ROS
    arguments the node was started with) that is addressed to another IMU filter's node name
    (:func:`looks_like_imu_filter`) and not to this node (``/namespace/node_name``): such
    parameters are silently ignored by ROS. Each warning names them and says how to apply
    them. A file that cannot be read is left to rcl (which refuses to start)."""
    fqn = namespace.rstrip("/") + "/" + node_name
    files, rules = ros_parameter_sources(argv)
    out = []
    for path in files:
        try:
            tree = yaml.safe_load(Path(path).read_text())
        except (OSError, yaml.YAMLError):
            continue
        for key in _node_keys(tree):
            last = key.strip("/").rpartition("/")[2]
            if "*" in last or not looks_like_imu_filter(last) or node_key_matches(key, fqn):
                continue
            out.append(f"{path}: the parameters for node {key!r} (another IMU filter's node "
                       f"name) are not for this node ({fqn}) and are ignored; to apply them, "
                       f"{_run_as(key, namespace)} or rename the key {key!r} to "
                       f"{node_name!r} (or '/**')")
    for node, rule in rules:
        if looks_like_imu_filter(node) and not node_key_matches(node, fqn):
            out.append(f"-p {node}:{rule} is addressed to node {node!r} (another IMU filter's "
                       f"node name), not to this node ({fqn}), and is ignored; to apply it, "
                       f"write -p {rule} or {_run_as(node, namespace)}")
    return out
