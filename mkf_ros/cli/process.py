"""``mkf process``: the estimator over a bag, without DDS; accuracy and plots against the truth.

Several bags (or a folder of bags) are processed in parallel by :mod:`mkf_ros.cli.process_batch`.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from mkf_ros.core.params import Param

HELP = "run the estimator over a bag (no DDS), write imu/data, score against ground truth"

#: bags with at least this many messages get progress bars (on a terminal)
PROGRESS_MIN = 100_000


def _stream_params() -> list[Param]:
    """The parameters ``mkf process`` takes as flags
    (:func:`~mkf_ros.bags.process.stream_param_names`)."""
    from mkf_ros.bags.process import stream_param_names
    from mkf_ros.core.params import BY_NAME

    return [BY_NAME[n] for n in stream_param_names()]


class Once(argparse.Action):
    """A flag that takes one value and may be given once: a repeated ``--imu-topic`` is an
    error, not a silent choice of the last."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: Any, option_string: str | None = None) -> None:
        old = getattr(namespace, self.dest, None)
        if old is not None:
            hint = (" (separate accelerometer and gyroscope topics: --accel-topic and "
                    "--gyro-topic)" if self.dest == "imu_topic" else "")
            parser.error(f"{option_string} given twice ({old}, {values}); it takes one "
                         f"topic{hint}")
        setattr(namespace, self.dest, values)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mkf_ros.cli.options import add_param_flags
    from mkf_ros.core.params import SMOOTH_MODES

    parser.add_argument("bags", nargs="+", metavar="BAG", help="input bag: rosbag2 directory, "
                        ".mcap, .db3 or ROS 1 .bag; several bags or a folder of bags are "
                        "processed in parallel into the folder --out")
    parser.add_argument("--out", required=True, metavar="OUT_BAG",
                        help="output bag (new); with several bags the output folder (one bag "
                             "and plot per input, summary.csv)")
    parser.add_argument("--storage", default="mcap", metavar="{mcap,sqlite3}",
                        help="output storage (default mcap)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing OUT_BAG")
    parser.add_argument("--imu-topic", action=Once, metavar="TOPIC",
                        help="sensor_msgs/Imu topic, gyro and accelerometer in each message "
                        "(default: the bag's only Imu topic, or imu/data_raw among several)")
    parser.add_argument("--accel-topic", action=Once, metavar="TOPIC",
                        help="split input (with --gyro-topic): the accelerometer's "
                        "sensor_msgs/Imu topic (RealSense: camera/accel/sample)")
    parser.add_argument("--gyro-topic", action=Once, metavar="TOPIC",
                        help="split input (with --accel-topic): the gyroscope's "
                        "sensor_msgs/Imu topic (RealSense: camera/gyro/sample); the output "
                        "has one message per gyro message")
    parser.add_argument("--mag-topic", action=Once, metavar="TOPIC",
                        help="sensor_msgs/MagneticField topic, with --use-mag (default: the "
                        "bag's only one, or imu/mag among several)")
    parser.add_argument("--truth-topic", default="imu/ground_truth", metavar="TOPIC",
                        help="geometry_msgs/QuaternionStamped, sensor → ENU (scored if present)")
    parser.add_argument("--output-topic", default="imu/data", metavar="TOPIC")
    parser.add_argument("--copy-input", action="store_true",
                        help="also copy every input topic into OUT_BAG")
    parser.add_argument("--plot", metavar="PNG", help="plot file (default: OUT_BAG.png)")
    parser.add_argument("--no-plot", action="store_true", help="write no plot")
    parser.add_argument("--skip", type=float, default=0.0, metavar="S",
                        help="leave the first S seconds out of the scores (default 0)")
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    sm = parser.add_argument_group("smoothing (offline: the future is known)")
    sm.add_argument("--smooth", nargs="?", const="rts", default=False,
                    choices=SMOOTH_MODES,
                    help="write the fixed-interval manifold smoother's orientation and "
                    "orientation_covariance (docs/math.md §11; algorithm mekf or mukf) instead "
                    "of the causal filter's; the other fields as without it. rts (the default, "
                    "--smooth alone) or two-way: its tilt fused with the same smoother's over the "
                    "recording reversed (§11.5; more accurate, about twice the time, the bag "
                    "read twice, about 0.2 KB per step in temporary files beside the output). "
                    "Memory is bounded: messages are written once smoothed, at most one "
                    "smoothing window + overlap (+ a read window) behind")
    sm.add_argument("--smooth-window", type=int, default=None, metavar="N",
                    help="with --smooth: filter steps per smoothing window (default 131072)")
    sm.add_argument("--smooth-overlap", type=int, default=None, metavar="N",
                    help="with --smooth: steps smoothed past each window and dropped "
                    "(default: 60 s at the IMU topic's mean rate, at most 131072)")
    b = parser.add_argument_group("several bags")
    b.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="bags processed at once on this machine (default: number of cores)")
    b.add_argument("--scheduler", metavar="ADDRESS", default=None,
                   help="process the bags on the Dask cluster of this scheduler "
                        "(tcp://HOST:8786; paths must be the same on every worker, "
                        "docs/bags.md)")
    parser.add_argument("--params", metavar="PARAMS_YAML", default=None,
                        help="a ROS parameters file (as for estimator --ros-args --params-file, "
                        "e.g. from mkf calibrate-mag); flags given here take precedence")
    add_param_flags(parser, _stream_params(), "estimator parameters (as the node's)")


