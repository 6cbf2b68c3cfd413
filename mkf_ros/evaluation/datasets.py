"""Readers for real IMU recordings with optical ground truth (benchmark only, no ROS).

Each reader takes a dataset folder and returns a list of :class:`Recording`: the sensor arrays
in the units :func:`mkf_ros.estimate` expects (s, rad/s, m/s², magnetometer in any unit), the
reference orientation as [w, x, y, z] sensor → world quaternions (NaN rows where the reference
is invalid or missing) and how the recording must be scored (see :mod:`mkf_ros.evaluation.scoring`).
Adding a format is one function ``read_xxx(folder) -> list[Recording]`` in :data:`READERS` and,
optionally, a content test in :func:`detect_format`.

Formats:

- ``repoimu``: RepoIMU T-stick (Szczęsna et al., ICCVG 2016) semicolon CSV, two header lines,
  columns time, Vicon quaternion W X Y Z, acc (m/s²), gyro (rad/s), magnetometer (normalised).
  The Vicon quaternion is relative to the start pose, so scoring needs one constant global
  alignment. The static trial (no reference) is skipped; ``Test05`` is read but marked
  ``excluded`` (its reference is unusable: 40–110° errors for every algorithm).
- ``ese650``: UPenn ESE 650 (2011) ``imu/imuRawK.mat`` raw 10-bit ADC counts and
  ``vicon/viconRotK.mat`` rotation matrices on the same clock; 6D, inclination only.
- ``broad``: BROAD (Laidig et al., Data 2021, CC BY 4.0) ``NN_*.mat`` trials (rad/s, m/s², µT,
  optical quaternion in ENU, 286 Hz) and ``trials.json`` (each trial's groups); 9D, scored only
  on the ``movement`` samples, no alignment.

The data themselves are not part of this package (RepoIMU and ESE650 state no licence); the
readers only take a folder given by the user. ``.mat`` files need SciPy, imported lazily (a test
and benchmark dependency: ``requirements/dev.txt``, not a runtime one).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Standard gravity, to convert accelerometer readings in g to m/s².
G0 = 9.80665

ALL_ERRORS: tuple[str, ...] = ("total", "heading", "inclination")


@dataclass
class Recording:
    """One recording: sensors, reference and how to score it (one row per IMU sample)."""

    name: str  #: unique within its dataset, e.g. ``TStick_Test02_Trial1`` or ``set01``
    dataset: str  #: format key in :data:`READERS`
    t: np.ndarray  #: (N,) s, strictly increasing
    gyr: np.ndarray  #: (N, 3) rad/s, sensor frame
    acc: np.ndarray  #: (N, 3) m/s², specific force (+g up at rest)
    mag: np.ndarray | None  #: (N, 3) any unit, or None (no magnetometer)
    q_ref: np.ndarray  #: (N, 4) [w, x, y, z] sensor → reference world; NaN rows = invalid
    #: ``"constant_global"``: score ``G ⊗ q_est`` with G the quaternion average of
    #: ``q_ref ⊗ q_est⁻¹`` (reference world has an arbitrary constant rotation);
    #: ``"none"``: compare directly (reference world z is up, heading arbitrary).
    alignment: str = "none"
    errors: tuple[str, ...] = ALL_ERRORS  #: error kinds that are meaningful for this recording
    excluded: bool = False  #: not part of the dataset mean (reported separately)
    note: str = ""  #: why it is excluded / what is suspect
    meta: dict = field(default_factory=dict)  #: reader-specific details (biases, counts, ...)

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def valid(self) -> np.ndarray:
        """(N,) bool: samples with a valid reference."""
        return np.isfinite(self.q_ref).all(axis=1)

    @property
    def has_mag(self) -> bool:
        """True if a magnetometer is present."""
        return self.mag is not None

    @property
    def rate(self) -> float:
        """Mean sampling rate in Hz, (N − 1) / (t[-1] − t[0])."""
        return float((len(self.t) - 1) / (self.t[-1] - self.t[0]))


# ----------------------------------------------------------------------------------- helpers
def quat_from_rotmat(r: np.ndarray) -> np.ndarray:
    """Quaternions [w, x, y, z] (w ≥ 0) of rotation matrices ``r`` of shape (..., 3, 3), such
    that ``R(q) = r`` (the matrix maps sensor to world when q does): the filter's own
    :func:`mkf_ros.core.frames.quat_from_matrix` (Shepperd's method, accurate for every
    rotation) on each matrix. Non-finite input gives NaN rows."""
    from mkf_ros.core.frames import quat_from_matrix

    r = np.asarray(r, dtype=float)
    m = r.reshape(-1, 3, 3)
    q = np.full((m.shape[0], 4), np.nan)
    for i in np.flatnonzero(np.isfinite(m).all(axis=(1, 2))):
        q[i] = quat_from_matrix(np.ascontiguousarray(m[i]))
    return q.reshape(*r.shape[:-2], 4)


def _valid_rotmats(r: np.ndarray, tol: float = 1e-3) -> np.ndarray:
    """(M,) bool for rotation matrices (M, 3, 3): finite, orthonormal and det = +1 within tol."""
    ok = np.isfinite(r).all(axis=(1, 2))
    rr = np.where(ok[:, None, None], r, np.eye(3))
    orth = np.abs(np.einsum("nij,nkj->nik", rr, rr) - np.eye(3)).max(axis=(1, 2)) < tol
    det = np.abs(np.linalg.det(rr) - 1.0) < tol
    return ok & orth & det


def match_nearest(t: np.ndarray, t_ref: np.ndarray, q_ref: np.ndarray,
                  tol: float) -> tuple[np.ndarray, np.ndarray]:
    """Reference quaternion for each time in ``t``: the valid (finite) row of ``q_ref`` whose
    stamp in ``t_ref`` is nearest, if within ``tol`` seconds, else a NaN row. ``t_ref`` need
    not be sorted and may repeat. Returns the (N, 4) quaternions and the (N,) time offsets
    ``t_ref[match] − t`` (NaN where unmatched)."""
    good = np.isfinite(q_ref).all(axis=1) & np.isfinite(t_ref)
    tr = t_ref[good]
    qr = q_ref[good]
    n = t.shape[0]
    out = np.full((n, 4), np.nan)
    off = np.full(n, np.nan)
    if tr.size == 0:
        return out, off
    order = np.argsort(tr, kind="stable")
    tr, qr = tr[order], qr[order]
    j = np.searchsorted(tr, t)
    lo = np.clip(j - 1, 0, tr.size - 1)
    hi = np.clip(j, 0, tr.size - 1)
    pick = np.where(np.abs(tr[hi] - t) < np.abs(tr[lo] - t), hi, lo)
    d = tr[pick] - t
    ok = np.abs(d) <= tol
    out[ok] = qr[pick[ok]]
    off[ok] = d[ok]
    return out, off


# ----------------------------------------------------------------------------------- RepoIMU
REPOIMU_EXCLUDED = {"TStick_Test05": "reference unusable (40-110 deg errors for every algorithm)"}
REPOIMU_SUSPECT = {"TStick_Test06_Trial1": "suspect reference (~11 deg inclination error for "
                                           "every algorithm)"}


def read_repoimu_csv(path: str | Path) -> Recording:
    """Read one RepoIMU CSV (two header lines, ``;``-separated, optional trailing ``;``).

    Reference rows whose quaternion norm is not 1 ± 0.01 (e.g. the all-zero rows of the static
    trial) become NaN. The magnetometer is returned in the file's normalised units."""
    path = Path(path)
    a = np.loadtxt(path, delimiter=";", skiprows=2, usecols=range(14), ndmin=2)
    t = a[:, 0]
    q = a[:, 1:5].copy()
    norm = np.linalg.norm(q, axis=1)
    q[~(np.abs(norm - 1.0) < 0.01)] = np.nan
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q[q[:, 0] < 0] *= -1.0
    name = path.stem
    excluded = next((why for key, why in REPOIMU_EXCLUDED.items() if name.startswith(key)), "")
    note = excluded or REPOIMU_SUSPECT.get(name, "")
    return Recording(
        name=name, dataset="repoimu", t=t, gyr=a[:, 8:11].copy(), acc=a[:, 5:8].copy(),
        mag=a[:, 11:14].copy(), q_ref=q, alignment="constant_global", errors=ALL_ERRORS,
        excluded=bool(excluded), note=note, meta={"path": str(path)},
    )


