"""The offline API: :func:`estimate` runs a filter over whole arrays."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from mkf_ros.core import smoother as sm
from mkf_ros.core.filter import AttitudeFilter
from mkf_ros.core.params import FilterParams


@dataclass
class EstimateResult:
    """Output of :func:`estimate`, one row per input sample."""

    quat: np.ndarray  #: (N, 4) [w, x, y, z], sensor → world, w ≥ 0
    cov: np.ndarray  #: (N, 3, 3) orientation covariance about world axes, rad²
    omega: np.ndarray  #: (N, 3) estimated angular velocity, body frame, rad/s
    bias: np.ndarray  #: (N, 3) estimated gyro bias, rad/s (zeros unless estimated)
    bias_std: np.ndarray  #: (N, 3) its standard deviation, rad/s
    initialized: np.ndarray  #: (N,) bool: False before the first usable accelerometer sample
    counters: dict[str, int] = field(default_factory=dict)  #: skipped/invalid samples etc.
    params: FilterParams = field(default_factory=FilterParams)
    #: ``smooth=True``: the causal filter's ``quat`` and ``cov`` (the fields above are then the
    #: smoother's, docs/math.md §11); None otherwise
    filtered_quat: np.ndarray | None = None
    filtered_cov: np.ndarray | None = None
    smoothed: bool = False  #: whether ``quat``, ``cov``, ``omega``, ``bias`` are smoothed


def _as_samples(name: str, a: object, n: int | None) -> np.ndarray:
    try:
        arr = np.asarray(a, dtype=float)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a numeric array of shape (N, 3)") from None
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {arr.shape}")
    if n is not None and arr.shape[0] != n:
        raise ValueError(f"{name} has {arr.shape[0]} samples, expected {n} (as gyr/acc)")
    inf = np.isinf(arr)
    if inf.any():
        i = int(np.argwhere(inf)[0, 0])
        raise ValueError(f"{name}[{i}] contains an infinite value: {arr[i].tolist()} "
                         "(use NaN to mark a missing sample)")
    return np.ascontiguousarray(arr)


def _time_steps(n: int, dt: object, timestamps: object) -> np.ndarray:
    if (dt is None) == (timestamps is None):
        raise ValueError("give exactly one of dt (seconds per sample) or timestamps (N,)")
    dts = np.zeros(n)
    if dt is not None:
        try:
            d = float(dt)  # type: ignore[arg-type]
        except (TypeError, ValueError):
            raise ValueError(f"dt must be a positive number of seconds, got {dt!r}") from None
        if not (np.isfinite(d) and d > 0):
            raise ValueError(f"dt must be a positive finite number of seconds, got {dt!r}")
        dts[1:] = d
        return dts
    t = np.asarray(timestamps, dtype=float)
    if t.shape != (n,):
        raise ValueError(f"timestamps must have shape ({n},), got {t.shape}")
    bad = ~np.isfinite(t)
    if bad.any():
        i = int(np.argmax(bad))
        raise ValueError(f"timestamps[{i}] is not finite: {t[i]}")
    steps = np.diff(t)
    if (steps <= 0).any():
        i = int(np.argmax(steps <= 0)) + 1
        raise ValueError(f"timestamps must increase: timestamps[{i}] = {t[i]:g} is not after "
                         f"timestamps[{i - 1}] = {t[i - 1]:g}")
    dts[1:] = steps
    return dts


def estimate(
    gyr: object,
    acc: object,
    mag: object = None,
    *,
    dt: float | None = None,
    timestamps: object = None,
    smooth: bool | str = False,
    smooth_window: int | None = None,
    smooth_overlap: int | None = None,
    **params: object,
) -> EstimateResult:
    """Estimate the orientation of a rigid body from IMU samples (offline; causal, or smoothed
    with ``smooth=True``).

    Args:
        gyr: (N, 3) angular velocity in rad/s, body frame, or None (no gyroscope).
        acc: (N, 3) specific force in m/s² (+g up at rest).
        mag: (N, 3) magnetic field, any unit, or None. Giving it implies ``use_mag=True``
            unless ``use_mag`` is passed.
        dt: sample period in seconds, or
        timestamps: (N,) strictly increasing sample times in seconds.
        smooth: use the future too: the fixed-interval manifold smoother (docs/math.md §11;
            MEKF or MUKF). ``quat``, ``cov``, ``omega``, ``bias`` and ``bias_std`` are then the
            smoothed ones, ``filtered_quat`` and ``filtered_cov`` the causal filter's.
            ``True`` or ``"rts"``: the Rauch–Tung–Striebel smoother; ``"two-way"``: its tilt
            fused with that of the same smoother run over the reversed recording
            (docs/math.md §11.5: the causal low-pass's lag has the opposite sign there; about
            twice the time; ``quat`` and ``cov`` fused, ``omega`` and ``bias`` the forward
            smoother's). The smoothers' loops are compiled on their first use on a machine
            (about 10 s, once; not at install time), then cached.
        smooth_window, smooth_overlap: the smoother's window and overlap in samples (memory
            ~0.53 kB per sample of their sum; default
            :data:`~mkf_ros.core.smoother.DEFAULT_WINDOW` samples and
            :data:`~mkf_ros.core.smoother.DEFAULT_OVERLAP_S` seconds at the recording's mean
            rate, :func:`~mkf_ros.core.smoother.window_sizes`).
        **params: filter parameters (see :data:`mkf_ros.core.params.PARAMS`), e.g.
            ``algorithm="mukf", chart="rv", chart_update=False, world_frame="ned"``.

    A row that is all NaN means "no reading at this sample" (e.g. a slower magnetometer); a
    partly-NaN or zero row is invalid. Either skips only that sensor's update and is counted in
    ``counters``. Infinite values, wrong shapes and non-increasing timestamps raise ValueError
    naming the argument and the sample index.
    """
    if gyr is None and acc is None:
        raise ValueError("give at least one of gyr or acc")
    ref = gyr if gyr is not None else acc
    ref_shape = np.asarray(ref).shape  # what np.shape / np.ndim do with a non-array
    n = int(ref_shape[0]) if len(ref_shape) >= 1 else -1
    g = _as_samples("gyr", gyr, None) if gyr is not None else None
    n = g.shape[0] if g is not None else n
    a = _as_samples("acc", acc, n) if acc is not None else np.full((n, 3), np.nan)
    n = a.shape[0]
    if g is None:
        g = np.full((n, 3), np.nan)
    if mag is not None:
        params.setdefault("use_mag", True)
        m = _as_samples("mag", mag, n)
    else:
        if params.get("use_mag"):
            raise ValueError("use_mag=True needs mag, an (N, 3) array")
        m = np.full((n, 3), np.nan)
    mode = sm.smooth_mode(smooth)
    if mode:
        params = sm.forward_params(params)
    p = FilterParams(params)
    dts = _time_steps(n, dt, timestamps)
    f = AttitudeFilter(p)
    if mode:
        run = sm.smooth_both_ways if mode == "two-way" else sm.smooth_run
        filt, s = run(f, dts, g, a, m, smooth_window, smooth_overlap)
        return EstimateResult(
            quat=s.quat, cov=s.cov, omega=s.omega, bias=s.bias,
            bias_std=np.sqrt(s.bias_var), initialized=filt.initialized,
            counters=f.counter_dict(), params=p, filtered_quat=filt.quat,
            filtered_cov=filt.cov, smoothed=True)
    out = f.run(dts, g, a, m)
    return EstimateResult(
        quat=out.quat, cov=out.cov, omega=out.omega, bias=out.bias, bias_std=np.sqrt(out.bias_var),
        initialized=out.initialized, counters=f.counter_dict(),
        params=p,
    )
