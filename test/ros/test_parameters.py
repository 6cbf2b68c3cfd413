"""Runtime reconfiguration through SetParameters, from another node, for EVERY parameter.

The parameter lists are generated from :data:`mkf_ros.core.params.PARAMS`, so a parameter
added there is covered here without touching this file.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from rclpy.node import Node
from rclpy.parameter import Parameter
from rosharness import Harness, quat, record_arrival, recording_messages, reference_outputs
from sensor_msgs.msg import Imu

from mkf_ros.core.params import BY_NAME, PARAMS, Param
from mkf_ros.core.quaternion import angle_between
from mkf_ros.ros.estimator_node import EstimatorNode, ParameterError
from mkf_ros.sim import simulate
from mkf_ros.stream.adapter import StreamAdapter

pytestmark = pytest.mark.ros
T0 = 100.0


def alt_value(p: Param) -> Any:
    """A valid value different from the default."""
    if p.type is bool:
        return not p.default
    if p.type is str:
        return next(c for c in p.choices if c != p.default) if p.choices else "test_frame"
    if p.type is list:
        return [float(x) * 1.1 + 0.01 * (i % 2) for i, x in enumerate(p.default)]
    lo, hi = p.range if p.range else (-math.inf, math.inf)
    for v in (p.default * 2, p.default / 2, (lo + hi) / 2, hi, lo):
        if v != p.default and lo <= v <= hi and math.isfinite(v):
            return p.type(v)
    raise AssertionError(f"no alternative value for {p.name}")


def invalid_values(p: Param) -> list[Any]:
    """Values that must be rejected (wrong type, out of range, not a choice, wrong length)."""
    bad: list[Any] = []
    if p.type in (float, int):
        bad.append("fast")
        if p.range:
            bad += [p.type(p.range[1] * 2 + 1), p.type(p.range[0] - 1 - abs(p.range[0]))]
    elif p.type is bool:
        bad.append(3.5)
    elif p.type is str:
        bad.append(1.0)
        if p.choices:
            bad.append("no_such_" + p.name)
    elif p.type is list:
        bad += ["x", [1.0, 2.0]]
        if p.range:
            bad.append([p.range[1] * 2 + 1] * (p.length or 3))
    return bad


@pytest.fixture
def running(harness) -> Harness:
    """A node that has been initialised by a few samples and keeps publishing."""
    h = harness()
    h.send_imu([T0 + 0.01 * k for k in range(5)])
    assert len(h.out) == 5
    return h


def publishes(h: Harness, t: float) -> bool:
    n = len(h.out)
    h.send_imu([t, t + 0.01], gyr=(0.0, 0.0, 0.1))
    return len(h.out) == n + 2


def test_descriptors_generated_from_the_definition(running) -> None:
    h = running
    fut = h.params.describe_parameters([p.name for p in PARAMS])
    descs = h.wait(fut).descriptors
    for p, d in zip(PARAMS, descs, strict=True):
        assert d.name == p.name
        assert d.description == p.doc(), p.name
        if p.unit:
            assert f"[{p.unit}]" in d.description
        if p.type is float and p.range:
            r = d.floating_point_range[0]
            assert (r.from_value, r.to_value) == p.range, p.name
        if p.choices:
            assert all(c in d.additional_constraints for c in p.choices), p.name
        assert d.read_only == p.read_only
    names = set(h.wait(h.params.list_parameters()).result.names)
    assert {p.name for p in PARAMS} <= names


def test_every_parameter_changes_at_runtime(running) -> None:
    """Each parameter set to another valid value (and back) from another node: accepted,
    readable, applied to the adapter (and the filter), and the node keeps publishing. A
    read-only parameter (``input_mode``: it decides the subscriptions) is refused and keeps
    its value."""
    h, t, failures = running, T0 + 1.0, []
    for p in PARAMS:
        if p.read_only:
            res = h.set(**{p.name: alt_value(p)})[0]
            if res.successful or h.get(p.name)[0] != p.default:
                failures.append(f"read-only {p.name} changed at runtime")
            continue
        for value in (alt_value(p), p.default):
            res = h.set(**{p.name: value})[0]
            got = h.get(p.name)[0]
            applied = h.est.stream.params[p.name]
            if not res.successful:
                failures.append(f"{p.name}={value!r} rejected: {res.reason}")
            elif (got, applied) != (value, value):
                failures.append(f"{p.name}={value!r}: reads {got!r}, applied {applied!r}")
            elif p.scope == "filter" and h.est.stream.filter.params[p.name] != value:
                failures.append(f"{p.name}={value!r} not in the filter")
            elif not publishes(h, t):
                failures.append(f"{p.name}={value!r}: node stopped publishing")
            t += 0.02
    assert not failures, "\n".join(failures)
    assert h.est._exceptions == 0


def test_invalid_values_rejected_with_reason(running) -> None:
    h, failures = running, []
    before = dict(h.est.stream.params)
    for p in PARAMS:
        for value in invalid_values(p):
            res = h.set(**{p.name: value})[0]
            if res.successful:
                failures.append(f"{p.name}={value!r} accepted")
            elif not res.reason.strip():
                failures.append(f"{p.name}={value!r} rejected without a reason")
            if h.get(p.name)[0] != before[p.name]:
                failures.append(f"{p.name}={value!r} changed the parameter")
    assert not failures, "\n".join(failures)
    assert h.est.stream.params == before
    # the reasons are specific
    r = h.set(algorithm="ekf")[0]
    choices = ", ".join(BY_NAME["algorithm"].choices)
    assert f"algorithm must be one of {choices}, got 'ekf'" in r.reason
    r = h.set(max_dt=-1.0)[0]
    assert "max_dt" in r.reason and "range" in r.reason
    r = h.set(mag_reference=[1.0, 2.0])[0]
    assert "mag_reference must have 3 elements" in r.reason


def test_unknown_name_rejected_naming_it(running) -> None:
    """The refusal names the parameter: rclpy's own answer was "Invalid access to undeclared
    parameter(s): []"."""
    h = running
    before = dict(h.est.stream.params)
    r = h.set(gain=0.1)[0]
    assert not r.successful
    assert r.reason.startswith("unknown parameter 'gain': imu_filter_madgwick's gain has no "
                               "equivalent")
    assert "madgwick_beta" in r.reason
    r = h.set(zeta=0.1)[0]
    assert not r.successful and "unknown parameter 'zeta'" in r.reason
    assert "estimate_gyro_bias" in r.reason
    r = h.set(gyro_nosie=0.1)[0]
    assert not r.successful
    assert r.reason == ("unknown parameter 'gyro_nosie': not a parameter of this node (did you "
                        "mean 'gyro_noise' or 'gyro_bias_noise' or 'mag_noise'?)")
    assert h.est.stream.params == before
    assert publishes(h, T0 + 1.0)