def _repoimu_files(folder: Path) -> list[Path]:
    for d in (folder, folder / "TStick"):
        files = sorted(d.glob("TStick_*.csv"))
        if files:
            return files
    return []


def read_repoimu(folder: str | Path) -> list[Recording]:
    """RepoIMU T-stick: every ``TStick_*.csv`` in ``folder`` (or ``folder/TStick``) that has a
    reference (the static trial has none and is skipped), sorted by name. 9D."""
    folder = Path(folder)
    files = _repoimu_files(folder)
    if not files:
        raise FileNotFoundError(f"no TStick_*.csv in {folder} (RepoIMU T-stick folder expected)")
    recs = []
    for f in files:
        r = read_repoimu_csv(f)
        if r.valid.any():
            recs.append(r)
    return recs


# ----------------------------------------------------------------------------------- ESE650
ESE650_VREF_MV = 3300.0
ESE650_FULL_SCALE = 1023.0
ESE650_ACC_MV_PER_G = 330.0  # ADXL335 at 3.3 V
ESE650_GYR_MV_PER_DPS = 3.33  # 4x outputs
#: zero-g levels of the accelerometer after the x, y sign flip (counts)
ESE650_ACC_ZERO = np.array([-510.8, -501.0, 505.1])
ESE650_BIAS_SAMPLES = 200  # the board rests ~2 s at the start
ESE650_MATCH_TOL = 0.006  # s, nearest Vicon frame (Vicon 100 Hz, IMU ~104 Hz)


