"""Published results of the paper's study, digitised from its Figs. 5–7 (``docs/math.md``
§7.5): mean orientation error in degrees per (filter, chart, R, update) at the rates
:data:`RATES_HZ`. ``cu`` = chart update, ``reset`` = no chart update (NCU). The MUKF values are
those of the authors' ``Q_ω·Δt²`` noise scaling (§8 item 3).
"""

from __future__ import annotations

RATES_HZ: tuple[float, ...] = (2.0, 5.0, 10.0, 50.0, 100.0, 500.0, 1000.0)

#: (filter, chart, R, update) → μ in degrees at each of RATES_HZ
MEAN_DEG: dict[tuple[str, str, float, str], tuple[float, ...]] = {
    ("mekf", "o", 1e-2, "cu"): (75.8, 54.9, 26.8, 5.57, 3.48, 1.51, 1.06),
    ("mekf", "o", 1e-2, "reset"): (79.9, 58.4, 26.8, 5.47, 3.46, 1.5, 1.05),
    ("mekf", "rp", 1e-2, "cu"): (81.2, 59.4, 28.2, 5.39, 3.46, 1.49, 1.1),
    ("mekf", "rp", 1e-2, "reset"): (76.3, 54.6, 25.7, 5.34, 3.61, 1.56, 1.07),
    ("mekf", "mrp", 1e-2, "cu"): (76.3, 60.1, 27.2, 5.39, 3.47, 1.51, 1.08),
    ("mekf", "mrp", 1e-2, "reset"): (74.3, 59.1, 26.4, 5.38, 3.45, 1.56, 1.06),
    ("mekf", "rv", 1e-2, "cu"): (79.0, 58.3, 27.4, 5.39, 3.47, 1.46, 1.09),
    ("mekf", "rv", 1e-2, "reset"): (77.5, 56.9, 26.6, 5.45, 3.49, 1.5, 1.08),
    ("mekf", "o", 1e-4, "cu"): (70.6, 60.9, 34.3, 5.4, 2.77, 1.0, 0.76),
    ("mekf", "o", 1e-4, "reset"): (71.2, 65.0, 34.9, 5.3, 2.79, 0.98, 0.75),
    ("mekf", "rp", 1e-4, "cu"): (75.8, 65.3, 39.7, 5.22, 2.75, 0.99, 0.75),
    ("mekf", "rp", 1e-4, "reset"): (69.6, 58.9, 35.1, 5.41, 2.85, 1.01, 0.74),
    ("mekf", "mrp", 1e-4, "cu"): (74.9, 62.6, 34.7, 5.3, 2.77, 0.98, 0.73),
    ("mekf", "mrp", 1e-4, "reset"): (72.6, 60.9, 34.8, 5.3, 2.8, 0.96, 0.72),
    ("mekf", "rv", 1e-4, "cu"): (74.4, 62.3, 35.2, 5.17, 2.8, 0.99, 0.76),
    ("mekf", "rv", 1e-4, "reset"): (71.0, 60.5, 35.3, 5.22, 2.89, 0.99, 0.72),
    ("mekf", "o", 1e-6, "cu"): (73.9, 62.2, 34.2, 5.43, 2.75, 0.99, 0.75),
    ("mekf", "o", 1e-6, "reset"): (71.2, 62.6, 34.2, 5.09, 2.84, 1.03, 0.77),
    ("mekf", "rp", 1e-6, "cu"): (75.1, 68.0, 38.5, 5.27, 2.79, 0.97, 0.72),
    ("mekf", "rp", 1e-6, "reset"): (72.9, 58.9, 36.2, 5.36, 2.73, 0.96, 0.73),
    ("mekf", "mrp", 1e-6, "cu"): (75.5, 62.6, 37.2, 5.41, 2.82, 0.94, 0.73),
    ("mekf", "mrp", 1e-6, "reset"): (68.8, 60.5, 34.6, 5.3, 2.87, 0.97, 0.75),
    ("mekf", "rv", 1e-6, "cu"): (72.9, 61.2, 37.1, 5.35, 2.77, 0.97, 0.74),
    ("mekf", "rv", 1e-6, "reset"): (74.3, 62.6, 36.0, 5.3, 2.79, 0.97, 0.72),
    ("mukf", "o", 1e-2, "cu"): (81.8, 44.3, 26.7, 18.6, 19.6, 19.6, 19.1),
    ("mukf", "o", 1e-2, "reset"): (87.9, 48.1, 27.6, 18.4, 18.9, 19.1, 18.6),
    ("mukf", "rp", 1e-2, "cu"): (87.5, 52.2, 31.3, 19.6, 18.9, 18.7, 18.8),
    ("mukf", "rp", 1e-2, "reset"): (80.5, 45.1, 26.7, 19.5, 18.2, 18.8, 18.6),
    ("mukf", "mrp", 1e-2, "cu"): (83.1, 51.7, 28.6, 19.2, 19.4, 18.7, 18.3),
    ("mukf", "mrp", 1e-2, "reset"): (81.4, 45.5, 27.3, 19.3, 19.0, 18.6, 19.0),
    ("mukf", "rv", 1e-2, "cu"): (84.3, 48.9, 27.7, 19.5, 18.9, 18.7, 17.6),
    ("mukf", "rv", 1e-2, "reset"): (79.6, 46.0, 27.8, 20.1, 18.8, 19.2, 18.1),
    ("mukf", "o", 1e-4, "cu"): (87.5, 60.1, 35.7, 8.51, 4.56, 1.64, 1.42),
    ("mukf", "o", 1e-4, "reset"): (97.0, 67.0, 38.6, 8.41, 4.57, 1.63, 1.38),
    ("mukf", "rp", 1e-4, "cu"): (94.0, 66.3, 39.6, 8.83, 4.62, 1.65, 1.37),
    ("mukf", "rp", 1e-4, "reset"): (88.2, 61.4, 36.3, 8.31, 4.45, 1.62, 1.42),
    ("mukf", "mrp", 1e-4, "cu"): (94.4, 67.1, 40.0, 8.39, 4.44, 1.65, 1.37),
    ("mukf", "mrp", 1e-4, "reset"): (89.9, 64.3, 37.7, 9.01, 4.49, 1.6, 1.38),
    ("mukf", "rv", 1e-4, "cu"): (95.1, 68.2, 37.7, 8.73, 4.4, 1.66, 1.37),
    ("mukf", "rv", 1e-4, "reset"): (93.4, 65.5, 38.7, 8.54, 4.45, 1.57, 1.43),
    ("mukf", "o", 1e-6, "cu"): (92.0, 66.9, 40.1, 9.66, 4.7, 1.22, 0.85),
    ("mukf", "o", 1e-6, "reset"): (98.1, 74.0, 42.6, 9.76, 4.91, 1.23, 0.84),
    ("mukf", "rp", 1e-6, "cu"): (92.9, 67.1, 41.4, 9.73, 5.15, 1.23, 0.84),
    ("mukf", "rp", 1e-6, "reset"): (90.6, 67.8, 41.8, 9.5, 4.66, 1.22, 0.85),
    ("mukf", "mrp", 1e-6, "cu"): (95.5, 69.8, 43.0, 10.0, 4.63, 1.22, 0.82),
    ("mukf", "mrp", 1e-6, "reset"): (92.3, 67.3, 42.3, 9.43, 4.69, 1.24, 0.83),
    ("mukf", "rv", 1e-6, "cu"): (96.6, 72.2, 41.9, 9.51, 4.81, 1.23, 0.85),
    ("mukf", "rv", 1e-6, "reset"): (93.4, 68.6, 41.3, 9.54, 4.75, 1.25, 0.85),
}

