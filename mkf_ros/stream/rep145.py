"""REP-145 rules for the vector fields of ``sensor_msgs/Imu``, in one place (no ROS imports).

Input: a field whose covariance[0] is -1 is "not reported" and reaches the filter as missing
(None for one message, a NaN row in a stack). Output (``imu/data``): a field without a value
is published as zeros with covariance[0] = -1 (:data:`NOT_REPORTED`); a field with a value
carries the filter's own covariance when it has one, and otherwise the input's covariance,
filled by :func:`covariance_out` (all zeros "unknown" → ``stddev²`` on the
diagonal, plus the filter's ``add``).

The node's message path (:mod:`mkf_ros.ros.convert`), its CDR fast path
(:mod:`mkf_ros.ros.rawmsg`) and ``mkf process`` (:mod:`mkf_ros.bags.process`, stacks of
messages) all use these functions, so they publish the same covariances.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

#: covariance of a field that is not reported: element 0 = -1, the rest zero
NOT_REPORTED = np.array([-1.0, 0, 0, 0, 0, 0, 0, 0, 0])
NOT_REPORTED.setflags(write=False)

Fill = Callable[[Any, float, Any], np.ndarray]


def not_reported(cov0: Any) -> Any:
    """True where covariance[0] is the "not reported" marker -1 (one value or an array)."""
    return cov0 == -1.0


def input_vector(value: Any, cov0: float, copy: bool = True) -> Any:
    """One input field as 3 floats (a copy: a read-only view of a message would make numba
    compile a read-only variant; ``copy=False`` for a caller that copies it itself), None when
    it is not reported."""
    if not_reported(cov0):
        return None
    return np.array(value, dtype=float) if copy else value


def input_rows(values: Any, cov0: np.ndarray) -> np.ndarray:
    """A stack of input fields as (N, 3) floats, NaN rows where not reported (the adapter
    treats them like missing readings)."""
    v = np.array(values, dtype=float)
    v[not_reported(cov0)] = math.nan
    return v


def covariance_out(input_cov: Any, stddev: float, add: Any = None) -> np.ndarray:
    """Published 3×3 covariances (9 values, row major) from the input's (REP-145): one
    (9 values) or a stack (M, 9), with ``add`` as one (3×3) or a stack (M, 3, 3).

    An unknown input covariance (all zeros) is filled with ``stddev²`` on the diagonal when
    ``stddev > 0`` and otherwise stays unknown; ``add`` is added to a known one. A
    covariance with NaN/Inf or the "not reported" marker (-1 first) counts as unknown.
    """
    from mkf_ros.stream import kernel as sk  # compiled kernels: loaded on first use

    c = np.array(input_cov, dtype=float)
    rows = c.reshape(-1, 9)  # a view: ``c`` is filled through it
    sk.covariance_rows(rows, float(stddev), _NO_ADD if add is None else
                       np.ascontiguousarray(add, dtype=float).reshape(-1, 9))
    return c.reshape(-1) if c.ndim < 2 or c.shape == (3, 3) else rows


_NO_ADD = np.zeros((0, 9))


def published_covariance(value: np.ndarray | None, filter_cov: np.ndarray | None,
                         input_cov: Any, stddev: float, add: Any = None,
                         fill: Fill | None = None) -> np.ndarray:
    """The 9 published covariance values of one output field: :data:`NOT_REPORTED` without
    a value; the filter's own ``filter_cov`` (3×3) when given; else the input's filled
    (``fill``, default :func:`covariance_out`, called as
    ``fill(input_cov, stddev, add)``)."""
    if value is None:
        return NOT_REPORTED.copy()
    if filter_cov is not None:
        return np.ascontiguousarray(filter_cov, dtype=float).reshape(9)
    return (fill or covariance_out)(input_cov, stddev, add)


def published_covariances(value_ok: np.ndarray, filter_cov: np.ndarray | None,
                          input_cov: np.ndarray, stddev: float,
                          add: np.ndarray | None = None) -> np.ndarray:
    """:func:`published_covariance` over a stack of M messages: ``value_ok`` (M,) bool,
    ``filter_cov`` (M, 3, 3) with NaN where the filter has none (or None), ``input_cov``
    (M, 9), ``add`` (M, 3, 3) with NaN where there is none (or None). Returns (M, 9)."""
    m = len(value_ok)
    out = np.tile(NOT_REPORTED, (m, 1))
    own = np.zeros(m, dtype=bool)
    if filter_cov is not None:
        own = value_ok & ~np.isnan(filter_cov[:, 0, 0])
        out[own] = filter_cov[own].reshape(-1, 9)
    filled = value_ok & ~own
    a = None if add is None else add[filled]
    if a is not None:  # rows without an ``add`` (NaN) add nothing, as for one message
        a = None if np.isnan(a).all() else np.where(np.isnan(a), 0.0, a)
    out[filled] = covariance_out(input_cov[filled], stddev, a)
    return out