def ese650_convert(vals: np.ndarray, bias_samples: int = ESE650_BIAS_SAMPLES
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Raw ESE650 counts (6, N) → gyro (N, 3) rad/s, acc (N, 3) m/s², gyro bias (3,) counts.

    Row order of ``vals`` is [ax, ay, az, wz, wx, wy]; ax, ay are sign-inverted. Accelerometer
    ``(flipped − zero_g) · 3300/1023 / 330`` g (then × 9.80665), gyro
    ``(raw_xyz − bias) · 3300/1023 / (3.33 · 180/π)`` rad/s, with the gyro bias the mean of the
    first ``bias_samples`` samples (the board rests at the start)."""
    v = np.asarray(vals, dtype=float)
    if v.ndim != 2 or v.shape[0] != 6:
        raise ValueError(f"vals must have shape (6, N), got {v.shape}")
    acc_raw = np.stack([-v[0], -v[1], v[2]], axis=1)
    acc = (acc_raw - ESE650_ACC_ZERO) * (ESE650_VREF_MV / ESE650_FULL_SCALE) \
        / ESE650_ACC_MV_PER_G * G0
    gyr_raw = v[[4, 5, 3]].T
    bias = gyr_raw[:bias_samples].mean(axis=0)
    gyr = (gyr_raw - bias) * (ESE650_VREF_MV / ESE650_FULL_SCALE) \
        / (ESE650_GYR_MV_PER_DPS * 180.0 / np.pi)
    return gyr, acc, bias


def _loadmat(path: Path) -> dict:
    try:
        from scipy.io import loadmat
    except ImportError as e:  # pragma: no cover - test and bench dependency, not runtime
        raise ImportError("reading .mat files needs scipy (pip install -r "
                          "requirements/dev.txt, or ./run setup)") from e
    return loadmat(str(path))


def read_ese650_set(imu_path: str | Path, vicon_path: str | Path, name: str = "",
                    tol: float = ESE650_MATCH_TOL) -> Recording:
    """One ESE650 set: raw IMU counts converted to SI, Vicon matrices (body → world) converted
    to quaternions, invalid frames dropped, and each IMU sample given the nearest valid Vicon
    frame within ``tol`` seconds (no interpolation: the Vicon stamps jitter by a few ms, so
    interpolating between them gains nothing; unmatched samples get NaN)."""
    imu = _loadmat(Path(imu_path))
    vic = _loadmat(Path(vicon_path))
    vals = np.asarray(imu["vals"])
    ts = np.asarray(imu["ts"], dtype=float).ravel()
    gyr, acc, bias = ese650_convert(vals)
    rots = np.moveaxis(np.asarray(vic["rots"], dtype=float), -1, 0)  # (M, 3, 3)
    tv = np.asarray(vic["ts"], dtype=float).ravel()
    good = _valid_rotmats(rots)
    qv = np.full((rots.shape[0], 4), np.nan)
    qv[good] = quat_from_rotmat(rots[good])
    q_ref, off = match_nearest(ts, tv, qv, tol)
    # strictly increasing IMU stamps: drop (rare) repeated or backward ones
    keep = np.concatenate([[True], ts[1:] > np.maximum.accumulate(ts)[:-1]])
    return Recording(
        name=name or Path(imu_path).stem, dataset="ese650", t=ts[keep] - ts[0], gyr=gyr[keep],
        acc=acc[keep], mag=None, q_ref=q_ref[keep], alignment="none", errors=("inclination",),
        meta={"gyro_bias_counts": bias.tolist(), "vicon_frames": int(rots.shape[0]),
              "vicon_invalid": int((~good).sum()), "t0_unix": float(ts[0]),
              "matched": int(np.isfinite(off[keep]).sum()), "dropped_imu": int((~keep).sum()),
              "imu_path": str(imu_path)},
    )


def read_ese650(folder: str | Path) -> list[Recording]:
    """ESE650: every set K with both ``imu/imuRawK.mat`` and ``vicon/viconRotK.mat`` (1–10 in
    the course data; 11–13 have no Vicon and are skipped), sorted by K, named ``setKK``."""
    folder = Path(folder)
    sets = []
    for p in (folder / "imu").glob("imuRaw*.mat"):
        m = re.fullmatch(r"imuRaw(\d+)", p.stem)
        if m and (folder / "vicon" / f"viconRot{m.group(1)}.mat").is_file():
            sets.append(int(m.group(1)))
    if not sets:
        raise FileNotFoundError(f"no imu/imuRawK.mat with vicon/viconRotK.mat in {folder} "
                                "(ESE650 folder expected)")
    return [read_ese650_set(folder / "imu" / f"imuRaw{k}.mat",
                            folder / "vicon" / f"viconRot{k}.mat", name=f"set{k:02d}")
            for k in sorted(sets)]


# ----------------------------------------------------------------------------------- BROAD
#: BROAD's trial files: two digits, an underscore, the trial's name (``01_undisturbed_...``).
BROAD_GLOB = "[0-9][0-9]_*.mat"


def read_broad_trial(path: str | Path, groups: tuple[str, ...] = (),
                     group_categories: dict[str, str] | None = None,
                     description: str = "") -> Recording:
    """One BROAD trial (``.mat``): gyro rad/s, acc m/s², magnetometer µT, optical quaternion
    [w x y z] IMU → global (ENU, z up: no alignment). Only the ``movement`` samples are scored
    (the benchmark's rule): the reference is NaN elsewhere, and where the markers were lost.

    ``meta`` holds ``groups`` (the trial's groups from ``trials.json``), ``group_categories``
    (every group of the benchmark → its category: ``motion``, ``speed``, ``breaks``,
    ``disturbance``, or ``""`` for the levels 0–1 groups ``all_trials``, ``undisturbed``,
    ``disturbed``; in the file's order), the sampling rate and the number of movement samples."""
    path = Path(path)
    d = _loadmat(path)
    gyr = np.array(d["imu_gyr"], dtype=float)
    n = gyr.shape[0]
    rate = float(np.asarray(d["sampling_rate"], dtype=float).ravel()[0])
    q = np.array(d["opt_quat"], dtype=float)
    move = np.asarray(d["movement"]).ravel().astype(bool)
    if q.shape != (n, 4) or move.shape != (n,):
        raise ValueError(f"{path}: opt_quat {q.shape} / movement {move.shape} do not match "
                         f"imu_gyr ({n}, 3)")
    q[~move] = np.nan
    q[q[:, 0] < 0] *= -1.0
    return Recording(
        name=path.stem, dataset="broad", t=np.arange(n) / rate, gyr=gyr,
        acc=np.array(d["imu_acc"], dtype=float), mag=np.array(d["imu_mag"], dtype=float),
        q_ref=q, alignment="none", errors=ALL_ERRORS, note="",
        meta={"path": str(path), "rate": rate, "groups": list(groups),
              "group_categories": dict(group_categories or {}), "description": description,
              "movement_samples": int(move.sum())},
    )


def read_broad(folder: str | Path) -> list[Recording]:
    """BROAD (Laidig et al., Data 2021): every ``NN_*.mat`` trial in ``folder``, sorted by name,
    with its groups (motion, speed, breaks, disturbance) from ``trials.json`` when present
    (``{"groups": [{"name", "level", "category"}, ...], "trials": {stem: {"description",
    "groups"}}}``)."""
    import json

    folder = Path(folder)
    files = sorted(folder.glob(BROAD_GLOB))
    if not files:
        raise FileNotFoundError(f"no NN_*.mat trials in {folder} (BROAD folder expected)")
    meta_path = folder / "trials.json"
    meta = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    trials = meta.get("trials", {})
    cats = {g["name"]: g.get("category", "") for g in meta.get("groups", [])}
    return [read_broad_trial(f, tuple(trials.get(f.stem, {}).get("groups", ())), cats,
                             trials.get(f.stem, {}).get("description", ""))
            for f in files]


def read_tyrex_trial(path: str | Path, info: dict | None = None) -> Recording:
    """One trial of the tyrex smartphone benchmark (Michel et al., Pervasive and Mobile
    Computing 2018), as prepared for this project (``.npz``): everything on one grid at the
    gyro's rate, gyro rad/s (the authors' static bias removed), acc m/s² (+g up), magnetometer
    µT, reference quaternion [w x y z] phone → ENU (absolute heading: no alignment), ``valid``
    where the reference is scored. ``meta["groups"]``: the motion (AR, Texting, …), the
    disturbance (Dist, NoDist), the device and the user, from ``info`` (an entry of
    ``trials.json``) or the file name ``User_Device_Dist_Motion``."""
    path = Path(path)
    with np.load(path) as z:
        gyr = np.array(z["gyr"], dtype=float)
        acc = np.array(z["acc"], dtype=float)
        mag = np.array(z["mag"], dtype=float)
        q = np.array(z["q"], dtype=float)
        valid = np.asarray(z["valid"], dtype=bool)
        rate = float(z["rate"])
    n = gyr.shape[0]
    if acc.shape != (n, 3) or mag.shape != (n, 3) or q.shape != (n, 4) or valid.shape != (n,):
        raise ValueError(f"{path}: acc {acc.shape}, mag {mag.shape}, q {q.shape}, valid "
                         f"{valid.shape} do not match gyr ({n}, 3)")
    q[~valid] = np.nan
    q[q[:, 0] < 0] *= -1.0
    parts = path.stem.split("_")
    info = dict(info or {})
    device = str(info.get("device", parts[1] if len(parts) > 1 else ""))
    dist = info.get("magnetic_disturbance", len(parts) > 2 and parts[2] == "Dist")
    motion = str(info.get("motion", parts[-1]))
    user = str(info.get("user", parts[0]))
    groups = ["all_trials", motion, "Dist" if dist else "NoDist", device, user]
    cats = {"all_trials": "", "Dist": "disturbance", "NoDist": "disturbance"}
    return Recording(
        name=path.stem, dataset="tyrex", t=np.arange(n) / rate, gyr=gyr, acc=acc, mag=mag,
        q_ref=q, alignment="none", errors=ALL_ERRORS, note="",
        meta={"path": str(path), "rate": rate, "groups": groups,
              "group_categories": {**cats, motion: "motion", device: "device", user: "user"}},
    )


TYREX_GLOB = "*_*_*Dist_*.npz"


def read_tyrex(folder: str | Path) -> list[Recording]:
    """The tyrex smartphone trials in ``folder`` (``User_Device_[No]Dist_Motion.npz``, sorted by
    name), with their device, disturbance and motion from ``trials.json`` when present. The
    groups' categories are merged over the trials (every motion, disturbance and device)."""
    import json

    folder = Path(folder)
    files = sorted(folder.glob(TYREX_GLOB))
    if not files:
        raise FileNotFoundError(f"no User_Device_[No]Dist_Motion.npz trials in {folder} "
                                "(tyrex folder expected)")
    meta_path = folder / "trials.json"
    info = json.loads(meta_path.read_text()) if meta_path.is_file() else {}
    recs = [read_tyrex_trial(f, info.get(f.stem)) for f in files]
    cats: dict[str, str] = {}
    for r in recs:
        cats.update(r.meta["group_categories"])
    for r in recs:
        r.meta["group_categories"] = cats
    return recs


# ----------------------------------------------------------------------------------- registry
READERS: dict[str, Callable[[Path], list[Recording]]] = {
    "repoimu": read_repoimu,
    "ese650": read_ese650,
    "broad": read_broad,
    "tyrex": read_tyrex,
}


def detect_format(folder: str | Path) -> str:
    """The :data:`READERS` key for a dataset folder, decided by its content."""
    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder} is not a directory")
    if any((folder / "imu").glob("imuRaw*.mat")) and any((folder / "vicon").glob("viconRot*.mat")):
        return "ese650"
    if _repoimu_files(folder):
        return "repoimu"
    if any(folder.glob(BROAD_GLOB)):
        return "broad"
    if any(folder.glob(TYREX_GLOB)):
        return "tyrex"
    raise ValueError(f"cannot tell the format of {folder}: expected TStick_*.csv (RepoIMU), "
                     "imu/imuRawK.mat + vicon/viconRotK.mat (ESE650), NN_*.mat (BROAD) or "
                     "User_Device_[No]Dist_Motion.npz (tyrex); "
                     f"known: {', '.join(READERS)}")


def read_dataset(folder: str | Path, fmt: str | None = None) -> tuple[str, list[Recording]]:
    """Read a dataset folder with the reader of ``fmt`` (auto-detected if None)."""
    fmt = fmt or detect_format(folder)
    if fmt not in READERS:
        raise ValueError(f"unknown dataset format {fmt!r}; known: {', '.join(READERS)}")
    return fmt, READERS[fmt](Path(folder))
