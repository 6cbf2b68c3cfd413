"""Real-data readers and scoring (mkf_ros.datasets, mkf_ros.scoring, bench/real_data.py) on tiny
synthetic files written in each format from simulated truth. No real data are needed."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

import mkf_ros
from mkf_ros.core.quaternion import qconj_np, qmul_np, rotmat_np
from mkf_ros.datasets import (
    ALL_ERRORS,
    ESE650_ACC_ZERO,
    G0,
    READERS,
    Recording,
    detect_format,
    ese650_convert,
    match_nearest,
    quat_from_rotmat,
    read_dataset,
    read_repoimu,
)
from mkf_ros.scoring import (
    dataset_mean,
    error_series,
    global_alignment,
    quat_average,
    score_recording,
)
from mkf_ros.sim import simulate

ROOT = Path(__file__).resolve().parent.parent
HEADER = ("Time (s);Vicon Orientation;;;;IMU Acceleration;;;IMU Gyroscope;;;"
          "IMU Magnetometer;;;\n;W;X;Y;Z;X;Y;Z;X;Y;Z;X;Y;Z;\n")
ACC_SCALE = 3300.0 / 1023.0 / 330.0  # g per count
GYR_SCALE = 3300.0 / 1023.0 / (3.33 * 180.0 / math.pi)  # rad/s per count
GYR_BIAS = np.array([373.6, 375.4, 369.7])  # x, y, z counts


def canon(q: np.ndarray) -> np.ndarray:
    """Unit quaternions with w ≥ 0 (q and −q are the same rotation)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0, -q, q)


def random_quats(n: int, seed: int) -> np.ndarray:
    return canon(np.random.default_rng(seed).normal(size=(n, 4)))


def quat_z(angle: float) -> np.ndarray:
    return np.array([math.cos(angle / 2), 0.0, 0.0, math.sin(angle / 2)])


# ----------------------------------------------------------------------------------- writers
def write_repoimu_csv(path: Path, t: np.ndarray, q: np.ndarray, acc: np.ndarray,
                      gyr: np.ndarray, mag: np.ndarray) -> None:
    """A RepoIMU T-stick file: two header lines, ';'-separated, trailing ';' on every line."""
    rows = np.column_stack([t, q, acc, gyr, mag])
    with open(path, "w") as f:
        f.write(HEADER)
        for r in rows:
            f.write(";".join(f"{x:.17g}" for x in r) + ";\n")


def repoimu_sim(folder: Path) -> tuple[dict, np.ndarray]:
    """Write a T-stick-like trial from the simulator (reference relative to the start pose,
    magnetometer normalised), a Test05 trial and a static one; return the truth and the
    constant rotation between the reference world and ENU."""
    sim = simulate("slow_rotation", duration=8.0, rate=100.0, seed=4)
    c = qconj_np(sim.quat[0])  # reference world = start pose: q_ref = q0⁻¹ ⊗ q_enu
    q_ref = canon(qmul_np(c, sim.quat))
    mag = sim.mag / np.linalg.norm(sim.mag, axis=1, keepdims=True)
    t = 0.08 + np.arange(len(sim)) * 0.01
    truth = {"t": t, "q_ref": q_ref, "acc": sim.acc, "gyr": sim.gyr, "mag": mag}
    write_repoimu_csv(folder / "TStick_Test02_Trial1.csv", t, q_ref, sim.acc, sim.gyr, mag)
    write_repoimu_csv(folder / "TStick_Test05_Trial2.csv", t, q_ref, sim.acc, sim.gyr, mag)
    write_repoimu_csv(folder / "TStick_Test01_Static.csv", t, np.zeros_like(q_ref), sim.acc,
                      sim.gyr, mag)
    return truth, c


def ese650_raw(gyr: np.ndarray, acc: np.ndarray) -> np.ndarray:
    """Inverse of the ESE650 conversion: SI → (6, N) counts [ax, ay, az, wz, wx, wy] with the
    x, y accelerometer signs inverted, the README's zero-g levels and gyro bias."""
    flipped = acc / G0 / ACC_SCALE + ESE650_ACC_ZERO
    raw_gyr = gyr / GYR_SCALE + GYR_BIAS
    return np.stack([-flipped[:, 0], -flipped[:, 1], flipped[:, 2],
                     raw_gyr[:, 2], raw_gyr[:, 0], raw_gyr[:, 1]])


