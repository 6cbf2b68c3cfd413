"""The cells of the study (``docs/math.md`` §7.1) and how a selection of them is named.

A *cell* is one (filter, chart, update, R, rate) configuration run on ``N_s`` trajectories; the
paper has 2 × 4 × 2 × 3 × 7 = 336 of them. Two further keys select readings the paper leaves
open: the MUKF noise scaling (§8 item 3; ``-`` for the MEKF, which has none) and the sampling of
the true noise levels (§8 item 11).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import numpy as np

from mkf_ros.core.charts import CHART_NAMES
from mkf_ros.study import published
from mkf_ros.study.sim import MEKF, MUKF, n_updates

FILTERS: tuple[str, ...] = ("mekf", "mukf")
CHARTS: tuple[str, ...] = CHART_NAMES  # o, rp, mrp, rv
UPDATES: tuple[str, ...] = ("cu", "reset")  # chart update / reset (no chart update, NCU)
RS: tuple[float, ...] = (1e-2, 1e-4, 1e-6)
RATES_HZ: tuple[float, ...] = published.RATES_HZ
SCALINGS: tuple[str, ...] = ("published", "consistent")  # MUKF ω noise: Q_ω·Δt² / Q_ω·Δt
SAMPLINGS: tuple[str, ...] = ("sigma", "variance")  # true noise: σ- or variance-uniform
NO_SCALING = "-"

#: Trajectories per work unit (fixed, so that resumed runs cut the same chunks).
CHUNK = 5


@dataclass(frozen=True)
class Cell:
    """One configuration of the study; ``key`` identifies it in the CSV and the part files."""

    filter: str
    chart: str
    update: str
    r: float
    rate_hz: float
    mukf_scaling: str = NO_SCALING
    sampling: str = "sigma"

    @property
    def key(self) -> str:
        return (f"{self.filter}/{self.chart}/{self.update}/R={self.r:.0e}/f={self.rate_hz:g}/"
                f"{self.mukf_scaling}/{self.sampling}")

    @property
    def label(self) -> str:
        """The cell as the report's tables name it: ``MEKF RP cu R=1e-02 100 Hz``."""
        return (f"{self.filter.upper()} {self.chart.upper()} {self.update} R={self.r:.0e} "
                f"{self.rate_hz:g} Hz")

    @property
    def variant(self) -> tuple[str, str, str, str]:
        """The filter variant (everything except R, rate and sampling)."""
        return (self.filter, self.chart, self.update, self.mukf_scaling)

    @property
    def spec(self) -> tuple[int, int, int, int]:
        """Row ``(kind, chart id, chart_update, published_scaling)`` for the numba runner."""
        return (MEKF if self.filter == "mekf" else MUKF, CHARTS.index(self.chart),
                int(self.update == "cu"), int(self.mukf_scaling == "published"))

    @property
    def published_deg(self) -> float | None:
        return published.published_mean(self.filter, self.chart, self.r, self.update,
                                         self.rate_hz)

    @property
    def published_ci_deg(self) -> tuple[float, float] | None:
        return published.published_ci(self.filter, self.chart, self.r, self.update, self.rate_hz)

    def sort_key(self) -> tuple:
        return (SAMPLINGS.index(self.sampling), FILTERS.index(self.filter),
                (*SCALINGS, NO_SCALING).index(self.mukf_scaling), self.r * -1.0,
                CHARTS.index(self.chart), UPDATES.index(self.update), self.rate_hz)


def cells(filters: Iterable[str] = FILTERS, charts: Iterable[str] = CHARTS,
          updates: Iterable[str] = UPDATES, rs: Iterable[float] = RS,
          rates: Iterable[float] = RATES_HZ, scalings: Iterable[str] = ("published",),
          samplings: Iterable[str] = ("sigma",)) -> list[Cell]:
    """Every combination of the selection, MEKF cells once (they have no MUKF scaling)."""
    out: list[Cell] = []
    for s in samplings:
        for f in filters:
            for sc in (scalings if f == "mukf" else (NO_SCALING,)):
                for r in rs:
                    for c in charts:
                        for u in updates:
                            for rate in rates:
                                out.append(Cell(f, c, u, float(r), float(rate), sc, s))
    return sorted(set(out), key=Cell.sort_key)


def validate(values: Sequence[str], allowed: Sequence[str], what: str) -> list[str]:
    """Lower-cased ``values``; ``ValueError`` naming the choices for an unknown one."""
    out = []
    for v in values:
        k = v.strip().lower()
        if k not in allowed:
            raise ValueError(f"unknown {what} {v!r}; choose from {', '.join(allowed)}")
        out.append(k)
    return out


def chunks(n_s: int) -> list[tuple[int, int]]:
    """Trajectory ranges ``[t0, t1)`` of the work units."""
    return [(t0, min(t0 + CHUNK, n_s)) for t0 in range(0, n_s, CHUNK)]


# Cost model for the progress bar and its ETA only, in MEKF updates: mean convergence-phase
# length per rate (MEKF, MUKF; measured in a --quick run) and the MUKF/MEKF time per update.
_CONV_MEAN = {2.0: (35000, 6000), 5.0: (8500, 2000), 10.0: (2400, 1300), 50.0: (650, 1600),
              100.0: (1050, 2250), 500.0: (2450, 2800), 1000.0: (2700, 3300)}
_T_UPDATE = (1.0, 6.0)  # MEKF, MUKF
SUBSTEP_COST = 2.0  # truth simulation (100 sub-steps) per update


def unit_cost(group: Sequence[Cell], n_traj: int) -> float:
    """Rough relative cost of running ``group`` (cells of one rate) on ``n_traj`` trajectories."""
    if not group:
        return 0.0
    rate = group[0].rate_hz
    conv = _CONV_MEAN.get(rate, (2000, 2000))
    c = 0.0
    for cell in group:
        k = 0 if cell.filter == "mekf" else 1
        c += (n_updates(rate) + conv[k]) * _T_UPDATE[k]
    c += n_updates(rate) * SUBSTEP_COST
    return c * n_traj


def specs_array(group: Sequence[Cell]) -> tuple[np.ndarray, np.ndarray, list[tuple]]:
    """Distinct variant specs and Rs of ``group`` for :func:`sim.run_trajectory`."""
    variants = sorted({c.variant for c in group}, key=lambda v: (FILTERS.index(v[0]),
                                                                 CHARTS.index(v[1]),
                                                                 UPDATES.index(v[2]), v[3]))
    rs = sorted({c.r for c in group}, reverse=True)
    specs = np.array([Cell(v[0], v[1], v[2], 1.0, 1.0, v[3]).spec for v in variants],
                     dtype=np.int64).reshape(-1, 4)
    return specs, np.array(rs, dtype=float), variants
