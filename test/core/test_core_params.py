"""The single parameter definition (mkf_ros.core.params) and what is generated from it."""

from __future__ import annotations

import argparse

import pytest
import yaml

from mkf_ros.cli.options import add_filter_options, filter_overrides
from mkf_ros.cli.params_cmd import to_markdown, to_yaml
from mkf_ros.core.params import BY_NAME, PARAMS, FilterParams, filter_params


@pytest.mark.parametrize("p", PARAMS, ids=lambda p: p.name)
def test_definition_is_complete_and_default_valid(p) -> None:
    assert p.description and p.type in (bool, int, float, str, list)
    assert p.validate(p.default) == p.default
    if p.type in (int, float):
        assert p.range is not None and p.range[0] <= p.default <= p.range[1]
        assert p.unit, f"{p.name} has no unit"
    if p.choices:  # strings are either a closed set or free-form (frame ids)
        assert p.default in p.choices
    assert p.scope in ("filter", "node")


@pytest.mark.parametrize("p", [p for p in PARAMS if p.type in (int, float)], ids=lambda p: p.name)
def test_ranges_are_enforced(p) -> None:
    lo, hi = p.range
    with pytest.raises(ValueError, match=p.name):
        p.validate(hi + abs(hi) + 1)
    with pytest.raises(ValueError, match=p.name):
        p.validate(lo - abs(lo) - 1)
    with pytest.raises(ValueError, match="must be a number"):
        p.validate("fast")


def test_filter_params_mapping() -> None:
    fp = FilterParams(chart="RV", use_mag="true")
    assert fp.chart == "rv" and fp["use_mag"] is True
    assert set(fp) == {p.name for p in filter_params()}
    assert fp.replace(algorithm="mukf").algorithm == "mukf" and fp.algorithm == "mekf"


def test_filter_params_is_a_mapping() -> None:
    """The exported object behaves as the Mapping it claims to be: values()/items()/keys()
    (a field named ``values`` once shadowed values()), dict(), equality, immutability,
    pickling (process pools)."""
    import pickle
    from collections.abc import Mapping

    import mkf_ros

    fp = mkf_ros.FilterParams(chart="rv")
    names = [p.name for p in filter_params()]
    expected = {p.name: (p.default if p.name != "chart" else "rv") for p in filter_params()}
    assert isinstance(fp, Mapping)
    assert list(fp.keys()) == names and len(fp) == len(names)
    assert list(fp.values()) == [expected[n] for n in names]
    assert dict(fp.items()) == expected == dict(fp) == {**fp}
    assert fp == expected and "chart" in fp and "values" not in fp
    assert fp.get("nope", 7) == 7
    with pytest.raises(AttributeError, match="immutable"):
        fp.chart = "mrp"  # type: ignore[misc]
    with pytest.raises(AttributeError, match="no attribute 'nope'"):
        _ = fp.nope
    assert pickle.loads(pickle.dumps(fp)) == fp


def test_yaml_lists_every_parameter_with_doc() -> None:
    text = to_yaml(list(BY_NAME.values()), "estimator")
    data = yaml.safe_load(text)["estimator"]["ros__parameters"]
    assert set(data) == set(BY_NAME)
    for p in BY_NAME.values():
        assert data[p.name] == p.default
        assert f"# {p.doc()}" in text
    md = to_markdown(list(BY_NAME.values()))
    assert all(f"`{name}`" in md for name in BY_NAME)


def test_cli_flags_are_generated() -> None:
    parser = argparse.ArgumentParser()
    add_filter_options(parser)
    args = parser.parse_args(["--chart", "mrp", "--no-chart-update", "--gyro-noise", "0.02",
                              "--mag-reference", "0", "1", "-1"])
    assert filter_overrides(args) == {"chart": "mrp", "chart_update": False,
                                      "gyro_noise": 0.02, "mag_reference": [0.0, 1.0, -1.0]}
    with pytest.raises(SystemExit):
        parser.parse_args(["--chart", "euler"])


# --- coercion and the unknown-keyword message ---------------------------------------------------

def test_numpy_booleans_are_booleans() -> None:
    import numpy as np

    assert FilterParams(use_mag=np.True_).use_mag is True
    assert FilterParams(chart_update=np.False_).chart_update is False


@pytest.mark.parametrize(("kw", "message"), [
    ({"gravity": True}, "gravity must be a number, got True"),
    ({"acc_noise": False}, "acc_noise must be a number, got False"),
    ({"mag_reference": "123"}, "mag_reference must be a list of numbers, got '123'"),
    ({"mag_reference": [True, 0.0, 0.0]}, "mag_reference must be a list of numbers"),
])
def test_a_boolean_or_a_string_is_not_a_number(kw: dict, message: str) -> None:
    with pytest.raises(ValueError, match=f"^{message}"):
        FilterParams(**kw)


def test_unknown_keyword_is_one_short_line_with_a_suggestion() -> None:
    with pytest.raises(ValueError) as e:
        FilterParams(gyro_nosie=0.1)
    msg = str(e.value)
    assert "\n" not in msg and len(msg) <= 200
    assert msg.startswith("unknown filter parameter 'gyro_nosie' (did you mean 'gyro_noise'")
    with pytest.raises(ValueError, match=r"^unknown filter parameter 'turbo'; ") as e:
        FilterParams(turbo=1)
    assert len(str(e.value)) <= 200


@pytest.mark.parametrize("name, level", [("acc_gate", "16.3"), ("mag_gate", "10.8"),
                                         ("gyro_gate", "10000"), ("acc_recovery_time", "1 s"),
                                         ("mag_recovery_time", "10 s"),
                                         ("rest_bias_range", "0.05 rad/s"),
                                         ("acc_norm_tolerance", "0.5 g off gravity")])
def test_a_removed_parameter_is_refused_with_the_level_that_replaced_it(name: str,
                                                                        level: str) -> None:
    """A script or parameter file written for the version that had them is told what
    happened, in one line, not "unknown"; the level is the one docs/math.md §9.3–9.4 states."""
    with pytest.raises(ValueError, match=f"^filter parameter '{name}' was removed: a fixed") as e:
        FilterParams(**{name: 1.0})
    assert level in str(e.value) and "\n" not in str(e.value)


def test_rules_between_parameters_are_the_parameters_own() -> None:
    """A combination the filter cannot run is refused where the parameters are made (the node's
    SetParameters, ``mkf`` flags and ``estimate()`` all build FilterParams), not later."""
    with pytest.raises(ValueError, match="mag_soft_iron must be an invertible 3x3 matrix"):
        FilterParams(mag_soft_iron=[1, 0, 0, 0, 1, 0, 0, 0, 0])
    with pytest.raises(ValueError, match="init_mode 'paper' with use_mag needs mag_reference"):
        FilterParams(init_mode="paper", use_mag=True)
    ok = FilterParams(init_mode="paper", use_mag=True, mag_reference=[0.0, 0.4, -0.9])
    with pytest.raises(ValueError, match="needs mag_reference"):
        ok.replace(mag_reference=[0.0, 0.0, 0.0])
