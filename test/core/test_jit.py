"""The kernel cache and compile switches (mkf_ros/core/_jit.py, mkf_ros.kernels.warmup): the
cache key covers every kernel source, the cache lives where the docs say and is reused by the next
process, ``NUMBA_DISABLE_JIT=1`` runs the same equations as plain Python, and ``warmup()``
leaves nothing for the first real samples to compile.

The checks that start Python run in child processes (numba's switches are read at import);
they use the shared warm cache, so they take seconds, not a cold compile."""

from __future__ import annotations

import ast
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mkf_ros.core import _jit

PKG = Path(_jit.__file__).resolve().parents[1]


def _child(code: str, **env: str) -> dict:
    """Run ``code`` in a fresh Python; it prints one JSON line last, returned."""
    out = subprocess.run([sys.executable, "-c", code], env={**os.environ, **env},
                         capture_output=True, text=True, timeout=280, check=False)
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def _decorated_with_jit(path: Path) -> bool:
    """True if any function in ``path`` carries ``@jit`` / ``@jit_inline`` / ``@unit(...)``
    (read by AST)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    for node in ast.walk(tree):
        if isinstance(node, ast.FunctionDef):
            for d in node.decorator_list:
                d = d.func if isinstance(d, ast.Call) else d
                if isinstance(d, ast.Name) and d.id in ("jit", "jit_inline", "unit"):
                    return True
    return False


def test_every_kernel_file_is_in_the_cache_key() -> None:
    """The key hashes every file of the package that defines a kernel (found here by its
    decorators, not by the module's own marker string), and _jit.py itself."""
    kernels = {p.resolve() for p in PKG.rglob("*.py") if _decorated_with_jit(p)}
    assert len(kernels) >= 5
    assert kernels | {Path(_jit.__file__).resolve()} <= set(_jit._KERNEL_FILES)


def test_the_key_changes_with_any_kernel_source(tmp_path: Path, monkeypatch) -> None:
    """Any byte of any kernel source changes the key (so a kernel that calls a changed
    kernel in another file is recompiled), a non-kernel file does not, and an unchanged tree
    gives the same key."""
    copy = tmp_path / "mkf_ros"
    files = []
    for p in _jit._KERNEL_FILES:
        q = copy / p.relative_to(PKG)
        q.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(p, q)
        files.append(q)
    other = copy / "not_a_kernel.py"
    other.write_text("x = 1\n")
    monkeypatch.setattr(_jit, "_PACKAGE_DIR", copy)
    monkeypatch.setattr(_jit, "_KERNEL_FILES", files)
    key = _jit._kernel_hash()
    assert key == _jit.KERNEL_HASH  # the copy is the same sources
    for f in files:
        text = f.read_bytes()
        f.write_bytes(text + b"\n# edited\n")
        assert _jit._kernel_hash() != key, f.name
        f.write_bytes(text)
    other.write_text("x = 2\n")
    assert _jit._kernel_hash() == key


def test_cache_dir_follows_the_environment(tmp_path: Path, monkeypatch) -> None:
    """$MKF_ROS_CACHE_DIR, else $XDG_CACHE_HOME/mkf_ros, else ~/.cache/mkf_ros; one folder
    per key."""
    monkeypatch.delenv("MKF_ROS_CACHE_DIR", raising=False)
    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    name = f"numba-{_jit.KERNEL_HASH}"
    assert _jit.configured_cache_dir() == tmp_path / "home" / ".cache" / "mkf_ros" / name
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert _jit.configured_cache_dir() == tmp_path / "xdg" / "mkf_ros" / name
    monkeypatch.setenv("MKF_ROS_CACHE_DIR", str(tmp_path / "own"))
    assert _jit.configured_cache_dir() == tmp_path / "own" / name


_COMPILE_ONE = """
import json
from mkf_ros.core._jit import kernel_cache_dir
from mkf_ros.core.quaternion import qmul_t
assert qmul_t((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)) == (0.0, 1.0, 0.0, 0.0)
s = qmul_t.stats
print(json.dumps({"dir": str(kernel_cache_dir()), "hits": sum(s.cache_hits.values()),
                  "misses": sum(s.cache_misses.values())}))
"""


def test_a_kernel_is_cached_and_reused_by_the_next_process(tmp_path: Path) -> None:
    """A kernel compiled in one process is written under the cache folder of this key and
    loaded, not compiled, by the next one."""
    first = _child(_COMPILE_ONE, MKF_ROS_CACHE_DIR=str(tmp_path))
    assert Path(first["dir"]) == tmp_path / f"numba-{_jit.KERNEL_HASH}"
    # compiled here, or loaded from the install-time kernels the new cache was seeded with
    assert first["misses"] + first["hits"] == 1
    assert list((Path(first["dir"]) / "core").glob("quaternion.qmul_t-*.nbi"))
    second = _child(_COMPILE_ONE, MKF_ROS_CACHE_DIR=str(tmp_path))
    assert second["hits"] == 1 and second["misses"] == 0


_FIRST_KERNEL = """
import json, sys
from pathlib import Path
import mkf_ros, mkf_ros.kernels  # every kernel module
root = Path(sys.argv[1])
before = sorted(p.name for p in root.iterdir())
from mkf_ros.core.quaternion import qmul_t
qmul_t((1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0))
print(json.dumps({"before": before, "after": sorted(p.name for p in root.iterdir())}))
"""


def test_import_touches_no_cache_directory_the_first_kernel_does(tmp_path: Path) -> None:
    """Importing every kernel module creates, seeds and prunes nothing on disk; the first
    kernel compiled or loaded chooses this version's cache directory and removes another
    version's unused for over a week."""
    stale = tmp_path / "numba-0000000000000000"
    stale.mkdir()
    week_ago = os.path.getmtime(stale) - 8 * 86400
    os.utime(stale, (week_ago, week_ago))
    code = _FIRST_KERNEL.replace("sys.argv[1]", repr(str(tmp_path)))
    got = _child(code, MKF_ROS_CACHE_DIR=str(tmp_path))
    assert got == {"before": [stale.name], "after": [f"numba-{_jit.KERNEL_HASH}"]}


_ESTIMATE = """
import json
import numpy as np
import numba
from mkf_ros import estimate
from mkf_ros.core import mekf, mukf
from mkf_ros.sim import simulate
r = simulate("slow_rotation", duration=0.5, rate=100.0, seed=4, mag_rate=100.0)
out = {"dispatcher": isinstance(mekf.mekf_vector_update, numba.core.dispatcher.Dispatcher)
                     or isinstance(mukf.mukf_step_ext, numba.core.dispatcher.Dispatcher)}
for algo in ("mekf", "mukf"):
    q = estimate(r.gyr, r.acc, r.mag, dt=0.01, algorithm=algo, estimate_gyro_bias=True)
    out[algo] = q.quat.tolist()
print(json.dumps(out))
"""


def test_numba_disable_jit_runs_the_same_equations_in_python() -> None:
    """With ``NUMBA_DISABLE_JIT=1`` the kernels are the plain Python functions (a debugger
    steps through them) and the filters give the compiled results to rounding."""
    plain = _child(_ESTIMATE, NUMBA_DISABLE_JIT="1")
    compiled = _child(_ESTIMATE, NUMBA_DISABLE_JIT="0")
    assert plain["dispatcher"] is False and compiled["dispatcher"] is True
    import numpy as np

    for algo in ("mekf", "mukf"):
        a, b = np.array(plain[algo]), np.array(compiled[algo])
        assert a.shape == b.shape and a.size > 0
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)


