"""``mkf calibrate-mag`` on a bag with a known hard- and soft-iron distortion: the parameters
file it writes recovers the distortion, is accepted by ``mkf process --params`` and improves the
heading there; poor coverage and bad input are refused with one line."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
import yaml

from mkf_ros.bags.process import process_bag
from mkf_ros.bags.synth import write_bag
from mkf_ros.cli.main import main
from mkf_ros.sim import simulate

A_TRUE = np.array([[1.10, 0.05, -0.03], [0.05, 0.92, 0.06], [-0.03, 0.06, 1.04]])
H_TRUE = np.array([25e-6, -30e-6, 15e-6])  # T: an offset of about the Earth field's size


def _bag(tmp_path: Path, scenario: str, name: str, **kw: object) -> tuple[Path, float]:
    sim = simulate(scenario, duration=60, rate=50, seed=4, **kw)  # type: ignore[arg-type]
    field = float(np.nanmedian(np.linalg.norm(sim.mag, axis=1)))
    sim = dataclasses.replace(sim, mag=sim.mag @ A_TRUE.T + H_TRUE)  # NaN rows stay NaN
    path = tmp_path / name
    write_bag(sim, path)
    return path, field


def test_calibration_file_recovers_the_distortion_and_fixes_the_heading(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag, field = _bag(tmp_path, "slow_rotation", "rot.mcap")
    out, png = tmp_path / "mag.yaml", tmp_path / "mag.png"
    assert main(["calibrate-mag", str(bag), "--out", str(out), "--plot", str(png)]) == 0
    text = capsys.readouterr().out
    assert "coverage" in text and "RMS" in text
    values = yaml.safe_load(out.read_text())["/**"]["ros__parameters"]
    h = np.array([values["mag_bias_x"], values["mag_bias_y"], values["mag_bias_z"]])
    assert np.max(np.abs(h - H_TRUE)) < 0.01 * field
    SA = np.reshape(values["mag_soft_iron"], (3, 3)) @ A_TRUE
    np.testing.assert_allclose(SA / np.cbrt(np.linalg.det(SA)), np.eye(3), atol=0.01)
    assert png.is_file() and png.stat().st_size > 10_000

    # the file through mkf process --params: the distorted field misleads the heading without it
    def heading_rmse(*extra: str) -> float:
        dest = tmp_path / f"out{len(extra)}.mcap"
        assert main(["process", str(bag), "--out", str(dest), "--no-plot", "--use-mag",
                     *extra]) == 0
        return float(capsys.readouterr().out.split("heading")[1].split()[0].strip(":°,"))

    raw_err, cal_err = heading_rmse(), heading_rmse("--params", str(out))
    assert cal_err < 2.0 < raw_err, (raw_err, cal_err)


def test_process_params_file_equals_the_flags(tmp_path: Path) -> None:
    """``--params FILE`` applies the same values as the flags (and flags override it)."""
    bag, _ = _bag(tmp_path, "slow_rotation", "p.mcap")
    params = tmp_path / "p.yaml"
    params.write_text("/**:\n  ros__parameters:\n    use_mag: true\n    mag_bias_x: 2.5e-05\n"
                      "    publish_tf: true\n")
    a = process_bag(bag, tmp_path / "a.mcap", {"use_mag": True, "mag_bias_x": 2.5e-5})
    from mkf_ros.cli.process import read_params_file

    b = process_bag(bag, tmp_path / "b.mcap", read_params_file(str(params)))
    assert a.scores is not None and b.scores is not None
    np.testing.assert_array_equal(a.scores.q_est, b.scores.q_est)


def test_one_axis_turn_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag, _ = _bag(tmp_path, "slow_turn", "turn.mcap", rest=1.0)
    out = tmp_path / "never.yaml"
    assert main(["calibrate-mag", str(bag), "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "cover" in err and "sphere" in err and len(err.splitlines()) == 1
    assert not out.exists()


@pytest.mark.parametrize("args, match", [
    (["--mag-topic", "nope/mag"], "nope/mag"),
    (["--min-coverage", "2"], "--min-coverage"),
    (["--duration", "0.2"], "at least 20 finite samples"),
])
def test_bad_arguments_are_one_line_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           args: list[str], match: str) -> None:
    bag, _ = _bag(tmp_path, "slow_rotation", "b.mcap")
    assert main(["calibrate-mag", str(bag), *args]) == 2
    err = capsys.readouterr().err.strip()
    assert match in err and len(err.splitlines()) == 1, err


def test_process_params_file_errors(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bag, _ = _bag(tmp_path, "slow_rotation", "e.mcap")
    bad = tmp_path / "bad.yaml"
    bad.write_text("/**:\n  ros__parameters:\n    mag_bias_q: 1.0\n")
    assert main(["process", str(bag), "--out", str(tmp_path / "o.mcap"), "--params",
                 str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert "mag_bias_q" in err and len(err.splitlines()) == 1
    assert main(["process", str(bag), "--out", str(tmp_path / "o.mcap"), "--params",
                 str(tmp_path / "missing.yaml")]) == 2
    assert "missing.yaml" in capsys.readouterr().err
