"""REP-145 rules (mkf_ros/rep145.py) against the REP's text, transcribed literally."""

from __future__ import annotations

import math

import numpy as np

from mkf_ros.stream import rep145

MARKER = [-1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0]  # REP-145: covariance[0] = -1


def test_not_reported_marker_and_inputs() -> None:
    np.testing.assert_array_equal(rep145.NOT_REPORTED, MARKER)
    assert not rep145.NOT_REPORTED.flags.writeable
    assert rep145.input_vector([1.0, 2.0, 3.0], -1.0) is None
    np.testing.assert_array_equal(rep145.input_vector([1.0, 2.0, 3.0], 0.0), [1.0, 2.0, 3.0])
    rows = rep145.input_rows([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], np.array([-1.0, 0.5]))
    assert np.isnan(rows[0]).all()
    np.testing.assert_array_equal(rows[1], [4.0, 5.0, 6.0])


def test_published_covariance_rules() -> None:
    known = np.arange(1.0, 10.0)
    own = np.full((3, 3), 7.0)
    # no value: the marker, whatever the input said
    np.testing.assert_array_equal(rep145.published_covariance(None, own, known, 0.5), MARKER)
    # the filter's own covariance replaces the input's
    np.testing.assert_array_equal(rep145.published_covariance(np.zeros(3), own, known, 0.5),
                                  [7.0] * 9)
    # known input: copied; unknown (zeros): 0.5² on the diagonal
    np.testing.assert_array_equal(rep145.published_covariance(np.zeros(3), None, known, 0.5),
                                  known)
    np.testing.assert_array_equal(
        rep145.published_covariance(np.zeros(3), None, np.zeros(9), 0.5),
        [0.25, 0, 0, 0, 0.25, 0, 0, 0, 0.25])
    marker = rep145.published_covariance(None, None, known, 0.5)
    marker[0] = 3.0  # the caller owns its copy
    assert rep145.NOT_REPORTED[0] == -1.0


def test_stacked_rules_equal_one_message_at_a_time() -> None:
    rng = np.random.default_rng(0)
    m = 40
    ok = rng.random(m) > 0.3
    inp = np.where(rng.random((m, 1)) > 0.5, 0.0, rng.normal(size=(m, 9)))
    own = rng.normal(size=(m, 3, 3))
    own[rng.random(m) > 0.5] = math.nan
    add = np.where(rng.random((m, 1, 1)) > 0.5, math.nan, np.eye(3) * 1e-3)
    add[~np.isnan(own[:, 0, 0])] = math.nan
    got = rep145.published_covariances(ok, own, inp, 0.1, add)
    for k in range(m):
        one = rep145.published_covariance(
            np.zeros(3) if ok[k] else None, None if np.isnan(own[k, 0, 0]) else own[k],
            inp[k], 0.1, None if np.isnan(add[k, 0, 0]) else add[k])
        np.testing.assert_array_equal(got[k], one, err_msg=str(k))
    np.testing.assert_array_equal(rep145.published_covariances(ok, None, inp, 0.1)[~ok],
                                  np.tile(MARKER, ((~ok).sum(), 1)))
