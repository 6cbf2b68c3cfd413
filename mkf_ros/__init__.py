"""mkf_ros: Manifold Kalman Filters (MEKF/MUKF) for attitude estimation, with ROS 2 nodes.

Offline use needs only NumPy and numba::

    import mkf_ros
    res = mkf_ros.estimate(gyr, acc, mag, dt=0.01, algorithm="mekf", chart="rp")
    res.quat  # (N, 4) [w, x, y, z], sensor → world (ENU by default)
"""

from mkf_ros._version import __version__
from mkf_ros.api import EstimateResult, estimate
from mkf_ros.core.filter import AttitudeFilter
from mkf_ros.core.params import PARAMS, FilterParams
from mkf_ros.kernels import warmup

__all__ = [
    "PARAMS", "AttitudeFilter", "EstimateResult", "FilterParams", "__version__", "estimate",
    "warmup",
]
