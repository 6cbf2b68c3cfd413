"""``process_bag(smooth=True)`` (``mkf process --smooth``): the output carries the manifold
smoother's orientation and covariance, equal bit for bit to ``mkf_ros.estimate(...,
smooth=True)`` on the same samples, more accurate than the causal output against the bag's
truth; a bag smoothed in many windows (read one message at a time) matches one window within
the overlap's approximation, a window boundary on a magnetometer sample and on a gap, in
bounded memory; split input smooths too."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

import mkf_ros
from mkf_ros.bags import BagReader, cdr, mcap, smoothing
from mkf_ros.bags.process import process_bag
from mkf_ros.bags.synth import write_bag
from mkf_ros.core.smoother import forward_params
from mkf_ros.evaluation.metrics import orientation_errors, rmse_deg
from mkf_ros.sim import simulate
from mkf_ros.stream.kernel import MAX_STEPS_PER_EVENT


def _seconds(ns: np.ndarray) -> np.ndarray:
    """Stamps as the node (and ``process_bag``) turn them into seconds."""
    return ns // 1_000_000_000 + (ns % 1_000_000_000) * 1e-9


def _bag_samples(bag: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(stamps s, gyro, accelerometer, magnetometer on the IMU rows (NaN: none)) of a bag."""
    with BagReader(bag) as br:
        got = br.read(["/imu/data_raw", "/imu/mag"])
    imu = cdr.decode(got["/imu/data_raw"].raws, cdr.IMU)
    mg = cdr.decode(got["/imu/mag"].raws, cdr.MAGNETIC_FIELD)
    mag = np.full((len(imu.stamp_ns), 3), np.nan)
    i = np.searchsorted(imu.stamp_ns, mg.stamp_ns)
    assert np.array_equal(imu.stamp_ns[i], mg.stamp_ns)  # synth: at IMU stamps
    mag[i] = mg.fields["magnetic_field"]
    return (_seconds(imu.stamp_ns), imu.fields["angular_velocity"],
            imu.fields["linear_acceleration"], mag)