def ese650_sim(folder: Path, k: int = 1, dtype: type = np.float64) -> dict:
    """Write imu/imuRawK.mat and vicon/viconRotK.mat from the simulator: 2.5 s at rest (the
    gyro bias is taken from the first 200 samples), then sweeps. Vicon frames are stamped
    2 ms after the IMU samples; frames 300-309 are NaN and frame 400 is not a rotation."""
    from scipy.io import savemat

    sim = simulate("sweep", duration=8.0, rate=100.0, seed=5, hold=2.5, gyro_noise=0.0,
                   acc_noise=0.0)
    n = len(sim)
    ts = 1.3e9 + np.arange(n) * 0.01
    vals = ese650_raw(sim.gyr, sim.acc)
    if dtype is np.uint16:
        vals = np.round(vals)
    rots = rotmat_np(sim.quat)  # (N, 3, 3) body → world
    rots[300:310] = np.nan
    rots[400] = 2.0 * np.eye(3)
    (folder / "imu").mkdir(parents=True, exist_ok=True)
    (folder / "vicon").mkdir(parents=True, exist_ok=True)
    savemat(folder / "imu" / f"imuRaw{k}.mat", {"vals": vals.astype(dtype), "ts": ts[None, :]})
    savemat(folder / "vicon" / f"viconRot{k}.mat",
            {"rots": np.moveaxis(rots, 0, -1), "ts": (ts + 0.002)[None, :]})
    return {"sim": sim, "ts": ts}


# ----------------------------------------------------------------------------------- RepoIMU
def test_repoimu_roundtrip(tmp_path: Path) -> None:
    truth, _c = repoimu_sim(tmp_path)
    recs = read_repoimu(tmp_path)
    assert [r.name for r in recs] == ["TStick_Test02_Trial1", "TStick_Test05_Trial2"]  # no static
    r = recs[0]
    assert r.dataset == "repoimu" and r.alignment == "constant_global"
    assert r.errors == ALL_ERRORS and not r.excluded and r.has_mag
    np.testing.assert_allclose(r.t, truth["t"], atol=1e-12)
    np.testing.assert_allclose(r.q_ref, truth["q_ref"], atol=1e-12)
    for k in ("acc", "gyr", "mag"):
        np.testing.assert_allclose(getattr(r, k), truth[k], atol=1e-12)
    assert r.valid.all() and r.rate == pytest.approx(100.0)
    assert recs[1].excluded and "reference" in recs[1].note
    assert detect_format(tmp_path) == "repoimu"
    assert read_dataset(tmp_path)[0] == "repoimu"


def test_repoimu_invalid_reference_rows(tmp_path: Path) -> None:
    truth, _ = repoimu_sim(tmp_path)
    q = truth["q_ref"].copy()
    q[10:20] = 0.0
    write_repoimu_csv(tmp_path / "TStick_Test03_Trial1.csv", truth["t"], q, truth["acc"],
                      truth["gyr"], truth["mag"])
    r = next(r for r in read_repoimu(tmp_path) if r.name == "TStick_Test03_Trial1")
    assert np.isnan(r.q_ref[10:20]).all() and r.valid.sum() == len(r) - 10


def test_repoimu_frames_with_our_filter(tmp_path: Path) -> None:
    """Our 9D estimate (ENU) scored against the start-pose reference after the constant
    alignment: small errors, and the alignment found is the ENU → start-pose rotation."""
    _truth, c = repoimu_sim(tmp_path)
    r = read_repoimu(tmp_path)[0]
    q = mkf_ros.estimate(r.gyr, r.acc, r.mag, timestamps=r.t).quat
    s = score_recording(r, q)
    assert s["total"] < 1.0 and s["inclination"] < 0.5, s
    g = global_alignment(q, r.q_ref)
    ang = 2 * np.degrees(np.arccos(min(1.0, abs(float(canon(g) @ canon(c))))))
    assert ang < 1.0


# ----------------------------------------------------------------------------------- ESE650
def test_ese650_conversion_constants() -> None:
    """One count and the zero levels, straight from the README's formulas."""
    vals = np.zeros((6, 3))
    vals[:, 0] = [510.8, 501.0, 505.1, 369.7, 373.6, 375.4]  # zero-g (raw x, y unflipped), bias
    vals[:, 1] = [510.8 - 1 / ACC_SCALE, 501.0, 505.1 + 1 / ACC_SCALE, 369.7, 373.6 + 1, 375.4]
    vals[:, 2] = vals[:, 0]
    gyr, acc, bias = ese650_convert(vals, bias_samples=1)
    np.testing.assert_allclose(bias, [373.6, 375.4, 369.7])
    np.testing.assert_allclose(acc[0], 0.0, atol=1e-9)
    np.testing.assert_allclose(acc[1], [G0, 0.0, G0], atol=1e-9)  # x sign flipped back
    np.testing.assert_allclose(gyr[1], [GYR_SCALE, 0.0, 0.0], atol=1e-12)
    with pytest.raises(ValueError, match="shape"):
        ese650_convert(np.zeros((3, 10)))