_WARMUP = """
import json, sys
import numpy as np
import numba
import mkf_ros

def compiled():
    seen = {}
    for name, mod in list(sys.modules.items()):
        if not name.startswith("mkf_ros"):
            continue
        for attr, obj in list(vars(mod).items()):
            if isinstance(obj, numba.core.dispatcher.Dispatcher):
                seen[f"{obj.py_func.__module__}.{attr}"] = sorted(map(str, obj.signatures))
    return seen

from mkf_ros.sim import simulate
r = simulate("slow_rotation", duration=0.3, rate=100.0, seed=1, mag_rate=50.0)  # the input
mkf_ros.warmup()
before = compiled()
from mkf_ros import estimate
from mkf_ros.core.filter import AttitudeFilter
from mkf_ros.stream.adapter import StreamAdapter
for algo in ("mekf", "mukf"):
    for mag in (r.mag, None):
        estimate(r.gyr, r.acc, mag, dt=0.01, algorithm=algo)
        estimate(r.gyr, r.acc, mag, dt=0.01, algorithm=algo, estimate_gyro_bias=True)
    for use_mag in (False, True):
        f = AttitudeFilter(algorithm=algo, use_mag=use_mag)
        for k in range(len(r.t)):
            f.step(0.01, r.gyr[k], r.acc[k], r.mag[k] if use_mag else None)
        f.quaternion, f.covariance
        s = StreamAdapter(algorithm=algo, use_mag=use_mag)
        for k in range(len(r.t)):
            if use_mag and not np.isnan(r.mag[k, 0]):
                s.on_mag(100.0 + r.t[k], r.mag[k])
            s.on_imu(100.0 + r.t[k], r.gyr[k], r.acc[k])
        s.reset()
        s.process(200.0 + r.t, r.gyr, r.acc, 200.0 + r.t, r.mag)
after = compiled()
new = {k: sorted(set(v) - set(before.get(k, []))) for k, v in after.items()}
print(json.dumps({k: v for k, v in new.items() if v}))
"""


