"""``estimator_lifecycle``: the estimator as a managed (lifecycle) node, opt-in.

The same node as :mod:`mkf_ros.ros.estimator_node` (topics, parameters, services), driven by the
standard lifecycle services ``~/change_state``, ``~/get_state``, ``~/get_available_states``,
``~/get_available_transitions`` (lifecycle_msgs):

* **unconfigured** (at start and after cleanup): only the parameters exist; they can be set and
  are validated as usual, and take effect at configure;
* **configure**: the filter is built from the current parameter values; publishers,
  subscriptions, services and the diagnostics timer are created;
* **activate**: input is taken and ``imu/data`` (a lifecycle publisher) and ``/diagnostics``
  are published;
* **deactivate**: input is dropped and nothing is published; the filter keeps its state (a
  reactivation after a gap longer than ``max_dt`` re-aligns the tilt, as after any gap);
* **cleanup** / **shutdown**: everything but the parameters is destroyed.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from typing import Any

from rclpy.impl.implementation_singleton import rclpy_implementation as _rclpy
from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn
from rclpy.publisher import Publisher
from rclpy.qos_overriding_options import QoSOverridingOptions
from sensor_msgs.msg import Imu

from mkf_ros.ros.estimator_main import USAGE, main
from mkf_ros.ros.estimator_node import EstimatorNode
from mkf_ros.ros.qos import output_qos


class EstimatorLifecycleNode(EstimatorNode, LifecycleNode):
    """The estimator as a managed node (see the module docstring)."""

    MANAGED = True

    def __init__(self, node_name: str = "estimator", *, warm: bool = True,
                 **node_kwargs: Any) -> None:
        super().__init__(node_name, warm=warm, **node_kwargs)
        self._guard_change_state()
        self.get_logger().info("managed node: unconfigured (configure, then activate, through "
                               "~/change_state)")

    def _guard_change_state(self) -> None:
        """A transition that does not exist in the current state (``activate`` while
        unconfigured) makes rclpy's ``~/change_state`` raise inside the executor, which stops
        the node; answer ``success = false`` instead and log why."""
        for srv in self.services:
            if not srv.srv_name.endswith("/change_state"):
                continue
            inner = srv.callback

            def guarded(request: Any, response: Any, inner: Any = inner) -> Any:
                try:
                    return inner(request, response)
                except _rclpy.RCLError as e:
                    state = self._state_machine.current_state[1]
                    self.get_logger().warning(
                        f"transition {request.transition.id} {request.transition.label!r} "
                        f"refused in state {state!r}: {' '.join(str(e).split())}")
                    response.success = False
                    return response
            srv.callback = guarded

    def _make_output_publisher(self) -> Publisher:
        return self.create_lifecycle_publisher(
            Imu, "imu/data", output_qos(),
            qos_overriding_options=QoSOverridingOptions.with_default_policies())

    def _destroy_output_publisher(self, pub: Publisher) -> None:
        self.destroy_lifecycle_publisher(pub)  # type: ignore[arg-type]

    # --- transitions ---------------------------------------------------------------------------
    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        try:
            self._configure()
        except Exception as e:
            self.get_logger().error(f"configure failed: {type(e).__name__}: {e}")
            self._teardown()
            return TransitionCallbackReturn.FAILURE
        return super().on_configure(state)

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        ret = super().on_activate(state)  # enables the lifecycle publisher
        with self._lock:
            self._active = True
        self.get_logger().info("active: taking input and publishing")
        return ret

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        with self._lock:
            self._active = False
        self.get_logger().info("inactive: input dropped, nothing published")
        return super().on_deactivate(state)

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        with self._lock:
            self._active = False
        self._teardown()
        return super().on_cleanup(state)

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        with self._lock:
            self._active = False
        self._teardown()
        return super().on_shutdown(state)

    def on_error(self, state: LifecycleState) -> TransitionCallbackReturn:
        with self._lock:
            self._active = False
        self._teardown()
        return TransitionCallbackReturn.SUCCESS


LIFECYCLE_USAGE = USAGE.replace("usage: estimator ", "usage: estimator_lifecycle ", 1).replace(
    "a drop-in replacement for imu_filter_madgwick.",
    "as a managed (lifecycle) node:\n  starts unconfigured; ~/change_state configure, activate, "
    "deactivate, cleanup,\n  shutdown (lifecycle_msgs/ChangeState), ~/get_state.", 1)


def lifecycle_main(argv: Sequence[str] | None = None) -> int:
    """Console script ``estimator_lifecycle``."""
    return main(argv, node_class=EstimatorLifecycleNode, prog="estimator_lifecycle",
                usage=LIFECYCLE_USAGE)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(lifecycle_main())
