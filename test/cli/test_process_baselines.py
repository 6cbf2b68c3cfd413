"""``mkf process --algorithm`` runs the seed report's baselines (docs/baselines.md) like the MKFs,
and a bad choice is one clear line."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mkf_ros.bags.synth import write_bag
from mkf_ros.cli.main import main
from mkf_ros.sim import simulate


@pytest.mark.parametrize("algorithm", ["euler_kf", "euler_ukf", "madgwick"])
def test_process_runs_a_baseline(tmp_path: Path, algorithm: str,
                                 capsys: pytest.CaptureFixture) -> None:
    """9D synthetic bag (magnetometer 25 Hz): the printed RMSE is at the sensor-noise level
    (one accelerometer sample: 0.3° of tilt; one magnetometer sample: 1.1° of heading)."""
    sim = simulate("slow_rotation", duration=8.0, rate=100.0, mag_rate=25.0, seed=2)
    write_bag(sim, tmp_path / "in", "mcap")
    assert main(["process", str(tmp_path / "in"), "--out", str(tmp_path / "out"), "--use-mag",
                 "--algorithm", algorithm, "--no-plot"]) == 0
    text = capsys.readouterr().out
    assert f"filter  {algorithm}-" in text
    m = re.search(r"total\s+([\d.]+)\s+heading\s+([\d.]+)\s+inclination\s+([\d.]+)", text)
    assert m, text
    total, _, incl = map(float, m.groups())
    assert total < 1.5 and incl < 1.0, text


def test_process_bad_algorithm(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    sim = simulate("static", duration=1.0, rate=100.0, seed=2)
    write_bag(sim, tmp_path / "in", "mcap")
    assert main(["process", str(tmp_path / "in"), "--out", str(tmp_path / "out"),
                 "--algorithm", "euler"]) == 2
    err = capsys.readouterr().err
    assert "euler_kf" in err and "madgwick" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1  # not after the usage of every flag