@pytest.mark.slow
def test_warmup_leaves_nothing_to_compile_for_the_filters() -> None:
    """After ``warmup()``, the public ways to run a filter (estimate, AttitudeFilter.step,
    StreamAdapter per message and per recording; MEKF and MUKF, with and without the
    magnetometer and the bias) compile no new kernel signature: the first real sample is not
    delayed by a compile."""
    assert _child(_WARMUP) == {}


_FIRST_USE = """
import json
import numpy as np
import mkf_ros
from mkf_ros.core import baseline_glue as glue, sensor, smoother
from mkf_ros.core.filter import AttitudeFilter
from mkf_ros.kernels import INSTALLED_ALGORITHMS, compile_tasks, warmup_installed
from mkf_ros.sim import simulate
from mkf_ros.stream.adapter import StreamAdapter

def compiled():
    units = {"mukf": (sensor.mukf_update,),
             "baselines": (sensor.baseline_step, glue.export, glue.restore)}
    out = {k: [u._compiled is not None for u in v] for k, v in units.items()}
    loops = (smoother.forward_recorded, smoother.backward, smoother.fuse_tilt_rows)
    out["smoother"] = [bool(d.signatures) for d in loops]  # compiled or loaded
    return out

r = simulate("slow_rotation", duration=1.0, rate=100.0, seed=2, mag_rate=100.0)
warmup_installed()
# every front end of the MEKF but the smoothers
mkf_ros.estimate(r.gyr, r.acc, r.mag, dt=0.01)
AttitudeFilter(use_mag=True).step(0.01, r.gyr[0], r.acc[0], r.mag[0])
StreamAdapter().process(r.t, r.gyr, r.acc)
steps = {"mekf": compiled()}
q = {"smoother": mkf_ros.estimate(r.gyr, r.acc, r.mag, dt=0.01,
                                  smooth="two-way").quat[-1].tolist()}
steps["smoother"] = compiled()
for algo in ("mukf", "euler_kf", "euler_ukf", "madgwick"):
    q[algo] = mkf_ros.estimate(r.gyr, r.acc, r.mag, dt=0.01, algorithm=algo).quat[-1].tolist()
    steps[algo] = compiled()
print(json.dumps({"installed": INSTALLED_ALGORITHMS, "steps": steps,
                  "tasks": " ".join(compile_tasks()), "q": q, "truth": r.quat[-1].tolist()}))
"""


def test_only_the_mekf_is_compiled_at_install_the_others_on_their_first_use() -> None:
    """The install-time compile makes the MEKF's kernels (the default) but its smoothers; the
    smoothers' loops, the MUKF's update and the comparison filters' kernels are compiled on
    their first use: the MEKF's other front ends run without compiling or loading them, a
    first smoothing compiles the smoothers' loops alone, the MUKF's first use its update
    alone, a baseline's the baselines' units, and each then tracks the truth."""
    out = _child(_FIRST_USE)
    assert out["installed"] == ["mekf"]
    steps = out["steps"]
    none, three = [False, False, False], [True, True, True]
    assert steps["mekf"] == {"mukf": [False], "baselines": none, "smoother": none}
    assert steps["smoother"] == {"mukf": [False], "baselines": none, "smoother": three}
    assert steps["mukf"] == {"mukf": [True], "baselines": none, "smoother": three}
    assert steps["euler_kf"] == {"mukf": [True], "baselines": three, "smoother": three}
    for name in ("mukf_update", "baseline_step", "baseline_glue.export",
                 "baseline_glue.restore", "entries:smoother"):
        assert name not in out["tasks"]
    assert "sensor.step" in out["tasks"]
    truth = np.array(out["truth"])
    for algo, q in out["q"].items():
        err = 2 * np.degrees(np.arccos(min(1.0, abs(float(np.dot(q, truth))))))
        assert err < 5.0, (algo, err)


PROBE = """
import numpy as np
from mkf_ros.stream.adapter import StreamAdapter
from mkf_ros.core._jit import kernel_cache_dir
s = StreamAdapter(algorithm="mekf", use_mag=False)
for k in range(20):
    o = s.on_imu(1.0 + 0.01 * k, np.array([0.0, 0.0, 0.1]), np.array([0.0, 0.0, 9.81]))
print(kernel_cache_dir())
print(*o.quat)
"""


def _probe(cache: str) -> subprocess.CompletedProcess[str]:
    env = dict(os.environ, MKF_ROS_CACHE_DIR=cache)
    return subprocess.run([sys.executable, "-c", PROBE], env=env, capture_output=True, text=True,
                          check=False)


