"""``mkf synth``: a synthetic IMU + magnetometer recording with ground truth, as a ROS 2 bag."""

from __future__ import annotations

import argparse
from typing import Any

HELP = "write a synthetic IMU/magnetometer bag with ground truth (imu/ground_truth)"


def _scenarios() -> dict[str, Any]:
    from mkf_ros.sim import SCENARIOS

    return SCENARIOS


def add_sim_arguments(parser: argparse.ArgumentParser, *, duration: float = 60.0) -> None:
    """Simulation options shared by ``synth`` and ``demo``."""
    g = parser.add_argument_group("simulation")
    g.add_argument("--duration", type=float, default=duration, metavar="S",
                   help=f"seconds (default {duration:g})")
    g.add_argument("--rate", type=float, default=200.0, metavar="HZ",
                   help="IMU rate (default 200)")
    g.add_argument("--mag-rate", type=float, default=50.0, metavar="HZ",
                   help="magnetometer rate (default 50)")
    g.add_argument("--seed", type=int, default=0)
    g.add_argument("--gyro-noise", type=float, default=0.01, metavar="RAD_S",
                   help="gyro white noise per sample (default 0.01)")
    g.add_argument("--acc-noise", type=float, default=0.05, metavar="M_S2",
                   help="accelerometer white noise per sample (default 0.05)")
    g.add_argument("--mag-noise", type=float, default=0.5e-6, metavar="T",
                   help="magnetometer white noise per sample (default 5e-7)")
    g.add_argument("--gyro-bias", type=float, nargs=3, default=(0.0, 0.0, 0.0),
                   metavar=("X", "Y", "Z"), help="constant gyro bias, rad/s")
    g.add_argument("--mag-field", type=float, nargs=3, default=None, metavar=("E", "N", "U"),
                   help="Earth field in ENU, tesla (default 50 µT, dip 60°)")
    g.add_argument("--param", action="append", default=[], metavar="NAME=VALUE",
                   help="a scenario parameter (see --list), e.g. --param acc_peak=2")


def parse_scenario_params(items: list[str]) -> dict[str, Any]:
    """``NAME=VALUE`` items → keywords; comma-separated values become tuples of floats."""
    from mkf_ros.cli.main import CliError

    out: dict[str, Any] = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name.strip():
            raise CliError(f"--param needs NAME=VALUE, got {item!r}")
        try:
            vals = tuple(float(v) for v in value.split(","))
        except ValueError:
            raise CliError(f"--param {name}: {value!r} is not a number (or a comma list)") \
                from None
        out[name.strip()] = vals[0] if len(vals) == 1 else vals
    return out


def simulate_from_args(args: argparse.Namespace, *, stream: bool = False) -> Any:
    """Run the simulator with the options of :func:`add_sim_arguments` (CliError if bad):
    the whole recording, or with ``stream`` a :class:`~mkf_ros.sim.SimStream` that generates
    it chunk by chunk (bounded memory)."""
    import numpy as np

    from mkf_ros.cli.main import CliError
    from mkf_ros.sim import MAG_FIELD_ENU, SimStream, simulate

    kw = parse_scenario_params(args.param)
    if args.mag_rate is not None and args.mag_rate <= 0:
        raise CliError("--mag-rate must be positive")
    for name in ("duration", "rate"):
        if not getattr(args, name) > 0:
            raise CliError(f"--{name} must be positive")
    if args.duration * args.rate > 5e7:
        raise CliError("--duration × --rate is over 50 million samples; make it shorter")
    try:
        make = SimStream if stream else simulate
        return make(args.scenario, duration=args.duration, rate=args.rate, seed=args.seed,
                    gyro_noise=args.gyro_noise, acc_noise=args.acc_noise,
                    mag_noise=args.mag_noise, gyro_bias=tuple(args.gyro_bias),
                    mag_field=MAG_FIELD_ENU if args.mag_field is None
                    else np.asarray(args.mag_field, float),
                    mag_rate=min(args.mag_rate, args.rate), **kw)
    except ValueError as e:
        raise CliError(str(e)) from None


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("scenario", nargs="?", metavar="SCENARIO",
                        help="motion scenario (mkf synth --list)")
    parser.add_argument("--list", action="store_true", help="list the scenarios and exit")
    parser.add_argument("--out", metavar="BAG", help="output bag (a directory)")
    parser.add_argument("--storage", default="mcap", metavar="{mcap,sqlite3}",
                        help="rosbag2 storage (default mcap, as Jazzy records)")
    parser.add_argument("--compress", action="store_true", help="zstd-compressed MCAP chunks")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing bag")
    parser.add_argument("--split-accel", type=int, default=0, metavar="K",
                        help="write separate accelerometer (imu/accel, every K-th sample) and "
                        "gyroscope (imu/gyro) topics instead of imu/data_raw, as a RealSense "
                        "publishes them (mkf process --accel-topic imu/accel --gyro-topic "
                        "imu/gyro); default 0: one combined topic")
    parser.add_argument("--frame-id", default="imu_link", help="header.frame_id (imu_link)")
    parser.add_argument("--start", type=float, default=1_704_067_200.0, metavar="UNIX_S",
                        help="stamp of the first sample (default 2024-01-01T00:00:00Z)")
    add_sim_arguments(parser)


def run(args: argparse.Namespace) -> int:
    from mkf_ros.cli.main import CliError

    scenarios = _scenarios()
    if args.list:
        for name, sc in scenarios.items():
            params = ", ".join(f"{k}={v}" for k, v in sc.params.items())
            print(f"{name:<16} {sc.description}" + (f"  [{params}]" if params else ""))
        return 0
    if not args.scenario:
        raise CliError("give a SCENARIO (mkf synth --list shows them)")
    if args.scenario not in scenarios:
        raise CliError(f"unknown scenario {args.scenario!r}; known: {', '.join(scenarios)}")
    if args.split_accel < 0:
        raise CliError(f"--split-accel must be >= 0, got {args.split_accel}")
    if not args.out:
        raise CliError("give the output bag with --out BAG")
    from mkf_ros.bags import BagError
    from mkf_ros.bags.synth import write_bag

    sim = simulate_from_args(args, stream=True)  # written chunk by chunk: bounded memory
    try:
        counts = write_bag(sim, args.out, args.storage, start_ns=round(args.start * 1e9),
                           frame_id=args.frame_id, overwrite=args.overwrite,
                           compress=args.compress, split_accel=args.split_accel)
    except BagError as e:
        raise CliError(str(e)) from None
    print(f"wrote {args.out} ({args.storage}): scenario {args.scenario}, "
          f"{args.duration:g} s at {args.rate:g} Hz, seed {args.seed}")
    for topic, n in counts.items():
        print(f"  {topic:<22} {n:>9,} messages")
    ivs = sim.meta.get("intervals", {})
    if ivs:
        print("  truth intervals: " + ", ".join(f"{k} ×{len(v)}" for k, v in ivs.items()))
    return 0
