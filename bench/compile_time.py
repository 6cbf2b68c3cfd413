"""The install-time kernel compile: wall time, CPU time and peak memory, from an empty cache.

    ./run bench compile_time [--jobs N] [--tasks] [--python PYTHON ...]

Copies the package (without its compiled kernels, ``mkf_ros/_kernels``) to a temporary
directory and runs the install-time compile there as ``pip install`` and ``colcon build`` do
(``mkf_ros.kernels.precompile`` into the copy's ``_kernels``). Prints the wall time, the CPU
time of every compiling process, and the peak resident memory, both of the largest process
and of all of them together (sampled from /proc every 20 ms). Then, in a fresh process on the
compiled cache, the time ``mkf_ros.kernels.warmup_installed()`` takes and how many numba
compiler passes it still ran (0: the install-time compile left nothing to compile for the
first start), and in others
what the first use of the MUKF, of a comparison filter (``euler_kf``, ``euler_ukf``,
``madgwick``) and of the smoothers (``estimate(..., smooth=...)``) costs: their own kernels
are compiled then, not at install time. ``--tasks`` adds
each compile task's own wall, CPU and peak memory.

One row per Python environment: this one, each ``--python`` given, and Ubuntu 24.04's set
(``.venv-noble``, built by ``.ci/noble``) when it exists; each compiles with its own numba.
The environments run one after the other.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_COMPILE = """
import json, sys
from pathlib import Path
import mkf_ros.core._jit as j
import mkf_ros.kernels as k
k.precompile(j.PACKAGED_CACHE_ROOT, jobs=int(sys.argv[1]) or None,
             report=lambda r: print("TASK " + json.dumps(r), flush=True))
"""

_CHECK = """
import json, time
import numba.core.event as ev
n = [0]
class Count(ev.Listener):  # a compiler pass runs only when something compiles (not on a load)
    def on_start(self, event):
        n[0] += 1
    def on_end(self, event):
        pass