def read_params_file(path: str) -> dict[str, Any]:
    """The parameters of a ROS parameters file (``NODE: {ros__parameters: {...}}``, every
    node's entry merged in file order) that ``mkf process`` applies; node-only parameters
    without an offline meaning (TF, diagnostics) are skipped. CliError (one line) for a file
    that cannot be read or parsed, or an unknown parameter name."""
    import yaml

    from mkf_ros.cli.main import CliError
    from mkf_ros.core.params import BY_NAME, unknown_parameter

    try:
        doc = yaml.safe_load(Path(path).read_text())
    except OSError as e:
        raise CliError(f"--params {path}: {e.strerror or e}") from None
    except yaml.YAMLError as e:
        raise CliError(f"--params {path}: not valid YAML ({' '.join(str(e).split())})") from None
    sections = [v["ros__parameters"] for v in (doc.values() if isinstance(doc, dict) else [])
                if isinstance(v, dict) and isinstance(v.get("ros__parameters"), dict)]
    if not sections:
        raise CliError(f"--params {path}: no 'NODE: ros__parameters:' mapping (a ROS parameters "
                       "file, as written by mkf calibrate-mag or mkf params)")
    offline = {p.name for p in _stream_params()}
    out: dict[str, Any] = {}
    for sec in sections:
        for name, value in sec.items():
            if name not in BY_NAME:
                raise CliError(f"--params {path}: {unknown_parameter(name, BY_NAME)}")
            if name in offline:
                out[name] = value
    return out


def _overrides(args: argparse.Namespace) -> dict[str, Any]:
    """The estimator parameters of ``--params FILE``, then those set by flags."""
    from mkf_ros.cli.options import param_overrides

    base = read_params_file(args.params) if getattr(args, "params", None) else {}
    return {**base, **param_overrides(args, _stream_params())}


class _Bars:
    """tqdm progress bars on stderr, only for long bags on a terminal."""

    def __init__(self, enabled: bool) -> None:
        self.enabled = enabled
        self.bars: list[Any] = []

    def __call__(self, desc: str, total: int) -> Callable[[int], object] | None:
        if not self.enabled:
            return None
        from tqdm import tqdm

        self.close()
        bar = tqdm(total=total, desc=f"{desc:<6}", leave=False, file=sys.stderr,
                   unit_scale=True, dynamic_ncols=True, mininterval=0.2)
        self.bars.append(bar)
        return bar.update

    def close(self) -> None:
        for b in self.bars:
            b.close()
        self.bars.clear()


@contextlib.contextmanager
def _bars(enabled: bool) -> Iterator[_Bars]:
    b = _Bars(enabled)
    try:
        yield b
    finally:
        b.close()


def _count_messages(bag: str) -> int:
    from mkf_ros.bags import BagReader

    with contextlib.suppress(Exception), BagReader(bag) as br:
        return br.message_count
    return 0


def default_plot_path(out: str | Path) -> Path:
    return Path(str(out).rstrip("/") + ".png")


def check_smooth(args: argparse.Namespace) -> None:
    """CliError (one line) for smoothing options without ``--smooth`` or out of range."""
    from mkf_ros.cli.main import CliError

    for flag in ("smooth_window", "smooth_overlap"):
        v = getattr(args, flag, None)
        name = "--" + flag.replace("_", "-")
        if v is not None and not args.smooth:
            raise CliError(f"{name} needs --smooth")
        if v is not None and v < (1 if flag == "smooth_window" else 0):
            raise CliError(f"{name} must be at least {1 if flag == 'smooth_window' else 0}, "
                           f"got {v}")


