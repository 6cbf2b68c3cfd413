"""``mkf demo``: the core filters on a synthesised stream with ground truth, accuracy printed."""

from __future__ import annotations

import argparse
import time

import numpy as np

from mkf_ros.cli.options import add_filter_options, filter_overrides

HELP = "run the filters on a synthesised IMU stream and print their accuracy against the truth"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--scenario", default="slow_rotation")
    parser.add_argument("--duration", type=float, default=60.0, help="seconds (default 60)")
    parser.add_argument("--rate", type=float, default=200.0, help="IMU rate, Hz (default 200)")
    parser.add_argument("--seed", type=int, default=0)
    add_filter_options(parser)


def run(args: argparse.Namespace) -> int:
    from mkf_ros.api import estimate
    from mkf_ros.cli.main import CliError
    from mkf_ros.metrics import orientation_errors
    from mkf_ros.sim import simulate

    try:
        sim = simulate(args.scenario, duration=args.duration, rate=args.rate, seed=args.seed)
    except ValueError as e:
        raise CliError(str(e)) from None
    base = filter_overrides(args)
    print(f"scenario {args.scenario}: {args.duration:g} s at {args.rate:g} Hz, magnetometer on, "
          "errors after the first second (RMSE, degrees)")
    print(f"{'filter':<22}{'total':>8}{'heading':>9}{'inclin.':>9}{'samples/s':>12}")
    for algo in ("mekf", "mukf"):
        for chart in ("o", "rp", "mrp", "rv"):
            p = dict(algorithm=algo, chart=chart) | base
            try:
                t0 = time.perf_counter()
                res = estimate(sim.gyr, sim.acc, sim.mag, timestamps=sim.t, **p)
                el = time.perf_counter() - t0
            except ValueError as e:
                raise CliError(str(e)) from None
            err = orientation_errors(res.quat, sim.quat)
            skip = sim.t >= sim.t[0] + 1.0
            rms = {k: float(np.sqrt(np.mean(np.degrees(v[skip]) ** 2))) for k, v in err.items()}
            name = f"{p['algorithm']}-{p['chart']}"
            print(f"{name:<22}{rms['total']:>8.3f}{rms['heading']:>9.3f}"
                  f"{rms['inclination']:>9.3f}{len(sim.t) / el:>12,.0f}")
    return 0
