"""The chunked simulator (``SimStream``): the same recording whatever the chunk size, each
streaming piece equal to what it replaces, and memory bounded by the chunk, not the duration."""

from __future__ import annotations

import itertools
import json
import tracemalloc

import numpy as np
import pytest

from mkf_ros.core.quaternion import q_omega, qmul, qnormalize
from mkf_ros.sim import SCENARIOS, SimData, SimStream, simulate
from mkf_ros.sim.motion import (
    _FIELDS,
    Draws,
    Integrator,
    _first_at_or_after,
    _intervals_where,
    _Runs,
    concat,
    integrate,
)

#: scenario → options that give it something to cut: its intervals, gaps, jumps, gimbal lock
CASES = {name: dict(duration=20.0, rate=50.0, substeps=5, seed=3, mag_rate=15.0)
         for name in SCENARIOS}
CASES["sweep"] = dict(CASES["sweep"], duration=40.0)  # reaches both gimbal locks
CASES["slow_turn"] = dict(CASES["slow_turn"], vib_acc=0.2, rest=3.0)  # a run of draws
CASES["dropouts"] = dict(CASES["dropouts"], gap=0.5)
CASES["time_jump"] = dict(CASES["time_jump"], jump_at=0.37)


def _same(a: SimData, b: SimData) -> None:
    for k in _FIELDS:
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k), err_msg=k, strict=True)
    assert json.dumps(a.meta, default=repr) == json.dumps(b.meta, default=repr)