def _written(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """(quaternions [w, x, y, z], covariances (M, 9)) of /imu/data in an output bag."""
    with BagReader(bag) as br:
        d = cdr.decode(br.read(["/imu/data"])["/imu/data"].raws, cdr.IMU)
    q = d.fields["orientation"]
    return np.column_stack([q[:, 3], q[:, :3]]), d.fields["orientation_covariance"]


@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
def test_smoothed_output_is_estimate_smooth_and_beats_the_filter(tmp_path: Path,
                                                                 algorithm: str) -> None:
    sim = simulate("slow_rotation", duration=8.0, rate=100.0, mag_rate=25.0, seed=2)
    bag = tmp_path / "in"
    write_bag(sim, bag)
    params = dict(use_mag=True, algorithm=algorithm)
    s = process_bag(bag, tmp_path / "s", params, smooth=True, keep_outputs=True, window=100,
                    smooth_window=300, smooth_overlap=200)
    # the causal run with the smoother's forward defaults (docs/math.md §11.1)
    c = process_bag(bag, tmp_path / "c", forward_params(params), keep_outputs=True)
    t, gyr, acc, mag = _bag_samples(bag)
    e = mkf_ros.estimate(gyr, acc, mag, timestamps=t, smooth=True, smooth_window=300,
                         smooth_overlap=200, **params)  # type: ignore[arg-type]
    q_s, cov_s = _written(tmp_path / "s")
    q_c, cov_c = _written(tmp_path / "c")
    assert len(q_s) == len(e.quat) == len(sim.t) == s.n_out
    # the same samples in the same steps: the same numbers, bit for bit
    assert np.array_equal(q_s, e.quat) and np.array_equal(cov_s, e.cov.reshape(-1, 9))
    assert e.filtered_quat is not None and np.array_equal(q_c, e.filtered_quat)
    # the smoother's covariance is the smaller one (it uses more data), and the smaller error
    assert np.all(np.trace(cov_s.reshape(-1, 3, 3), axis1=1, axis2=2)
                  <= np.trace(cov_c.reshape(-1, 3, 3), axis1=1, axis2=2) * (1 + 1e-9))
    err_s = rmse_deg(orientation_errors(q_s, sim.quat)["total"])
    err_c = rmse_deg(orientation_errors(q_c, sim.quat)["total"])
    assert err_s < 0.7 * err_c
    assert s.scores is not None and c.scores is not None
    assert s.scores.rmse["total"] == pytest.approx(err_s, abs=6e-4)  # scored: what is written
    # the other fields are the filter's
    assert s.outputs is not None and c.outputs is not None
    for f in ("angular_velocity", "angular_velocity_covariance", "linear_acceleration",
              "linear_acceleration_covariance", "index"):
        assert np.array_equal(getattr(s.outputs, f), getattr(c.outputs, f)), f


@pytest.fixture(scope="module")
def dropouts(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """12 s of the dropouts scenario (a 1 s gap, a magnetometer outage) at 50 Hz with the
    magnetometer at 25 Hz, a message per MCAP chunk."""
    path = tmp_path_factory.mktemp("in") / "drop"
    mp = pytest.MonkeyPatch()
    mp.setattr(mcap, "CHUNK_BYTES", 1)  # a chunk per message: read windows of one message
    try:
        write_bag(simulate("dropouts", duration=12.0, rate=50.0, mag_rate=25.0, seed=4), path)
    finally:
        mp.undo()
    return path


def test_many_windows_give_the_output_of_one(dropouts: Path, tmp_path: Path,
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """One smoothing window over the whole bag (546 steps) against windows of ``W`` (74)
    steps with an overlap of 150 steps (3 s), the bag read one message at a time: within 0.1°
    (max, at the start: the overlap's truncation), RMS under a tenth of the smoothed error
    itself (~0.33°); a window starts right after the gap, others at a magnetometer sample.
    Memory: never more than window + overlap slots, smoothed rows and waiting messages."""
    kw = dict(params=dict(use_mag=True), keep_outputs=True)
    one = process_bag(dropouts, tmp_path / "one", window=None, smooth=True,
                      smooth_window=1000, smooth_overlap=0,
                      **kw)  # type: ignore[arg-type]
    assert one.outputs is not None and one.counters["gaps"] == 1
    slot = one.outputs.slot
    assert np.array_equal(slot, np.arange(len(slot)))  # a step per output: no held samples
    stamps = one.stamps
    assert stamps is not None
    gap = int(np.argmax(np.diff(stamps))) + 1  # the first output after the 1 s gap
    assert np.diff(stamps)[gap - 1] > 0.5
    t, _, _, mag = _bag_samples(dropouts)
    # windows of W steps, W an even divisor of the gap's slot: one starts right after the gap,
    # others at a magnetometer sample (at every other IMU sample here)
    W = max(w for w in range(20, 101) if gap % w == 0 and w % 2 == 0)
    bounds = np.arange(W, len(slot), W)  # the first slot of each later window
    assert gap in bounds and len(bounds) >= 5
    assert np.isfinite(mag[bounds, 0]).any()  # a window that starts at a magnetometer sample
    held: list[tuple[int, int, int]] = []  # (slots, smoothed rows, messages) waiting
    ready = smoothing.Smoothing.ready

    def spy(self: smoothing.Smoothing, chunk: smoothing.Chunk | None,
            final: bool) -> list[smoothing.Chunk]:
        done = ready(self, chunk, final)
        held.append((len(self.wins.rec), len(self.quat),
                     sum(len(c.out_log) for c in self.pending)))
        return done

    monkeypatch.setattr(smoothing.Smoothing, "ready", spy)
    many = process_bag(dropouts, tmp_path / "many", window=1, smooth=True, smooth_window=W,
                       smooth_overlap=150, **kw)  # type: ignore[arg-type]
    span = W + 150
    assert len(held) > 500  # a read window per IMU message (with its equal-time others)
    assert max(h[0] for h in held) == span + MAX_STEPS_PER_EVENT  # never grows
    assert max(h[1] for h in held) <= span and max(h[2] for h in held) <= span
    qa, qb = _written(tmp_path / "one")[0], _written(tmp_path / "many")[0]
    assert len(qa) == len(qb) == one.n_out
    d = np.degrees(orientation_errors(qb, qa)["total"])
    assert one.scores is not None
    assert 0.0 < d.max() < 0.1 and np.sqrt(np.mean(d ** 2)) < 0.1 * one.scores.rmse["total"]
    # the same windows read in one go: the same slots, the same numbers
    same = process_bag(dropouts, tmp_path / "same", window=None, smooth=True,
                       smooth_window=W, smooth_overlap=150, **kw)  # type: ignore[arg-type]
    assert np.array_equal(_written(tmp_path / "same")[0], qb)
    assert same.counters == many.counters == one.counters
    # and estimate(smooth=True) with these windows, bit for bit
    e = mkf_ros.estimate(*_bag_samples(dropouts)[1:], timestamps=t, smooth=True,
                         smooth_window=W, smooth_overlap=150, use_mag=True)
    assert np.array_equal(e.quat, qb)


def test_split_input_is_smoothed(tmp_path: Path) -> None:
    """Separate accelerometer (every 4th sample) and gyro topics: one output per gyro
    message, more accurate smoothed than filtered."""
    sim = simulate("slow_rotation", duration=6.0, rate=200.0, seed=3)
    bag = tmp_path / "in"
    write_bag(sim, bag, split_accel=4)
    kw = dict(accel_topic="/imu/accel", gyro_topic="/imu/gyro")
    s = process_bag(bag, tmp_path / "s", smooth=True, **kw)  # type: ignore[arg-type]
    c = process_bag(bag, tmp_path / "c", **kw)  # type: ignore[arg-type]
    assert s.n_out == c.n_out == len(sim.t)
    assert s.scores is not None and c.scores is not None
    assert s.scores.rmse["inclination"] < 0.8 * c.scores.rmse["inclination"]


def test_baselines_are_refused(tmp_path: Path, dropouts: Path) -> None:
    from mkf_ros.bags import BagError

    with pytest.raises(BagError, match="--smooth needs algorithm mekf or mukf"):
        process_bag(dropouts, tmp_path / "o", dict(algorithm="madgwick"), smooth=True)
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("algorithm", ["mekf", "mukf"])
def test_two_way_output_is_estimate_two_way(tmp_path: Path, algorithm: str) -> None:
    """``--smooth two-way``: the bag read twice, the reversed smoother streamed from a file of
    the first pass's steps; the output equals ``estimate(smooth="two-way")`` on the same
    samples bit for bit, in many smoothing windows, and no temporary file is left."""
    sim = simulate("slow_rotation", duration=8.0, rate=100.0, mag_rate=25.0, seed=2)
    bag = tmp_path / "in"
    write_bag(sim, bag)
    params = dict(use_mag=True, algorithm=algorithm)
    ticks: dict[str, int] = {}

    def progress(desc: str, total: int) -> object:
        ticks[desc] = 0
        return lambda k: ticks.__setitem__(desc, ticks[desc] + k)

    r = process_bag(bag, tmp_path / "s", params, smooth="two-way", window=100,
                    smooth_window=300, smooth_overlap=200, progress=progress)
    t, gyr, acc, mag = _bag_samples(bag)
    e = mkf_ros.estimate(gyr, acc, mag, timestamps=t, smooth="two-way", smooth_window=300,
                         smooth_overlap=200, **params)  # type: ignore[arg-type]
    q, cov = _written(tmp_path / "s")
    assert len(q) == len(t) == r.n_out
    assert np.array_equal(q, e.quat) and np.array_equal(cov, e.cov.reshape(-1, 9))
    rts = mkf_ros.estimate(gyr, acc, mag, timestamps=t, smooth=True, smooth_window=300,
                           smooth_overlap=200, **params)  # type: ignore[arg-type]
    assert not np.array_equal(q, rts.quat)  # fused: not the RTS smoother's alone
    assert ticks["reversed pass"] == len(t) and ticks["process"] > 0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in", "s"]  # the spill removed
    assert "two-way" in r.timings
    # the event loop's time less only the pauses to smooth inside it: never negative
    assert all(v >= 0.0 for v in r.timings.values()), r.timings


def test_two_way_starts_anew_where_the_filter_did(tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    """A time jump resets the filter (a new chain of steps from the first sample after it):
    the reversed pass is told to start anew at that step (the rule itself:
    test/core/test_smoother.py), and the output is finite and smoothed on both sides."""
    from mkf_ros.core import smoother

    sim = simulate("time_jump", duration=6.0, rate=100.0, mag_rate=25.0, seed=3)
    bag = tmp_path / "in"
    write_bag(sim, bag)
    seen: list[tuple[int, list[int]]] = []
    real = smoother.smooth_reversed_into

    def spy(params: object, n: int, read: object, starts: list[int], *a: object,
            **k: object) -> None:
        seen.append((n, list(starts)))
        real(params, n, read, starts, *a, **k)  # type: ignore[arg-type]

    monkeypatch.setattr(smoother, "smooth_reversed_into", spy)
    r = process_bag(bag, tmp_path / "s", dict(use_mag=True), smooth="two-way")
    c = process_bag(bag, tmp_path / "c", dict(use_mag=True))
    assert r.counters["resets_time_jump"] == 1
    k = sim.meta["time_jumps"][0][0]
    assert seen == [(len(sim.t), [k])]  # a step per sample; anew at the jump's
    assert r.scores is not None and c.scores is not None
    assert np.isfinite(_written(tmp_path / "s")[0]).all()
    assert r.scores.rmse["inclination"] < c.scores.rmse["inclination"]


def test_two_way_refuses_before_reading(tmp_path: Path, dropouts: Path) -> None:
    """An output that exists, or a baseline algorithm: refused before the first pass, nothing
    written, no temporary file."""
    from mkf_ros.bags import BagError

    (tmp_path / "o").mkdir()
    with pytest.raises(BagError, match="already exists"):
        process_bag(dropouts, tmp_path / "o", smooth="two-way")
    with pytest.raises(BagError, match="--smooth needs algorithm mekf or mukf"):
        process_bag(dropouts, tmp_path / "m", dict(algorithm="madgwick"), smooth="two-way")
    with pytest.raises(BagError, match="smooth must be"):
        process_bag(dropouts, tmp_path / "m", smooth="both")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["o"]


def test_two_way_without_disk_space_fails_with_one_line(tmp_path: Path, dropouts: Path,
                                                         monkeypatch: pytest.MonkeyPatch) -> None:
    """A full disk while the temporary files are written: a BagError naming them and the
    space they need, no output, no temporary file left."""
    import errno

    from mkf_ros.bags import BagError

    def full(*a: object, **k: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(smoothing.Capture, "SLOTS", 64)  # spill in the middle of the pass
    real_open = open
    calls = {"n": 0}

    class Full:
        def __init__(self, f: object) -> None:
            self.f = f

        def write(self, b: bytes) -> int:
            calls["n"] += 1
            if calls["n"] >= 2:
                full()
            return self.f.write(b)  # type: ignore[attr-defined]

        def close(self) -> None:
            self.f.close()  # type: ignore[attr-defined]

    monkeypatch.setattr(smoothing, "open", lambda *a, **k: Full(real_open(*a, **k)),
                        raising=False)
    with pytest.raises(BagError, match=r"--smooth two-way: cannot write its temporary files "
                       r".*0\.2 KB per IMU step.*No space left on device"):
        process_bag(dropouts, tmp_path / "o", smooth="two-way")
    assert calls["n"] == 2 and list(tmp_path.iterdir()) == []
    monkeypatch.setattr(smoothing.TwoWay, "reverse", full)
    monkeypatch.setattr(smoothing, "open", real_open, raising=False)
    with pytest.raises(BagError, match=r"No space left on device"):
        process_bag(dropouts, tmp_path / "o", smooth="two-way")
    assert list(tmp_path.iterdir()) == []