def run(args: argparse.Namespace) -> int:
    from mkf_ros.bags import BagError
    from mkf_ros.bags.process import process_bag
    from mkf_ros.cli import process_batch
    from mkf_ros.cli.main import CliError

    check_smooth(args)
    if process_batch.wanted(args):
        return process_batch.run(args, _overrides(args))
    args.bag = args.bags[0]
    if args.storage not in ("mcap", "sqlite3"):
        raise CliError(f"unknown storage {args.storage!r} (choose from mcap, sqlite3)")
    out = Path(args.out)
    if Path(args.bag).resolve() == out.resolve():
        raise CliError("--out must differ from the input bag")
    if out.exists() and not args.overwrite:
        raise CliError(f"{out} already exists (use --overwrite to replace it)")
    show = not args.quiet and sys.stderr.isatty() and _count_messages(args.bag) >= PROGRESS_MIN
    try:
        with _bars(show) as bars:
            r = process_bag(args.bag, out, _overrides(args), imu_topic=args.imu_topic,
                            mag_topic=args.mag_topic, accel_topic=args.accel_topic,
                            gyro_topic=args.gyro_topic, truth_topic=args.truth_topic,
                            output_topic=args.output_topic, storage=args.storage,
                            overwrite=args.overwrite, copy_input=args.copy_input,
                            skip=args.skip, progress=bars, smooth=args.smooth,
                            smooth_window=args.smooth_window,
                            smooth_overlap=args.smooth_overlap)
    except BagError as e:
        raise CliError(str(e)) from None
    except ValueError as e:  # an invalid parameter value
        raise CliError(str(e)) from None
    report(r, args)
    return 0


def report(r: Any, args: argparse.Namespace) -> None:
    """Print what was done and how accurate it was."""
    p = r.params
    print(f"{args.bag} → {r.out} ({args.storage})")
    mag = (f", {r.mag_topic} {r.n_mag:,} (fused)" if r.mag_topic else ", no magnetometer")
    if r.accel_topic:
        print(f"  input   split: gyro {r.imu_topic} {r.n_imu:,}, accelerometer "
              f"{r.accel_topic} {r.n_accel:,}{mag}")
    else:
        print(f"  input   {r.imu_topic} {r.n_imu:,}{mag}")
    smoothed = (", smoothed both ways (two-way smoother)" if "two-way" in r.timings else
                ", smoothed (fixed-interval smoother)" if "smooth" in r.timings else "")
    print(f"  filter  {p['algorithm']}-{p['chart']}, world_frame {p['world_frame']}, "
          f"use_mag {str(p['use_mag']).lower()}{smoothed}")
    from mkf_ros.bags import normalize_topic

    print(f"  output  {normalize_topic(args.output_topic)} {r.n_out:,} messages")
    from mkf_ros.bags.batch import events

    rej = events(r.counters)
    if rej:
        print("  events  " + ", ".join(f"{k} {v}" for k, v in rej.items()))
    for note in r.notes:
        print(f"  note    {note}")
    s = r.scores
    if s is not None:
        n = s.n
        extra = f", first {args.skip:g} s left out" if args.skip else ""
        print(f"  accuracy against {args.truth_topic} ({n:,} samples{extra}), RMSE in degrees:")
        print(f"          total {s.rmse['total']:7.3f}   heading {s.rmse['heading']:7.3f}   "
              f"inclination {s.rmse['inclination']:7.3f}")
        if s.heading_aligned:
            print("          (no magnetometer: heading aligned to the truth once, at the start)")
        for kind, w in s.windows.items():
            print(f"          during {kind:<14} total {w['total']:7.3f}   heading "
                  f"{w['heading']:7.3f}   inclination {w['inclination']:7.3f}")
        if not args.no_plot:
            from mkf_ros.bags.batch import plot_result

            path = Path(args.plot) if args.plot else default_plot_path(r.out)
            plot_result(r, args.bag, path)
            print(f"  plot    {path}")
    tm = r.timings
    total = sum(tm.values())
    smooth = f", smooth {tm['smooth']:.2f}" if "smooth" in tm else ""
    if "two-way" in tm:  # the first pass and the reversed smoother
        smooth += f", first pass and reversed smoother {tm['two-way']:.2f}"
    print(f"  time    {total:.2f} s: read {tm['read']:.2f}, filter {tm['filter']:.2f} "
          f"({r.n_imu / max(tm['filter'], 1e-9):,.0f} IMU msgs/s){smooth}, write "
          f"{tm['write']:.2f}")