def test_integers_accepted_for_floats(running) -> None:
    h = running
    assert h.set(max_dt=1)[0].successful
    assert h.get("max_dt") == [1.0] and isinstance(h.get("max_dt")[0], float)
    assert h.set(mag_reference=[0, 1, -2])[0].successful
    assert h.est.stream.params["mag_reference"] == [0.0, 1.0, -2.0]


def test_cross_parameter_rule_rejects_all_atomically(running) -> None:
    h = running
    res = h.set_atomically(init_mode="paper", use_mag=True)
    assert not res.successful and "init_mode 'paper' with use_mag needs mag_reference" in res.reason
    assert h.get("init_mode", "use_mag") == ["align", False]
    res = h.set_atomically(algorithm="mukf", chart="mrp", gyro_noise=0.02, constant_dt=0.01)
    assert res.successful
    p = h.est.stream.params
    assert (p["algorithm"], p["chart"], p["gyro_noise"], p["constant_dt"]) == (
        "mukf", "mrp", 0.02, 0.01)


def test_other_nodes_parameters_do_not_affect_it(running, ros_context) -> None:
    """imu_filter_madgwick reacted to any node's parameter events (imu_tools PR #220).

    Event-driven: another node changes its own ``algorithm`` and ``gyro_noise``; once a probe
    has received those changes on /parameter_events (so every subscriber of that topic in
    this executor has had them), and the estimator has answered a service call after that,
    its parameters must still be its own."""
    from rcl_interfaces.msg import ParameterEvent

    h = running
    assert "/parameter_events" not in {s.topic_name for s in h.est.subscriptions}
    seen: set[str] = set()

    def on_event(ev: ParameterEvent) -> None:
        if ev.node == "/other":
            seen.update(p.name for p in ev.changed_parameters)

    h.cli.create_subscription(ParameterEvent, "/parameter_events", on_event, 100)
    other = Node("other", context=ros_context)
    h.ex.add_node(other)
    other.declare_parameter("algorithm", "mekf")
    other.declare_parameter("gyro_noise", 0.01)
    # parameter events are published without waiting for subscribers: repeat until seen
    for value in range(20):
        other.set_parameters([Parameter("algorithm", value="mukf"),
                              Parameter("gyro_noise", value=0.5 + value)])
        if h.spin_until(lambda: {"algorithm", "gyro_noise"} <= seen, 1.0):
            break
    assert {"algorithm", "gyro_noise"} <= seen, "the other node's events never arrived"
    assert h.get("algorithm", "gyro_noise") == ["mekf", 0.01]  # a round trip to the node
    assert h.est.stream.params["algorithm"] == "mekf"
    assert h.est.stream.params["gyro_noise"] == 0.01
    h.ex.remove_node(other)
    other.destroy_node()


