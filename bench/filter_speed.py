"""Filter speed on this machine, the analogue of the paper's Fig. 4 (docs/math.md §7.4).

Updates per second of every filter × chart × chart update (nx = 6, one vector sensor + gyro per
update, through the core kernels) and the MEKF/MUKF ratio (the paper: about 3×).

    ./run bench filter_speed [--updates N] [--repeats K] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import platform
import sys
from pathlib import Path


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--updates", type=int, default=20000, help="updates per repetition")
    p.add_argument("--repeats", type=int, default=7, help="repetitions per variant")
    p.add_argument("--both-scalings", action="store_true",
                   help="also time the MUKF with the consistent Q_ω·Δt scaling")
    p.add_argument("--json", type=Path, default=None, help="also write the results as JSON")
    a = p.parse_args(argv)
    if a.updates < 100 or a.repeats < 2:
        print("filter_speed: need --updates >= 100 and --repeats >= 2", file=sys.stderr)
        return 2
    from mkf_ros.study.speed import format_table, measure_speeds, mekf_mukf_ratio

    scal = ("published", "consistent") if a.both_scalings else ("published",)
    speeds = measure_speeds(a.updates, a.repeats, scalings=scal)
    print(f"# filter speed on {platform.processor() or platform.machine()}, "
          f"Python {platform.python_version()}, one core\n")
    print(format_table(speeds))
    ratio = mekf_mukf_ratio(speeds)
    print(f"\nMEKF/MUKF speed ratio: {ratio:.2f} (paper: about 3)")
    if a.json:
        from mkf_ros import files

        files.write_text(a.json, json.dumps({"speeds": [s.as_dict() for s in speeds],
                                      "mekf_mukf_ratio": ratio}, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
