"""Filter speed on this machine: the analogue of the paper's Fig. 4 (docs/math.md §7.4, §8 item 14).

The paper timed C++ builds on an Arduino MEGA and a Raspberry Pi 3 and reports only that the
MEKF runs about 3× faster than the MUKF. Here every filter × chart × chart update (the study's
nx = 6 state, one vector sensor + gyro per update) is fed the measurements of a 100 Hz study
trajectory through the core kernels; the maximum update frequency is reported as mean ± σ over
repetitions, like Fig. 4.
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass

import numpy as np

from mkf_ros.study import sim
from mkf_ros.study.config import CHARTS, UPDATES, Cell


@dataclass(frozen=True)
class Speed:
    """Updates per second of one variant (mean and σ over repetitions)."""

    filter: str
    chart: str
    update: str
    mukf_scaling: str
    mean_hz: float
    std_hz: float
    us_per_update: float

    def as_dict(self) -> dict:
        return asdict(self)


def variants(scalings: tuple[str, ...] = ("published",)) -> list[Cell]:
    """Every filter × chart × update (× MUKF scaling) as cells at R = 10⁻⁴, 100 Hz."""
    out = [Cell("mekf", c, u, 1e-4, 100.0) for c in CHARTS for u in UPDATES]
    out += [Cell("mukf", c, u, 1e-4, 100.0, s) for s in scalings for c in CHARTS for u in UPDATES]
    return out


def measure_speeds(n_updates: int = 20000, repeats: int = 7, seed: int = 1,
                   scalings: tuple[str, ...] = ("published",)) -> list[Speed]:
    """Time every variant: ``repeats`` runs of ``n_updates`` updates each (after one warm-up)."""
    rate = 100.0
    n_traj = -(-n_updates // sim.n_updates(rate))
    inps = [sim.trajectory_inputs(seed, rate, t, "sigma") for t in range(n_traj)]
    arr = {k: np.concatenate([i[k] for i in inps])[:n_updates]
           for k in ("vref", "vbody", "w_true", "z_noise")}
    out = []
    for cell in variants(scalings):
        spec = np.array(cell.spec, dtype=np.int64)
        args = (spec, cell.r, 1.0 / rate, arr["vref"], arr["vbody"], arr["w_true"],
                arr["z_noise"])
        sim.run_updates(*args[:3], *(a[:100] for a in args[3:]))  # compile / warm caches
        hz = []
        for _ in range(repeats):
            t = time.perf_counter()
            sim.run_updates(*args)
            hz.append(n_updates / (time.perf_counter() - t))
        h = np.array(hz)
        out.append(Speed(cell.filter, cell.chart, cell.update, cell.mukf_scaling,
                         float(h.mean()), float(h.std(ddof=1)) if h.size > 1 else 0.0,
                         float(1e6 / h.mean())))
    return out


def mekf_mukf_ratio(speeds: list[Speed], scaling: str = "published") -> float:
    """Mean MEKF rate over mean MUKF rate (the paper: about 3)."""
    mekf = [s.mean_hz for s in speeds if s.filter == "mekf"]
    mukf = [s.mean_hz for s in speeds if s.filter == "mukf" and s.mukf_scaling == scaling]
    return float(np.mean(mekf) / np.mean(mukf)) if mekf and mukf else float("nan")


def format_table(speeds: list[Speed]) -> str:
    """A Markdown table: variant, updates/s (mean ± σ), µs per update."""
    lines = ["| filter | chart | update | updates/s (mean ± σ) | µs/update |",
             "|---|---|---|---:|---:|"]
    for s in speeds:
        name = s.filter.upper() + ("" if s.filter == "mekf" else f" ({s.mukf_scaling})")
        lines.append(f"| {name} | {s.chart.upper()} | {s.update} | "
                     f"{s.mean_hz:,.0f} ± {s.std_hz:,.0f} | {s.us_per_update:.2f} |")
    return "\n".join(lines)