@pytest.mark.parametrize("switch", [
    {"algorithm": "mukf"},
    {"chart": "rv"},
    {"chart": "o", "chart_update": False},
    {"algorithm": "mukf", "chart": "mrp"},
], ids=lambda d: "+".join(f"{k}={v}" for k, v in d.items()))
def test_switch_continuity(harness, switch: dict[str, Any]) -> None:
    """Switching algorithm/chart/chart_update mid-stream keeps the estimate.

    Bound: across the switch the published orientation may only differ from an unswitched
    reference by what one step of the other filter does differently: < 0.05° (the motion
    turns by up to 0.35° per 10 ms step). The covariance carries over: its trace changes by
    less than 20 % in that step.
    """
    rec = simulate("slow_rotation", duration=3.0, rate=100.0, seed=5, mag_rate=50.0)
    base = {"use_mag": True, "algorithm": "mekf", "chart": "rp", "chart_update": True}
    h = harness(base)
    kinds = record_arrival(h.est.stream)
    k_switch = 150
    msgs = recording_messages(rec, T0)
    cut = [i for i, m in enumerate(msgs) if isinstance(m, Imu)][k_switch]
    h.send(msgs[:cut])
    assert len(h.out) == k_switch
    assert all(r.successful for r in h.set(**switch))
    h.send(msgs[cut:])
    q = np.array([quat(m) for m in h.out])
    cov = np.array([np.reshape(m.orientation_covariance, (3, 3)) for m in h.out])
    # the reference: the messages sent, in the node's arrival order, without the switch
    ref_out = reference_outputs(StreamAdapter(base), msgs, kinds)
    q_ref_before = ref_out[k_switch - 1].quat
    c_ref_before = ref_out[k_switch - 1].cov
    q_ref_after = ref_out[k_switch].quat

    def angle(a: np.ndarray, b: np.ndarray) -> float:
        return math.degrees(angle_between(np.asarray(a, float), np.asarray(b, float)))

    assert angle(q[k_switch - 1], q_ref_before) < 1e-9  # the same filter until the switch
    assert angle(q[k_switch], q_ref_after) < 0.05
    tr0, tr1 = np.trace(cov[k_switch - 1]), np.trace(cov[k_switch])
    assert abs(tr1 / tr0 - 1) < 0.2
    assert abs(np.trace(c_ref_before) / tr0 - 1) < 0.05
    # and it keeps tracking afterwards (no re-convergence, no jump later on)
    steps = [angle(q[k], q[k + 1]) for k in range(k_switch - 5, len(q) - 1)]
    assert max(steps) < 0.5


