"""``mkf calibrate-mag``: the magnetometer's hard- and soft-iron calibration from a bag
(docs/math.md §10.1), written as a parameters file for the estimator.

The output is a ROS parameters file (``estimator --ros-args --params-file FILE``, and
``mkf process --params FILE``) holding ``mag_bias_x/y/z`` and ``mag_soft_iron``.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    import numpy as np

    from mkf_ros.core.magcal import MagCalibration

HELP = "fit the magnetometer's hard- and soft-iron calibration from a bag (params YAML, plot)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from mkf_ros.core.magcal import MIN_COVERAGE

    parser.add_argument("bag", metavar="BAG", help="input bag: rosbag2 directory, .mcap, .db3 "
                        "or ROS 1 .bag, recorded while the sensor was turned in every direction")
    parser.add_argument("--mag-topic", metavar="TOPIC", help="sensor_msgs/MagneticField topic "
                        "(default: the bag's only one, or imu/mag among several)")
    parser.add_argument("--out", metavar="PARAMS_YAML", help="write the parameters file here "
                        "(default: print it)")
    parser.add_argument("--overwrite", action="store_true", help="replace an existing --out")
    parser.add_argument("--plot", metavar="FILE", help="plot raw and calibrated samples (PNG, "
                        "PDF, SVG)")
    parser.add_argument("--start", type=float, default=0.0, metavar="S",
                        help="use samples from S seconds after the first one (default 0)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="use S seconds of samples (default: all)")
    parser.add_argument("--min-coverage", type=float, default=MIN_COVERAGE, metavar="F",
                        help="refuse a fit whose calibrated directions cover less than this "
                        f"fraction of the sphere (default {MIN_COVERAGE})")
    parser.add_argument("--field-magnitude", type=float, default=None, metavar="B",
                        help="scale the calibrated field to this magnitude, in the topic's "
                        "unit (T for ROS); default: keep the sensor's scale (det S = 1)")
    parser.add_argument("--hard-iron-only", action="store_true",
                        help="fit the offset only (soft iron = identity): for a magnet on the "
                        "body, or when the recording covers only part of the sphere")
    parser.add_argument("--no-refine", action="store_true",
                        help="algebraic fit only (no geometric refinement)")
    parser.add_argument("--node-name", default="/**",
                        help="top-level key of the parameters file (default /**: any node)")


def read_mag(bag: str, topic: str | None) -> tuple[str, np.ndarray, np.ndarray]:
    """``(topic, stamps_s, fields)`` of the bag's magnetometer topic (BagError if none)."""
    import numpy as np

    from mkf_ros.bags import BagError, BagReader, cdr

    with BagReader(bag) as br:
        name = (br.resolve(topic, cdr.MAGNETIC_FIELD.msgtype, role="magnetometer")
                if topic is not None else
                br.discover(cdr.MAGNETIC_FIELD.msgtype, role="magnetometer",
                            flag="--mag-topic", preferred="imu/mag"))
        batch = br.read([name])[name]
    if len(batch) == 0:
        raise BagError(f"magnetometer topic {name} in {bag} has no messages")
    try:
        dec = cdr.decode(batch.data, cdr.MAGNETIC_FIELD, name)
    except cdr.CdrError as e:
        raise BagError(f"{bag}: {e}") from None
    return name, dec.stamp_ns.astype(np.float64) * 1e-9, dec.fields["magnetic_field"]


def plot(cal: MagCalibration, raw: np.ndarray, path: str, title: str) -> None:
    """Raw and calibrated samples in the three coordinate planes, with the calibrated sphere's
    outline: raw samples on an off-centre ellipse, calibrated ones on the circle."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import numpy as np

    from mkf_ros.files import atomic_path

    done = cal.apply(raw)
    r = cal.field_magnitude
    fig, axes = plt.subplots(1, 3, figsize=(13, 4.6))
    t = np.linspace(0, 2 * np.pi, 200)
    for ax, (i, j) in zip(axes, ((0, 1), (0, 2), (1, 2)), strict=True):
        ax.plot(raw[:, i], raw[:, j], ".", ms=1.5, alpha=0.5, label="raw")
        ax.plot(done[:, i], done[:, j], ".", ms=1.5, alpha=0.5, label="calibrated")
        ax.plot(r * np.cos(t), r * np.sin(t), "k-", lw=0.8, label=f"|m| = {r:.3g}")
        ax.plot(*cal.offset[[i, j]], "r+", ms=12, label="hard-iron offset")
        ax.set_xlabel("xyz"[i])
        ax.set_ylabel("xyz"[j])
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="best", fontsize=8, markerscale=4)
    fig.suptitle(f"{title}: RMS residual {100 * cal.rms_relative:.2f} % of the field, coverage "
                 f"{100 * cal.coverage:.0f} %", fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from mkf_ros.bags import BagError
    from mkf_ros.cli.main import CliError
    from mkf_ros.core.magcal import fit_ellipsoid, params_yaml
    from mkf_ros.files import write_text

    if args.out and Path(args.out).exists() and not args.overwrite:
        raise CliError(f"{args.out} already exists (use --overwrite to replace it)")
    if args.start < 0 or (args.duration is not None and not args.duration > 0):
        raise CliError("--start must be ≥ 0 and --duration > 0 (seconds)")
    if not 0.0 <= args.min_coverage <= 1.0:
        raise CliError(f"--min-coverage must be in [0, 1], got {args.min_coverage}")
    try:
        topic, t, m = read_mag(args.bag, args.mag_topic)
    except BagError as e:
        raise CliError(str(e)) from None
    t0 = t.min() + args.start
    keep = t >= t0
    if args.duration is not None:
        keep &= t < t0 + args.duration
    raw = m[keep]
    try:
        cal = fit_ellipsoid(raw, refine=not args.no_refine, min_coverage=args.min_coverage,
                            field_magnitude=args.field_magnitude,
                            soft_iron=not args.hard_iron_only)
    except ValueError as e:
        raise CliError(f"{topic}: {e}") from None
    print(f"{args.bag}: {topic}, {int(keep.sum())} of {len(m)} messages")
    print(cal.summary())
    text = params_yaml(cal, args.node_name)
    if args.out:
        write_text(args.out, text)
        print(f"parameters written to {args.out} (estimator --ros-args --params-file "
              f"{args.out}; mkf process --params {args.out})")
    else:
        print(text, end="")
    if args.plot:
        plot(cal, raw[np.all(np.isfinite(raw), axis=1)], args.plot, f"{Path(args.bag).name} "
             f"{topic}")
        print(f"plot written to {args.plot}")
    return 0
