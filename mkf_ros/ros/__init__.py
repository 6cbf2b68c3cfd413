"""rclpy front ends: the ``estimator`` node and its helpers (message conversion, parameter
descriptors, diagnostics). Thin wrappers: every rule about time and input lives in
:mod:`mkf_ros.stream`, every equation in :mod:`mkf_ros.core`."""
