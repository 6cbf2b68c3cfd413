"""Real-data readers (mkf_ros.evaluation.datasets) and the benchmark (bench/real_data.py) on tiny
synthetic files written in each format from simulated truth. No real data are needed. SciPy (for the
``.mat`` formats) is a test dependency (requirements/dev.txt): a missing SciPy fails here.
Scoring itself is tested in test_scoring.py."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from quat_helpers import canon, random_quats
from scipy.io import savemat

import mkf_ros
from mkf_ros.core.quaternion import qconj_np, qmul_np, rotmat_np
from mkf_ros.evaluation.datasets import (
    ALL_ERRORS,
    ESE650_ACC_ZERO,
    G0,
    READERS,
    Recording,
    detect_format,
    ese650_convert,
    match_nearest,
    quat_from_rotmat,
    read_broad,
    read_dataset,
    read_repoimu,
)
from mkf_ros.evaluation.scoring import (
    global_alignment,
    score_recording,
)
from mkf_ros.sim import simulate

ROOT = Path(__file__).resolve().parents[2]
HEADER = ("Time (s);Vicon Orientation;;;;IMU Acceleration;;;IMU Gyroscope;;;"
          "IMU Magnetometer;;;\n;W;X;Y;Z;X;Y;Z;X;Y;Z;X;Y;Z;\n")
ACC_SCALE = 3300.0 / 1023.0 / 330.0  # g per count
GYR_SCALE = 3300.0 / 1023.0 / (3.33 * 180.0 / math.pi)  # rad/s per count
GYR_BIAS = np.array([373.6, 375.4, 369.7])  # x, y, z counts


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
    d = ese650_sim(tmp_path, dtype=np.uint16)
    r = read_dataset(tmp_path, "ese650")[1][0]
    np.testing.assert_allclose(r.acc, d["sim"].acc, atol=0.6 * ACC_SCALE * G0)
    np.testing.assert_allclose(r.gyr, d["sim"].gyr, atol=1.2 * GYR_SCALE)


# ----------------------------------------------------------------------------------- BROAD
BROAD_RATE = 2000.0 / 7.0  # 285.714... Hz, as in the dataset
BROAD_GROUPS = [  # the benchmark's group list (trials.json), abridged
    {"name": "all_trials", "level": 0, "category": ""},
    {"name": "undisturbed", "level": 1, "category": ""},
    {"name": "rotation", "level": 2, "category": "motion"},
    {"name": "translation", "level": 2, "category": "motion"},
    {"name": "slow", "level": 2, "category": "speed"},
    {"name": "fast", "level": 2, "category": "speed"},
    {"name": "no_breaks", "level": 2, "category": "breaks"},
    {"name": "with_breaks", "level": 2, "category": "breaks"},
    {"name": "disturbed", "level": 1, "category": ""},
    {"name": "tapping", "level": 2, "category": "disturbance"},
]
BROAD_TRIALS = {
    "01_undisturbed_slow_rotation_A": ["all_trials", "undisturbed", "rotation", "slow",
                                       "no_breaks"],
    "24_disturbed_tapping_A": ["all_trials", "disturbed", "tapping"],
}


def broad_sim(folder: Path) -> dict:
    """Write two BROAD trials (``NN_*.mat`` with the README's keys and shapes) from the
    simulator, magnetometer in µT, and a trials.json. The movement phase is samples 100-899
    of 1000; markers are lost at 500-509; the reference's sign is flipped on every 3rd row."""
    sim = simulate("slow_rotation", duration=999 / BROAD_RATE, rate=BROAD_RATE, seed=8)
    n = len(sim)
    move = np.zeros((n, 1), dtype=np.uint8)
    move[100:900] = 1
    q = canon(sim.quat)
    q[::3] *= -1.0
    q[500:510] = np.nan
    mag_ut = sim.mag * 1e6
    for stem in BROAD_TRIALS:
        savemat(folder / f"{stem}.mat", {
            "imu_gyr": sim.gyr, "imu_acc": sim.acc, "imu_mag": mag_ut, "opt_quat": q,
            "opt_pos": np.zeros((n, 3)), "sampling_rate": np.array([[BROAD_RATE]]),
            "movement": move, "info": np.array(["synthetic"])})
    savemat(folder / "99_not_in_trials_json.mat", {
        "imu_gyr": sim.gyr[:50], "imu_acc": sim.acc[:50], "imu_mag": mag_ut[:50],
        "opt_quat": q[:50], "opt_pos": np.zeros((50, 3)),
        "sampling_rate": np.array([[BROAD_RATE]]), "movement": move[:50] + 1})
    (folder / "trials.json").write_text(json.dumps({
        "groups": BROAD_GROUPS,
        "trials": {k: {"description": k.replace("_", " "), "groups": g}
                   for k, g in BROAD_TRIALS.items()}}))
    return {"sim": sim, "n": n, "mag_ut": mag_ut}


def test_broad_roundtrip(tmp_path: Path) -> None:
    d = broad_sim(tmp_path)
    sim, n = d["sim"], d["n"]
    assert detect_format(tmp_path) == "broad"
    fmt, recs = read_dataset(tmp_path)
    assert fmt == "broad"
    assert [r.name for r in recs] == [*BROAD_TRIALS, "99_not_in_trials_json"]
    r = recs[0]
    assert r.dataset == "broad" and r.alignment == "none" and r.errors == ALL_ERRORS
    assert r.has_mag and not r.excluded and len(r) == n
    for k in ("gyr", "acc", "mag"):
        assert getattr(r, k).shape == (n, 3) and getattr(r, k).dtype == np.float64
    np.testing.assert_allclose(r.t, np.arange(n) / BROAD_RATE, rtol=1e-12)
    assert r.rate == pytest.approx(BROAD_RATE) and r.meta["rate"] == pytest.approx(BROAD_RATE)
    np.testing.assert_allclose(r.gyr, sim.gyr)  # rad/s as stored
    np.testing.assert_allclose(r.acc, sim.acc)  # m/s², +g up at rest
    assert np.linalg.norm(r.acc, axis=1).mean() == pytest.approx(G0, rel=0.05)
    np.testing.assert_allclose(r.mag, d["mag_ut"])  # µT as stored
    # the reference: NaN outside the movement phase and where the markers were lost,
    # w ≥ 0 and equal to the truth elsewhere
    valid = np.zeros(n, dtype=bool)
    valid[100:900] = True
    valid[500:510] = False
    assert (r.valid == valid).all()
    assert r.meta["movement_samples"] == 800
    np.testing.assert_allclose(r.q_ref[valid], canon(sim.quat[valid]), atol=1e-12)
    # groups and their categories from trials.json
    assert r.meta["groups"] == BROAD_TRIALS["01_undisturbed_slow_rotation_A"]
    assert recs[1].meta["groups"] == ["all_trials", "disturbed", "tapping"]
    assert r.meta["group_categories"]["rotation"] == "motion"
    assert r.meta["group_categories"]["tapping"] == "disturbance"
    assert list(r.meta["group_categories"]) == [g["name"] for g in BROAD_GROUPS]
    assert "slow rotation" in r.meta["description"]
    assert recs[2].meta["groups"] == [] and recs[2].valid.all()  # not in trials.json
    # only movement samples are scored: an estimate that is wrong outside them scores 0
    q_est = canon(sim.quat)
    q_est[:100] = [0.0, 1.0, 0.0, 0.0]
    s = score_recording(r, q_est)
    assert max(s.values()) < 1e-6
    # without trials.json: no groups, same data
    (tmp_path / "trials.json").unlink()
    r2 = read_broad(tmp_path)[0]
    assert r2.meta["groups"] == [] and r2.meta["group_categories"] == {}
    np.testing.assert_array_equal(r2.valid, r.valid)


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


def test_tyrex_roundtrip(tmp_path: Path) -> None:
    """Two trials written in the prepared format (float32 arrays on the gyro's grid, a
    ``valid`` mask, trials.json for one of them): read back as float64, the reference NaN where
    not valid and w ≥ 0, groups motion / disturbance / device from trials.json or the name."""
    import json

    sim = simulate("slow_rotation", duration=3, rate=100, seed=5)
    n = sim.t.size
    valid = np.ones(n, dtype=bool)
    valid[40:60] = False
    q = sim.quat.astype(np.float32)
    q[::2] *= -1.0  # either sign stored
    for stem in ("Jakob_Nexus5_Dist_AR", "Ann_iPhone5_NoDist_RunningPocket"):
        np.savez(tmp_path / f"{stem}.npz", gyr=sim.gyr.astype(np.float32),
                 acc=sim.acc.astype(np.float32), mag=(sim.mag * 1e6).astype(np.float32), q=q,
                 valid=valid, rate=np.float64(100.0))
    (tmp_path / "trials.json").write_text(json.dumps({"Jakob_Nexus5_Dist_AR": {
        "device": "Nexus5", "magnetic_disturbance": True, "motion": "AR"}}))
    assert detect_format(tmp_path) == "tyrex"
    fmt, recs = read_dataset(tmp_path)
    assert fmt == "tyrex" and [r.name for r in recs] == ["Ann_iPhone5_NoDist_RunningPocket",
                                                          "Jakob_Nexus5_Dist_AR"]
    r = recs[1]
    assert r.alignment == "none" and r.has_mag and len(r) == n and r.gyr.dtype == np.float64
    np.testing.assert_allclose(r.t, np.arange(n) / 100.0)
    np.testing.assert_allclose(r.gyr, sim.gyr.astype(np.float32))
    assert (r.valid == valid).all()
    np.testing.assert_allclose(r.q_ref[valid], canon(sim.quat[valid]), atol=1e-6)
    assert r.meta["groups"] == ["all_trials", "AR", "Dist", "Nexus5", "Jakob"]
    assert recs[0].meta["groups"] == ["all_trials", "RunningPocket", "NoDist", "iPhone5", "Ann"]
    cats = recs[0].meta["group_categories"]
    assert cats["AR"] == cats["RunningPocket"] == "motion" and cats["iPhone5"] == "device"
    assert cats["Jakob"] == cats["Ann"] == "user"  # each user on his own (per-user tables)


def test_detect_format_errors(tmp_path: Path) -> None:
    assert set(READERS) == {"repoimu", "ese650", "broad", "tyrex"}
    with pytest.raises(ValueError, match="cannot tell"):
        detect_format(tmp_path)
    with pytest.raises(FileNotFoundError):
        detect_format(tmp_path / "missing")
    with pytest.raises(ValueError, match="unknown dataset format"):
        read_dataset(tmp_path, "nope")


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
    assert {"madgwick 6D", "madgwick 9D", "euler_kf 6D"} <= set(cols)
    no_base = [f"{a.name} {d}" for a, d in rd.columns(True, None, baselines=False)]
    assert not any(c.split()[0] in ("euler_kf", "euler_ukf", "madgwick-ours") for c in no_base)
    assert "mekf 9D" in no_base and "madgwick 6D" in no_base
    cols6 = [f"{a.name} {d}" for a, d in rd.columns(False, ["m*"])]
    assert cols6[:2] == ["mekf 6D", "mukf 6D"]
    assert {"madgwick 6D", "mahony 6D"} <= set(cols6) and all(c.startswith("m") for c in cols6)


def test_bench_gyro_delay_reads_the_gyro_later() -> None:
    """``--gyro-delay S``: each stamp gets the gyro reading S median periods later (a ramp is
    interpolated exactly; the last stamp holds the last reading)."""
    rd = _bench()
    t = np.arange(6) * 0.01
    gyr = np.stack([t, 2.0 * t, -t], axis=1)
    out = rd._delayed(t, gyr, 0.5)
    np.testing.assert_allclose(out[:-1], np.stack([t + 0.005, 2 * (t + 0.005), -(t + 0.005)],
                                                  axis=1)[:-1], atol=1e-15)
    np.testing.assert_array_equal(out[-1], gyr[-1])


def test_bench_help(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        _bench().main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "--no-baselines" in out and "tilt coverage" in out


def test_bench_end_to_end_on_synthetic_files(tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    repoimu_sim(tmp_path)
    rd = _bench()
    assert rd.main([str(tmp_path), "--algorithms", "mekf*", "gyro-only*", "--jobs", "1",
                    "--json", str(tmp_path / "out.json")]) == 0
    out = capsys.readouterr().out
    assert "TStick_Test02_Trial1" in out and "excluded: TStick_Test05_Trial2" in out
    row = next(ln for ln in out.splitlines() if ln.startswith("| repoimu ") and "mekf 9D" in ln)
    assert [c.strip() for c in row.split("|")[1:4]] == ["repoimu", "1", "mekf 9D"]
    assert "repoimu 9D mean total: mekf" in out
    # tilt coverage: ours publish a covariance, the peers do not
    assert "3σ tilt coverage" in out and "**pooled**" in out
    assert "repoimu 3σ tilt coverage (pooled): mekf 9D" in out
    payload = json.loads((tmp_path / "out.json").read_text())
    s = payload["datasets"][0]["recordings"][0]["scores"]
    assert 0.0 <= s["mekf 9D"]["cov"] <= 1.0 and s["mekf 9D"]["cov_n"] > 0
    assert "cov" not in s["gyro-only 6D"]
    assert any(t["status"] == "n/a" for t in payload["targets"])  # no vqf column here


def test_bench_broad_classes_and_targets(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    broad_sim(tmp_path)
    rd = _bench()
    assert rd.main([str(tmp_path), "--algorithms", "mekf*", "gyro-only*", "--jobs", "1"]) == 0
    out = capsys.readouterr().out
    assert "## broad:" in out and "3 recordings in the mean" in out
    assert "| tilt σ |" in out.replace("  ", " ").replace("  ", " ")
    assert "### broad per class" in out
    for line in ("| rotation (1)   | 9D total", "| tapping (1)    | 6D inclination",
                 "no trial here: translation", "| all_trials (2)  | 9D heading"):
        assert line in out, line
    assert "broad every trial 9D total ≤ 1.5 × vqf + 0.3: mekf" in out
    assert any(ln.startswith("targets: ") and "FAIL" in ln for ln in out.splitlines())


def _fake_broad(rd: ModuleType, vals: dict[str, dict[str, tuple[float, float]]],
                cov: float = 0.95) -> object:
    """A BROAD DatasetResult whose columns' (9D total, 6D inclination) per trial are ``vals``."""
    names = list(next(iter(vals.values())))
    recs = [Recording(n, "broad", np.arange(3.0), np.zeros((3, 3)), np.zeros((3, 3)),
                      np.zeros((3, 3)), np.ones((3, 4))) for n in names]
    results: dict = {n: {} for n in names}
    for col, per in vals.items():
        for n, (tot, inc) in per.items():
            results[n][f"{col} 9D"] = {"total": tot, "heading": tot, "inclination": inc}
            results[n][f"{col} 6D"] = {"total": 9.0, "heading": 9.0, "inclination": inc}
            if col in ("mekf", "mukf"):
                for d in ("9D", "6D"):
                    results[n][f"{col} {d}"].update(cov_in=cov * 100, cov_n=100.0, cov=cov)
    cols = [f"{c} {d}" for c in vals for d in ("6D", "9D")]
    ds = rd.DatasetResult("broad", "x", recs, results, cols)
    ds.means = {c: {**rd.dataset_mean([results[n][c] for n in names]),
                    **rd.coverage_means([results[n][c] for n in names])} for c in cols}
    return ds


def test_bench_target_logic() -> None:
    rd = _bench()
    vals = {"vqf": {"a": (2.0, 0.6), "b": (1.0, 0.5)},
            "vqf-offline": {"a": (1.0, 0.3), "b": (1.0, 0.3)},
            "mekf": {"a": (1.8, 0.5), "b": (1.9, 0.6)},  # b: 1.9 > 1.5·1.0 + 0.3 = 1.8
            "mukf": {"a": (1.9, 0.5), "b": (1.8, 0.6)}}
    checks = rd.target_checks({"broad": _fake_broad(rd, vals)})
    by = {c.text: c.status for c in checks}
    assert by["broad 9D mean total: mekf 1.850 ≤ vqf 9D 1.500 (README 2.79)"] == "FAIL"
    assert by["broad 6D mean inclination: mekf 0.550 ≤ vqf 6D 0.550 (README 0.78)"] == "PASS"
    assert by["(moonshot) broad 6D mean inclination: mekf 0.550 ≤ vqf-offline 6D 0.300 "
              "(README 0.57)"] == "not met"
    trial = next(c for c in checks if c.text.startswith("broad every trial 9D total")
                 and ": mekf" in c.text)
    assert trial.status == "FAIL" and trial.text.endswith("1/2 trials; over: b 1.90 > 1.80")
    trial_u = next(c for c in checks if c.text.startswith("broad every trial 9D total")
                   and ": mukf" in c.text)
    assert trial_u.status == "PASS"  # 1.8 ≤ 1.8
    within = [c for c in checks if c.text.startswith("mukf within")]
    assert within and all(c.status == "PASS" for c in within)  # ≤ 5.6 % apart
    cover = [c for c in checks if "tilt coverage" in c.text]
    assert len(cover) == 4 and all(c.status == "PASS" for c in cover)
    # MUKF 20 % off on one trial, coverage 80 %: FAIL lines; moonshots never count as FAIL
    vals["mukf"]["a"] = (2.2, 0.5)
    checks = rd.target_checks({"broad": _fake_broad(rd, vals, cov=0.8)})
    bad = {c.text.split(":")[0] for c in checks if c.status == "FAIL"}
    assert "mukf within 10% of mekf, broad every trial 9D total" in bad
    assert "broad 3σ tilt coverage (pooled)" in bad
    assert not any(c.moonshot and c.status == "FAIL" for c in checks)