def test_ese650_roundtrip(tmp_path: Path) -> None:
    pytest.importorskip("scipy")
    d = ese650_sim(tmp_path, k=3)
    sim = d["sim"]
    assert detect_format(tmp_path) == "ese650"
    fmt, recs = read_dataset(tmp_path)
    assert fmt == "ese650" and [r.name for r in recs] == ["set03"]
    r = recs[0]
    assert r.alignment == "none" and r.errors == ("inclination",) and not r.has_mag
    np.testing.assert_allclose(r.t, d["ts"] - d["ts"][0], atol=1e-6)
    np.testing.assert_allclose(r.gyr, sim.gyr, atol=1e-9)  # bias from the rest at the start
    np.testing.assert_allclose(r.acc, sim.acc, atol=1e-9)
    np.testing.assert_allclose(r.meta["gyro_bias_counts"], GYR_BIAS, atol=1e-9)
    # reference: nearest frame (2 ms late) = the truth; NaN / non-rotation frames dropped
    bad = np.zeros(len(r), dtype=bool)
    bad[300:310] = True
    bad[400] = True
    assert (r.valid == ~bad).all()
    np.testing.assert_allclose(r.q_ref[~bad], canon(sim.quat[~bad]), atol=1e-9)
    assert r.meta["vicon_invalid"] == 11
    # frames: our 6D estimate on the converted data matches the reference's inclination
    q = mkf_ros.estimate(r.gyr, r.acc, timestamps=r.t).quat
    s = score_recording(r, q)
    assert np.isnan(s["total"]) and np.isnan(s["heading"]) and s["inclination"] < 1.0, s


def test_ese650_uint16_counts(tmp_path: Path) -> None:
    pytest.importorskip("scipy")
    d = ese650_sim(tmp_path, dtype=np.uint16)
    r = read_dataset(tmp_path, "ese650")[1][0]
    np.testing.assert_allclose(r.acc, d["sim"].acc, atol=0.6 * ACC_SCALE * G0)
    np.testing.assert_allclose(r.gyr, d["sim"].gyr, atol=1.2 * GYR_SCALE)


def test_match_nearest() -> None:
    t = np.array([0.0, 0.01, 0.02, 0.03])
    t_ref = np.array([0.031, 0.0, 0.0115, 0.0115, 0.5])  # unsorted, repeated
    q = random_quats(5, 1)
    q[2] = np.nan  # invalid: the repeated stamp's valid twin is used
    out, off = match_nearest(t, t_ref, q, tol=0.006)
    np.testing.assert_allclose(out[0], q[1])
    np.testing.assert_allclose(out[1], q[3])
    assert np.isnan(out[2]).all() and np.isnan(off[2])  # nearest is 8.5 ms away
    np.testing.assert_allclose(out[3], q[0])
    np.testing.assert_allclose(off[[0, 1, 3]], [0.0, 0.0015, 0.001], atol=1e-12)


def test_quat_from_rotmat_every_branch() -> None:
    q = random_quats(500, 2)
    # include the four branch extremes: w, x, y, z dominant (180° turns and identity)
    q = np.vstack([q, np.eye(4)])
    np.testing.assert_allclose(quat_from_rotmat(rotmat_np(q)), canon(q), atol=1e-12)
    assert np.isnan(quat_from_rotmat(np.full((3, 3), np.nan))).all()


def test_detect_format_errors(tmp_path: Path) -> None:
    assert set(READERS) == {"repoimu", "ese650"}
    with pytest.raises(ValueError, match="cannot tell"):
        detect_format(tmp_path)
    with pytest.raises(FileNotFoundError):
        detect_format(tmp_path / "missing")
    with pytest.raises(ValueError, match="unknown dataset format"):
        read_dataset(tmp_path, "nope")


# ----------------------------------------------------------------------------------- scoring
def _rec(q_ref: np.ndarray, alignment: str) -> Recording:
    n = q_ref.shape[0]
    z = np.zeros((n, 3))
    return Recording("r", "test", np.arange(n) * 0.01, z, z, None, q_ref, alignment=alignment)


def test_alignment_recovers_constant_rotation() -> None:
    q_est = random_quats(300, 3)
    g_true = canon(np.array([0.3, -0.5, 0.7, 0.2]))
    q_ref = qmul_np(g_true, q_est)
    q_ref[::7] *= -1.0  # sign flips must not matter
    q_ref[5] = np.nan  # invalid rows are ignored
    g = global_alignment(q_est, q_ref)
    np.testing.assert_allclose(canon(g), g_true, atol=1e-12)
    s = score_recording(_rec(q_ref, "constant_global"), q_est)
    assert max(s.values()) < 1e-5
    # without the alignment the same estimate is far off
    assert score_recording(_rec(q_ref, "none"), q_est)["total"] > 10.0