def test_unwritable_cache_dir_warns_once_and_still_runs(tmp_path: Path) -> None:
    """A cache directory that cannot be created (a path under a regular file: not writable even
    for root) gives one warning naming it and where the kernels went instead; the filter runs."""
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    wanted = blocker / "cache"
    r = _probe(str(wanted))
    assert r.returncode == 0, r.stderr
    warnings = [ln for ln in r.stderr.splitlines() if "not writable" in ln]
    assert len(warnings) == 1, r.stderr
    used, quat = r.stdout.splitlines()[-2:]
    assert str(wanted) in warnings[0] and used in warnings[0]
    assert not Path(used).is_relative_to(wanted) and Path(used).is_dir()
    q = np.array(quat.split(), float)
    assert np.all(np.isfinite(q)) and abs(np.linalg.norm(q) - 1.0) < 1e-9


def test_writable_cache_dir_is_used_without_warning(tmp_path: Path) -> None:
    r = _probe(str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert "not writable" not in r.stderr
    used = Path(r.stdout.splitlines()[-2])
    assert used == tmp_path / f"numba-{_jit.KERNEL_HASH}"
    assert any(used.rglob("*.nbi")), "no kernel index written into the cache directory"


def test_seed_copies_missing_install_time_kernels_and_keeps_existing(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    packaged = tmp_path / "pkg"
    src = packaged / f"numba-{_jit.KERNEL_HASH}" / "core"
    src.mkdir(parents=True)
    (src / "filter.run_batch-1.py311.nbi").write_bytes(b"index from the install")
    (src / "filter.run_batch-1.py311.0.nbc").write_bytes(b"code from the install")
    (src / "stream_kernel.run_events-9.py311.nbi").write_bytes(b"stream index")
    (src / "stream_kernel.run_events-9.py311.0.nbc").write_bytes(b"stream code")
    other = packaged / "numba-0000000000000000" / "core"  # another kernel version: never used
    other.mkdir(parents=True)
    (other / "stale.nbi").write_bytes(b"stale")
    monkeypatch.setattr(_jit, "PACKAGED_CACHE_ROOT", packaged)

    cache = tmp_path / "user" / f"numba-{_jit.KERNEL_HASH}"
    (cache / "core").mkdir(parents=True)
    (cache / "core" / "filter.run_batch-1.py311.nbi").write_bytes(b"the user's own index")
    _jit._seed(cache)

    # a kernel the user cache lacks arrives whole (index and code) ...
    got = cache / "core" / "stream_kernel.run_events-9.py311"
    assert got.with_suffix(".py311.nbi").read_bytes() == b"stream index"
    assert got.with_suffix(".py311.0.nbc").read_bytes() == b"stream code"
    # ... one it has (its own index, maybe other code files) is left alone
    own = (cache / "core" / "filter.run_batch-1.py311.nbi").read_bytes()
    assert own == b"the user's own index"
    assert not (cache / "core" / "filter.run_batch-1.py311.0.nbc").exists()
    assert not list(cache.rglob("stale.nbi"))
    assert not list(cache.rglob("*.tmp"))


def test_ir_inliner_copies_an_inlined_function_with_one_scope() -> None:
    """numba ≥ 0.59 inlines ``jit_inline`` kernels at IR level, copying the inlined function;
    the copy has one variable scope for all its blocks, as the function itself has (not one
    copy of the whole scope per block: time and memory quadratic in the function's size), and
    the compiled caller computes what the Python functions compute. On numba 0.58
    ``jit_inline`` kernels are ordinary kernels and numba's inliner is left as it is."""
    import numba
    from numba.core import inline_closurecall as ic

    if not _jit.INLINE_AT_IR_LEVEL:
        assert not _jit.share_inliner_memo()
        return
    assert _jit.share_inliner_memo()

    def branchy(x: float, n: int) -> float:  # several blocks, several variables
        acc = 0.0
        for i in range(n):
            if x > i:
                acc += x * i
            elif x < -i:
                acc -= x / (i + 1)
            else:
                acc += 1.0
        return acc

    def caller(x: float, n: int) -> float:
        return branchy(x, n) + 2.0 * branchy(-x, n + 1)

    copies: list = []
    inline_ir = ic.InlineWorker.inline_ir

    def spy(self, *args, **kwargs):  # (callee IR kept unmutated, its blocks, names, new blocks)
        out = inline_ir(self, *args, **kwargs)
        copies.append(out[0])
        return out

    inlined = numba.njit(inline="always")(branchy)
    compiled = numba.njit(lambda x, n: inlined(x, n) + 2.0 * inlined(-x, n + 1))
    ic.InlineWorker.inline_ir = spy
    try:
        for x, n in ((0.5, 4), (-3.0, 7), (10.0, 0)):
            assert compiled(x, n) == caller(x, n)
    finally:
        ic.InlineWorker.inline_ir = inline_ir
    assert len(copies) == 2
    for ir in copies:
        assert len(ir.blocks) > 3
        assert len({id(b.scope) for b in ir.blocks.values()}) == 1
