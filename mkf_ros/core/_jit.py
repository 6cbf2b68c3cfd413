"""The one place that decides how kernels are compiled and cached.

Every numerical kernel in mkf_ros is a plain Python function decorated with :func:`jit`. With
numba they are compiled once and cached on disk; with ``NUMBA_DISABLE_JIT=1`` they run as ordinary
Python, which is how a researcher can step through the equations in a debugger.

Caching: numba's own cache is keyed per source file, so a kernel is not recompiled when a kernel
it calls (in another file) changes — stale machine code. :class:`KernelCacheLocator` keys every
kernel on a hash of *all* kernel sources of the package instead, and keeps the cache in a per-user
directory (``$MKF_ROS_CACHE_DIR``, else ``$XDG_CACHE_HOME/mkf_ros``, else ``~/.cache/mkf_ros``),
so an editable install, a colcon install tree and every process share one cache, and any change
to any kernel invalidates all of them. If that directory is not writable numba's usual locations
are used.
"""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path

import numba
from numba.core import caching

_PACKAGE_DIR = Path(__file__).resolve().parents[1]
_MARKER = "core._jit import jit"


def _kernel_files() -> list[Path]:
    """Every package source file that defines kernels with :func:`jit` (and this one)."""
    return [p for p in sorted(_PACKAGE_DIR.rglob("*.py"))
            if p.name == "_jit.py" or _MARKER.encode() in p.read_bytes()]


_KERNEL_FILES = _kernel_files()


def _kernel_hash() -> str:
    """Hash of every kernel source file, plus the numba and Python versions."""
    h = hashlib.sha256(f"{numba.__version__} {sys.version_info[:2]}".encode())
    for path in _KERNEL_FILES:
        h.update(str(path.relative_to(_PACKAGE_DIR)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()[:16]


def _cache_root() -> Path:
    env = os.environ.get("MKF_ROS_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "mkf_ros"


KERNEL_HASH = _kernel_hash()


def kernel_cache_dir() -> Path:
    """Where this version of the kernels is cached (exists once something was compiled)."""
    return _cache_root() / f"numba-{KERNEL_HASH}"


class KernelCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """numba cache locator for mkf_ros kernels (see the module docstring)."""

    def __init__(self, py_func: object, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno  # type: ignore[attr-defined]
        rel = Path(py_file).resolve().parent.relative_to(_PACKAGE_DIR)
        self._cache_path = str(kernel_cache_dir() / rel)

    def get_cache_path(self) -> str:
        return self._cache_path

    def get_source_stamp(self) -> str:
        return KERNEL_HASH

    @classmethod
    def from_function(cls, py_func: object, py_file: str) -> KernelCacheLocator | None:
        if Path(py_file).resolve() not in _KERNEL_FILES:
            return None  # not hashed (not ours, or not using jit): numba's usual locators

        self = cls(py_func, py_file)
        try:
            self.ensure_cache_path()
        except OSError:
            return None
        return self


def _prune_old_caches(keep_days: float = 7.0) -> None:
    """Best effort: remove caches of other kernel versions unused for ``keep_days``."""
    import shutil
    import time

    root = _cache_root()
    try:
        for d in root.glob("numba-*"):
            old = time.time() - d.stat().st_mtime > keep_days * 86400
            if d.name != f"numba-{KERNEL_HASH}" and old:
                shutil.rmtree(d, ignore_errors=True)
    except OSError:
        pass


_prune_old_caches()

if KernelCacheLocator not in caching.CacheImpl._locator_classes:
    caching.CacheImpl._locator_classes.insert(0, KernelCacheLocator)

#: Compile options shared by every kernel: no Python objects, cached, GIL released.
jit = numba.njit(cache=True, nogil=True, error_model="numpy")
#: The same, inlined into every compiled caller at numba IR level (a Python call still gets a
#: normal compiled function): for kernels and helpers on the per-sample hot paths. A call between
#: compiled functions increfs and decrefs every array argument (atomic operations, together
#: more than the arithmetic of a 6-state update, ~0.3 µs for a call with many arrays); inlined,
#: numba prunes most of those pairs. Costs compile time at every call site. Not for functions
#: with more than 30 parameters (numba cannot inline such a call).
jit_inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")