def test_alignment_is_an_average_under_noise() -> None:
    rng = np.random.default_rng(7)
    q_est = random_quats(2000, 4)
    noise = canon(np.column_stack([np.ones(2000), rng.normal(0, 0.01, (2000, 3))]))
    g_true = canon(np.array([1.0, 0.2, 0.1, -0.3]))
    q_ref = qmul_np(qmul_np(g_true, noise), q_est)
    g = global_alignment(q_est, q_ref)
    assert 2 * np.degrees(np.arccos(min(1.0, abs(float(g @ g_true))))) < 0.1


def test_inclination_ignores_heading_offset() -> None:
    q_ref = random_quats(200, 5)
    q_est = qmul_np(quat_z(0.4), q_ref)  # world-frame heading offset of 0.4 rad
    s = score_recording(_rec(q_ref, "none"), q_est)
    assert s["inclination"] < 1e-5
    assert s["heading"] == pytest.approx(np.degrees(0.4), abs=1e-9)
    assert s["total"] == pytest.approx(np.degrees(0.4), abs=1e-9)
    tilt = np.array([math.cos(0.05), math.sin(0.05), 0.0, 0.0])  # 0.1 rad about world x
    s2 = score_recording(_rec(q_ref, "none"), qmul_np(tilt, q_est))
    assert s2["inclination"] == pytest.approx(np.degrees(0.1), rel=1e-6)


def test_scoring_meaningful_kinds_skip_start_and_mean() -> None:
    q_ref = random_quats(100, 6)
    r = _rec(q_ref, "none")
    r.errors = ("inclination",)
    q_est = q_ref.copy()
    q_est[:10] = qmul_np(np.array([math.cos(0.1), math.sin(0.1), 0, 0]), q_ref[:10])
    s = score_recording(r, q_est)
    assert np.isnan(s["total"]) and np.isnan(s["heading"]) and s["inclination"] > 1.0
    assert score_recording(r, q_est, skip_start=0.1)["inclination"] < 1e-5
    e = error_series(r, q_est, skip_start=0.05)
    assert np.isnan(e["inclination"][:5]).all() and np.isfinite(e["inclination"][5:]).all()
    m = dataset_mean([{"total": 1.0, "heading": 2.0, "inclination": 3.0},
                      {"total": 3.0, "heading": 4.0, "inclination": 5.0}])
    assert m == {"total": 2.0, "heading": 3.0, "inclination": 4.0}
    assert canon(quat_average(np.vstack([q_ref[0], -q_ref[0]]))) == pytest.approx(
        canon(q_ref[0]))


# ----------------------------------------------------------------------------------- bench
def _bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("real_data", ROOT / "bench" / "real_data.py")
    assert spec is not None and spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules["real_data"] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def test_bench_overrides_and_columns() -> None:
    rd = _bench()
    assert rd.parse_overrides(["acc_noise=0.1", "estimate_gyro_bias=true",
                               "mag_reference=0,1,-1"]) == {
        "acc_noise": 0.1, "estimate_gyro_bias": True, "mag_reference": [0.0, 1.0, -1.0]}
    for bad in (["acc_noise=-1"], ["nope=1"], ["algorithm=mukf"], ["acc_noise"]):
        with pytest.raises(SystemExit):
            rd.parse_overrides(bad)
    cols = [f"{a.name} {d}" for a, d in rd.columns(True, None)]
    assert "mekf 9D" in cols and "vqf 9D" in cols and "mahony 6D" not in cols
    cols6 = [f"{a.name} {d}" for a, d in rd.columns(False, ["m*"])]
    assert cols6[:2] == ["mekf 6D", "mukf 6D"]
    assert {"madgwick 6D", "mahony 6D"} <= set(cols6) and all(c.startswith("m") for c in cols6)


def test_bench_end_to_end_on_synthetic_files(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    repoimu_sim(tmp_path)
    rd = _bench()
    assert rd.main([str(tmp_path), "--algorithms", "mekf*", "gyro-only*", "--jobs", "1",
                    "--json", str(tmp_path / "out.json")]) == 0
    out = capsys.readouterr().out
    assert "TStick_Test02_Trial1" in out and "excluded: TStick_Test05_Trial2" in out
    assert "| repoimu | 1 | mekf 9D |" in out and "repoimu 9D mean total: mekf" in out
    assert (tmp_path / "out.json").is_file()
