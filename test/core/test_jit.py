"""The kernel cache of :mod:`mkf_ros.core._jit`: seeded from the install-time compile, and an
unwritable cache directory is not an error (issue 16)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mkf_ros.core import _jit

PROBE = """
import numpy as np
from mkf_ros.stream import StreamAdapter
from mkf_ros.core._jit import kernel_cache_dir
s = StreamAdapter(algorithm="mekf", use_mag=False)
for k in range(20):
    o = s.on_imu(1.0 + 0.01 * k, np.array([0.0, 0.0, 0.1]), np.array([0.0, 0.0, 9.81]))
print(kernel_cache_dir())
print(*o.quat_wxyz)
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
    assert (cache / "core" / "stream_kernel.run_events-9.py311.nbi").read_bytes() == b"stream index"
    assert (cache / "core" / "stream_kernel.run_events-9.py311.0.nbc").read_bytes() == b"stream code"
    # ... one it has (its own index, maybe other code files) is left alone
    assert (cache / "core" / "filter.run_batch-1.py311.nbi").read_bytes() == b"the user's own index"
    assert not (cache / "core" / "filter.run_batch-1.py311.0.nbc").exists()
    assert not list(cache.rglob("stale.nbi"))
    assert not list(cache.rglob("*.tmp"))