@pytest.mark.parametrize("name", list(SCENARIOS))
def test_every_scenario_is_the_same_in_any_chunks(name: str) -> None:
    """One chunk (the whole recording) and many chunks of 1, 7 and 64 samples: the same arrays
    bit for bit (magnetometer at its own rate, dropped samples, jumps) and the same metadata
    (intervals found across chunk boundaries, gimbal lock included)."""
    kw = CASES[name]
    n = round(kw["duration"] * kw["rate"]) + 1
    whole = simulate(name, chunk=n, **kw)
    for chunk in (1, 7, 64):
        stream = SimStream(name, chunk=chunk, **kw)
        parts = list(stream)
        assert len(parts) == -(-(n - 1) // chunk)  # the first chunk also holds sample 0
        _same(concat(parts, stream.meta), whole)
    assert simulate(name, **kw).gyr.tobytes() == whole.gyr.tobytes()  # the default chunks
    if name == "sweep":
        assert len(whole.meta["intervals"]["gimbal_lock"]) >= 2
    if name == "dropouts":
        assert len(whole) < n and len(whole.meta["intervals"]["dropout"]) == 2


@pytest.mark.parametrize(("duration", "rate", "substeps"),
                         [(0.001, 100.0, 100), (0.01, 100.0, 1), (0.02, 100.0, 3)])
def test_tiny_recordings(duration: float, rate: float, substeps: int) -> None:
    """One sample (no integration step), one step, a few steps: chunked as whole."""
    whole = simulate("wiener", duration=duration, rate=rate, substeps=substeps, chunk=10)
    _same(simulate("wiener", duration=duration, rate=rate, substeps=substeps, chunk=1), whole)
    assert len(whole) == round(duration * rate) + 1
    np.testing.assert_allclose(np.linalg.norm(whole.quat, axis=1), 1.0)


def test_a_stream_is_iterated_once() -> None:
    s = SimStream("static", duration=1.0, chunk=10)
    assert len(list(s)) == 10
    with pytest.raises(RuntimeError, match="once"):
        list(s)
    with pytest.raises(ValueError, match="chunk"):
        SimStream("static", chunk=0)


def test_draws_in_chunks_are_the_whole_draw_and_leave_the_generator_where_it_would() -> None:
    """numpy's own whole-array draw is the reference: the chunks concatenate to it, and the
    generator the run was taken from continues as after that draw."""
    for kind, shape in (("normal", (1000, 3)), ("uniform", (777,))):
        ref = np.random.default_rng(11)
        want = getattr(ref, kind)(0.5, 2.0, shape)
        after = ref.normal(size=5)
        rng = np.random.default_rng(11)
        d = Draws(rng, kind, 0.5, 2.0, shape)
        np.testing.assert_array_equal(rng.normal(size=5), after)
        got = np.concatenate([d.take(k) for k in (1, 0, 10, 500, shape[0] - 511)])
        np.testing.assert_array_equal(got, want)
        with pytest.raises(ValueError, match="left"):
            d.take(1)


def test_integrator_in_chunks_is_the_sequential_product() -> None:
    """Any cut of the steps gives the attitudes of one pass, bit for bit, and those are the
    step-by-step product of the step rotations (to rounding)."""
    rng = np.random.default_rng(0)
    w = rng.normal(size=(2000, 3)) * 4.0
    q0 = qnormalize(rng.normal(size=4))
    whole = integrate(q0, w, 1e-3)
    for every in (1, 10):
        it = Integrator(q0, len(w), 1e-3, every=every)
        cuts = [0, 1, 2, 45, 46, 700, 1999, 2000]
        got = np.concatenate([it.advance(w[a:b]) for a, b in itertools.pairwise(cuts)])
        np.testing.assert_array_equal(got, whole[every::every])
    q = q0.copy()
    for k in range(0, len(w)):
        q = qnormalize(qmul(q, q_omega(w[k], 1e-3)))
        if k % 199 == 0:
            np.testing.assert_allclose(whole[k + 1], q, atol=1e-12)
    with pytest.raises(ValueError, match="recording of 2000"):
        Integrator(q0, len(w), 1e-3).advance(np.zeros((2001, 3)))


def test_runs_across_chunks_are_the_runs_of_the_whole_mask() -> None:
    rng = np.random.default_rng(2)
    for _ in range(50):
        mask = rng.random(300) < rng.uniform(0.05, 0.95)
        t = np.arange(300) * 0.1
        out: list[tuple[float, float]] = []
        r = _Runs(out)
        cuts = np.unique(np.r_[0, rng.integers(0, 300, 8), 300])
        for a, b in itertools.pairwise(cuts):
            r.add(t[a:b], mask[a:b])
        r.close()
        assert out == _intervals_where(t, mask)


def test_sample_index_search_and_magnetometer_grid_match_their_array_definitions() -> None:
    """The chunked look-ups give what the whole arrays give: ``searchsorted`` on the sample
    instants, and the magnetometer's samples ``round(arange(0, T, 1/f_m) · f)``."""
    rng = np.random.default_rng(5)
    for rate in (100.0, 33.0, 1000.0, 7.3):
        n, dt = 500, 1.0 / rate
        t = np.arange(n) * dt
        for x in [*rng.uniform(-0.1, 1.1, 30) * t[-1], *t[::37], -1.0, 1e9]:
            assert _first_at_or_after(float(x), n, dt) == int(np.searchsorted(t, x)), (rate, x)
    for rate, mag_rate, duration in ((100.0, 30.0, 10.0), (1000.0, 100.0, 3.3), (50.0, 50.0, 2.0),
                                     (200.0, 7.0, 5.0)):
        s = SimStream("static", duration=duration, rate=rate, mag_rate=mag_rate, chunk=13)
        n = len(s)
        want = np.zeros(n, dtype=bool)
        want[np.unique(np.round(np.arange(0, duration, 1.0 / mag_rate) * rate).astype(int))] = True
        got = np.concatenate([s._mag_keep(a, min(a + 13, n)) for a in range(0, n, 13)])
        np.testing.assert_array_equal(got, want)


def _peak_mb(duration: float) -> tuple[float, int]:
    tracemalloc.start()
    n = 0
    try:
        for part in SimStream("wiener", duration=duration, rate=100.0, mag_rate=20.0,
                              chunk=500):
            n += len(part)
        return tracemalloc.get_traced_memory()[1] / 1e6, n
    finally:
        tracemalloc.stop()


def test_memory_is_bounded_by_the_chunk_not_the_duration() -> None:
    """Traced allocations (numpy's included) while streaming 10 s and 300 s (30 000 samples,
    3 million rate steps, ~120 MB as whole arrays): the same small peak."""
    short, n_short = _peak_mb(10.0)
    long, n_long = _peak_mb(300.0)
    assert n_long == 30_001 and n_short == 1_001
    assert long < 40.0, long
    assert long < 1.3 * short + 2.0, (short, long)