def test_start_up_parameters(ros_context, tmp_path, capfd) -> None:
    """A params file with imu_filter_madgwick leftovers, an int for a float; bad values fail
    the start with one line."""
    f = tmp_path / "p.yaml"
    f.write_text("/**:\n  ros__parameters:\n    max_dt: 2\n    gain: 0.1\n    zeta: 0.0\n"
                 "    algorithm: mukf\n    fixed_frame: Map_IMU\n")
    node = EstimatorNode(context=ros_context, warm=False,
                         cli_args=["--ros-args", "--params-file", str(f)])
    p = node.stream.params
    assert (p["max_dt"], p["algorithm"], p["fixed_frame"]) == (2.0, "mukf", "Map_IMU")
    node.destroy_node()
    err = capfd.readouterr().err
    assert "ignoring unknown parameter 'gain'" in err and "acc_noise" in err
    assert "ignoring unknown parameter 'zeta'" in err and "estimate_gyro_bias" in err
    for bad, why in ((Parameter("algorithm", value="ekf"), "algorithm must be one of"),
                     (Parameter("max_dt", value=-3.0), "max_dt"),
                     (Parameter("max_dt", value="long"), "max_dt")):
        with pytest.raises(ParameterError, match=why) as e:
            EstimatorNode(context=ros_context, warm=False, parameter_overrides=[bad])
        assert "\n" not in str(e.value)


MADGWICK_FILE = """imu_filter:
  ros__parameters:
    use_mag: true
    world_frame: ned
    gain: 0.1
"""


@pytest.mark.parametrize("key", ["imu_filter", "imu_filter_madgwick", "/robot/imu_filter",
                                 "complementary_filter_gain_node"])
def test_a_file_for_another_filters_node_name_is_named_with_the_fix(
        ros_context, tmp_path, capfd, key) -> None:
    """A parameter file keyed by imu_filter_madgwick's (or the complementary filter's) node
    name, given to this node, would be ignored without a word: the warning names the file and
    the key, and each fix it names applies the file (the node's parameters take its values)."""
    f = tmp_path / "imu_filter.yaml"
    f.write_text(MADGWICK_FILE.replace("imu_filter:", f"{key}:", 1))
    args = ["--ros-args", "--params-file", str(f)]
    node = EstimatorNode(context=ros_context, warm=False, cli_args=args)
    assert (node.stream.params["use_mag"], node.stream.params["world_frame"]) == (False, "enu")
    node.destroy_node()
    err = capfd.readouterr().err
    (line,) = [ln for ln in err.splitlines() if str(f) in ln]
    assert f"the parameters for node {key!r}" in line and "are ignored" in line
    name = key.rpartition("/")[2]
    remaps = f"-r __node:={name}" + (" -r __ns:=/robot" if key.startswith("/robot") else "")
    assert f"(--ros-args {remaps};" in line and f"rename the key {key!r} to 'estimator'" in line
    # the first fix: run under that name
    node = EstimatorNode(context=ros_context, warm=False,
                         cli_args=["--ros-args", *remaps.split(), "--params-file", str(f)])
    assert (node.stream.params["use_mag"], node.stream.params["world_frame"]) == (True, "ned")
    node.destroy_node()
    err = capfd.readouterr().err
    assert "are ignored" not in err and "ignoring unknown parameter 'gain'" in err
    # the second: rename the key
    f.write_text(MADGWICK_FILE.replace("imu_filter:", "estimator:", 1))
    node = EstimatorNode(context=ros_context, warm=False, cli_args=args)
    assert (node.stream.params["use_mag"], node.stream.params["world_frame"]) == (True, "ned")
    node.destroy_node()


def test_a_rule_for_another_filters_node_name_is_named(ros_context, capfd) -> None:
    """``-p imu_filter:use_mag:=true`` (a node-addressed override) is named too; a file or
    rule for some other node (a driver's) is not this node's business."""
    node = EstimatorNode(context=ros_context, warm=False, argv=[
        "estimator", "--ros-args", "-p", "imu_filter:use_mag:=true",
        "-p", "camera:fps:=30", "-p", "estimator:max_dt:=2"])
    node.destroy_node()
    warnings = [ln for ln in capfd.readouterr().err.splitlines() if "WARN" in ln]
    assert len(warnings) == 1
    assert ("-p imu_filter:use_mag:=true is addressed to node 'imu_filter'" in warnings[0]
            and "write -p use_mag:=true or run this node under that name "
                "(--ros-args -r __node:=imu_filter;" in warnings[0])