ev.register("numba:run_pass", Count())
t0 = time.perf_counter()
import mkf_ros
mkf_ros.kernels.warmup_installed()
print(json.dumps({"seconds": time.perf_counter() - t0, "compiled": n[0]}))
"""


_FIRST_USE = """
import json, resource, sys, time
t0, c0 = time.perf_counter(), time.process_time()
import mkf_ros
mkf_ros.warmup((sys.argv[1],), algorithms=(sys.argv[2],))
print(json.dumps({"seconds": time.perf_counter() - t0, "cpu": time.process_time() - c0,
                  "rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}))
"""


#: What is compiled on its first use, not at install time (``mkf_ros.kernels``'
#: ``INSTALLED_ALGORITHMS`` and ``INSTALLED_PARTS``), as (label, warmup part, algorithm): the
#: MUKF's own kernels, one baseline's (for all three), and the MEKF's smoothers.
_FIRST_USE_OF = (("mukf", "filter", "mukf"), ("madgwick", "filter", "madgwick"),
                 ("the smoother", "smoother", "mekf"))


def _tree_rss_kib(pid: int) -> tuple[int, int]:
    """(sum, max) of the resident memory (KiB) of ``pid`` and its descendants."""
    children: dict[int, list[int]] = {}
    rss: dict[int, int] = {}
    for d in Path("/proc").iterdir():
        if not d.name.isdigit():
            continue
        try:
            stat = (d / "stat").read_text()
            status = (d / "status").read_text()
        except OSError:
            continue
        ppid = int(stat.rsplit(")", 1)[1].split()[1])
        children.setdefault(ppid, []).append(int(d.name))
        for line in status.splitlines():
            if line.startswith("VmRSS:"):
                rss[int(d.name)] = int(line.split()[1])
    todo, total, largest = [pid], 0, 0
    while todo:
        p = todo.pop()
        total += rss.get(p, 0)
        largest = max(largest, rss.get(p, 0))
        todo.extend(children.get(p, []))
    return total, largest


def compile_copy(jobs: int, python: str = sys.executable) -> dict:
    """The install-time compile of a fresh copy of the package by ``python``; its figures."""
    with tempfile.TemporaryDirectory(prefix="mkf-compile-") as tmp:
        shutil.copytree(ROOT / "mkf_ros", Path(tmp) / "mkf_ros",
                        ignore=shutil.ignore_patterns("_kernels", "__pycache__"))
        env = dict(os.environ, PYTHONPATH=tmp, MKF_ROS_CACHE_DIR=str(Path(tmp) / "user-cache"))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.Popen([python, "-c", _COMPILE, str(jobs)], cwd=tmp, env=env,
                                stdout=subprocess.PIPE, text=True)
        peak = [0, 0]
        done = threading.Event()

        def sample() -> None:
            while not done.is_set():
                total, largest = _tree_rss_kib(proc.pid)
                peak[0], peak[1] = max(peak[0], total), max(peak[1], largest)
                time.sleep(0.02)

        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        out, _ = proc.communicate()
        wall = time.perf_counter() - t0
        done.set()
        sampler.join()
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode:
            sys.exit(f"compile_time: the compile failed (exit {proc.returncode})")
        tasks = [json.loads(line[5:]) for line in out.splitlines() if line.startswith("TASK ")]
        check = subprocess.run([python, "-c", _CHECK], cwd=tmp, env=env,
                               capture_output=True, text=True, check=True)
        first = {label: subprocess.run([python, "-c", _FIRST_USE, part, algo], cwd=tmp,
                                       env=env, capture_output=True, text=True,
                                       check=True).stdout
                 for label, part, algo in _FIRST_USE_OF}
        cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
        version = subprocess.run(
            [python, "-c", "import sys, numba, numpy; print(f'numba {numba.__version__}, "
             "NumPy {numpy.__version__}, Python {sys.version.split()[0]}')"],
            capture_output=True, text=True, check=True).stdout.strip()
        return {"env": version, "wall": wall, "cpu": cpu, "peak_sum_mb": peak[0] / 1024,
                "peak_max_mb": peak[1] / 1024, "tasks": tasks,
                "check": json.loads(check.stdout.strip().splitlines()[-1]),
                "first": {a: json.loads(o.strip().splitlines()[-1]) for a, o in first.items()}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--jobs", type=int, default=0,
                    help="compiling processes (default: the install's, mkf_ros.kernels."
                         "compile_jobs)")
    ap.add_argument("--tasks", action="store_true", help="print every compile task's figures")
    ap.add_argument("--python", action="append", default=[],
                    help="another environment's interpreter to compile with (repeatable)")
    args = ap.parse_args()
    pythons = [sys.executable, *args.python]
    noble = ROOT / ".venv-noble" / "bin" / "python"
    if noble.exists() and str(noble) not in pythons:
        pythons.append(str(noble))
    results = [compile_copy(args.jobs, py) for py in pythons]
    from mkf_ros.kernels import compile_jobs

    jobs = args.jobs or compile_jobs()
    print(f"\ninstall-time compile of every kernel, empty cache, {jobs} process(es) at a time, "
          f"{os.cpu_count()} CPUs\n")
    print("| environment | wall | CPU (all processes) | peak RSS, all processes |"
          " peak RSS, largest process | warmup_installed() after it |"
          " compiler passes run by it |"
          + "".join(f" first use of {a}: wall / CPU / peak RSS |" for a, _, _ in _FIRST_USE_OF))
    print("|---|---:|---:|---:|---:|---:|---:|" + "---:|" * len(_FIRST_USE_OF))
    for r in results:
        print(f"| {r['env']} | {r['wall']:.1f} s | {r['cpu']:.1f} s | {r['peak_sum_mb']:.0f} MB | "
              f"{r['peak_max_mb']:.0f} MB | {r['check']['seconds']:.2f} s | "
              f"{r['check']['compiled']} |" + "".join(
                  f" {b['seconds']:.1f} s / {b['cpu']:.1f} s / {b['rss_mb']:.0f} MB |"
                  for b in r["first"].values()))
    if args.tasks:
        for r in results:
            print(f"\n{r['env']}\n\n| task | wall | CPU | peak RSS |\n|---|---:|---:|---:|")
            for name, wall, cpu, rss in r["tasks"]:
                print(f"| {name} | {wall:.1f} s | {cpu:.1f} s | {rss / 1024:.0f} MB |")


if __name__ == "__main__":
    main()
