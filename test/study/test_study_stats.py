"""The study's metric and statistics (spec docs/math.md §7.3, §8 items 12-13)."""

from __future__ import annotations

import numpy as np
import pytest

from mkf_ros.study import sim
from mkf_ros.study.stats import agreement, cell_stats, paired_difference


def test_angle_metric_is_rotation_angle_and_sign_invariant() -> None:
    # θ(q̂, q) = 2 arccos|q̂·q| (eq. 72): 90° about x, and q ~ −q
    a = np.array([1.0, 0.0, 0.0, 0.0])
    b = np.array([np.cos(np.pi / 4), np.sin(np.pi / 4), 0.0, 0.0])
    assert sim._angle(a, b) == pytest.approx(np.pi / 2, abs=1e-12)
    assert sim._angle(a, -b) == pytest.approx(np.pi / 2, abs=1e-12)
    assert sim._angle(b, b * (1 + 1e-15)) == 0.0  # clamped, no NaN


def test_cell_stats_mean_sigma_ci_and_exclusions() -> None:
    err = np.array([1.0, 2.0, 3.0, 4.0, 50.0, np.nan, np.nan])
    status = np.array([sim.OK, sim.OK, sim.OK, sim.OK, sim.NON_CONVERGED, sim.CRASHED_CONV,
                       sim.CRASHED_EST], dtype=np.int8)
    conv = np.array([10, 20, 30, 40, 100, 5, 7])
    s = cell_stats(err, status, conv)
    sd = np.std([1, 2, 3, 4], ddof=1)
    assert (s.n_s, s.n_used, s.non_converged, s.crashed) == (7, 4, 1, 2)
    assert s.mu == pytest.approx(2.5)
    assert s.sigma == pytest.approx(sd)
    # eq. 74 with k = 3: μ ± 3σ/√n over the n runs in the mean
    assert s.ci_lo == pytest.approx(2.5 - 3 * sd / 2)
    assert s.ci_hi == pytest.approx(2.5 + 3 * sd / 2)
    assert s.mu_all == pytest.approx(np.mean([1, 2, 3, 4, 50]))
    assert s.conv_updates_mean == pytest.approx(np.mean(conv))
    # a run stopped at a fixed point is a non-converged run, counted once more as stalled
    s2 = cell_stats(np.append(err, 60.0), np.append(status, sim.STALLED), np.append(conv, 9))
    assert (s2.n_used, s2.non_converged, s2.stalled, s2.crashed) == (4, 2, 1, 2)
    assert s2.mu == pytest.approx(2.5)
    assert s2.mu_all == pytest.approx(np.mean([1, 2, 3, 4, 50, 60]))


def test_agreement_rules() -> None:
    s = cell_stats(np.array([2.0, 2.2, 2.4, 2.6]), np.zeros(4, dtype=np.int8), np.ones(4))
    rel, within, overlap = agreement(s, 2.5, None)
    assert rel == pytest.approx((2.3 - 2.5) / 2.5) and within and overlap
    # far away and tight: neither within 10% nor overlapping
    rel, within, overlap = agreement(s, 10.0, (9.5, 10.5))
    assert not within and not overlap and rel == pytest.approx(-0.77)
    # outside ±10% but the published bar reaches our interval
    rel, within, overlap = agreement(s, 2.9, (2.5, 3.3))
    assert not within and overlap


def test_paired_difference_uses_common_trajectories_only() -> None:
    a = np.array([1.0, 2.0, 3.0, 4.0])
    b = a - 0.5 + np.array([0.01, -0.01, 0.02, -0.02])
    ok = np.array([True, True, True, False])
    m, hw, n = paired_difference(a, b, ok, np.ones(4, bool))
    d = (a - b)[:3]
    assert n == 3 and m == pytest.approx(d.mean())
    assert hw == pytest.approx(3 * d.std(ddof=1) / np.sqrt(3))