#: Confidence bars of Fig. 6 (RP chart, chart update): (filter, R) → {rate: (low, high)} in degrees
CI_FIG6_DEG: dict[tuple[str, float], dict[float, tuple[float, float]]] = {
    ("mekf", 1e-2): {2.0: (75.5, 87.3), 10.0: (25.8, 30.6), 100.0: (3.26, 3.66),
                     1000.0: (1.03, 1.17)},
    ("mekf", 1e-4): {2.0: (69.9, 81.6), 10.0: (36.2, 43.4), 100.0: (2.58, 2.92),
                     1000.0: (0.70, 0.79)},
    ("mekf", 1e-6): {2.0: (69.1, 81.2), 10.0: (35.0, 42.0), 100.0: (2.61, 2.96),
                     1000.0: (0.68, 0.76)},
    ("mukf", 1e-2): {2.0: (82.6, 92.5), 10.0: (28.9, 33.7), 100.0: (17.4, 20.4),
                     1000.0: (17.2, 20.3)},
    ("mukf", 1e-4): {2.0: (89.5, 98.8), 10.0: (36.6, 42.6), 100.0: (4.29, 4.96),
                     1000.0: (1.25, 1.48)},
    ("mukf", 1e-6): {2.0: (88.4, 97.7), 10.0: (38.3, 44.5), 100.0: (4.73, 5.54),
                     1000.0: (0.79, 0.88)},
}

#: The paper's N_s (trajectories per configuration).
N_S_PAPER = 1000


def published_mean(filt: str, chart: str, r: float, update: str, rate_hz: float) -> float | None:
    """The published μ (degrees) of a cell, or None if the paper has no such cell."""
    vals = MEAN_DEG.get((filt, chart, r, update))
    if vals is None or rate_hz not in RATES_HZ:
        return None
    return vals[RATES_HZ.index(rate_hz)]


def published_ci(filt: str, chart: str, r: float, update: str,
                 rate_hz: float) -> tuple[float, float] | None:
    """The published confidence bar (degrees) of a cell, where Fig. 6 shows one."""
    if chart != "rp" or update != "cu":
        return None
    return CI_FIG6_DEG.get((filt, r), {}).get(rate_hz)
