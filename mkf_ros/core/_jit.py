"""The one place that decides how kernels are compiled and cached.

Every numerical kernel in mkf_ros is a plain Python function decorated with :func:`jit`. With
numba they are compiled once and cached on disk; with ``NUMBA_DISABLE_JIT=1`` they run as ordinary
Python, which is how a researcher can step through the equations in a debugger.

Caching: numba's own cache is keyed per source file, so a kernel is not recompiled when a kernel
it calls (in another file) changes — stale machine code. :class:`KernelCacheLocator` keys every
kernel on a hash of *all* kernel sources of the package instead (plus the numba and Python
versions; numba itself keys each entry on the CPU, so a foreign-CPU entry is never loaded), and
keeps the cache in a per-user directory (``$MKF_ROS_CACHE_DIR``, else
``$XDG_CACHE_HOME/mkf_ros``, else ``~/.cache/mkf_ros``), so an editable install, a colcon install
tree and every process share one cache, and any change to any kernel invalidates all of them.

Compiling takes minutes, so the kernels are also compiled at *install* time (``setup.py``'s
``build_py`` step, which ``pip install``, ``pip wheel`` and ``colcon build`` run, and
``./run setup`` for the editable checkout: :func:`precompile`) into the package itself
(``mkf_ros/_kernels/numba-<hash>/``). A user cache that lacks a kernel is seeded from there (a
file copy, well under a second), so a new user, container or cache directory starts in seconds.

A cache directory that cannot be written is not an error: the kernels go to a private temporary
directory instead (seeded the same way) and one warning says where it looked.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import warnings
from pathlib import Path
from types import FunctionType

import numba
from numba.core import caching

_PACKAGE_DIR = Path(__file__).resolve().parents[1]
_MARKER = "core._jit import jit"
#: Where the install-time compile puts its cache, inside the package.
PACKAGED_CACHE_ROOT = _PACKAGE_DIR / "_kernels"


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


KERNEL_HASH = _kernel_hash()
_VERSION_DIR = f"numba-{KERNEL_HASH}"


def _cache_root() -> Path:
    env = os.environ.get("MKF_ROS_CACHE_DIR")
    if env:
        return Path(env)
    xdg = os.environ.get("XDG_CACHE_HOME")
    return (Path(xdg) if xdg else Path.home() / ".cache") / "mkf_ros"


def _writable_dir(path: Path) -> bool:
    """Create ``path`` if needed; True when a file can be written in it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError:
        return False
    return True


def _seed(cache: Path) -> None:
    """Copy each install-time kernel whose index ``cache`` lacks (best effort). A kernel is an
    index ``NAME.nbi`` and its machine code ``NAME.<k>.nbc``; a kernel the cache already has is
    left alone, the code is copied before the index, and every file is written under a
    temporary name and renamed, so a concurrent process never loads half a kernel."""
    src = PACKAGED_CACHE_ROOT / _VERSION_DIR
    if not src.is_dir() or src.resolve() == cache.resolve():
        return
    try:
        for index in src.rglob("*.nbi"):
            dst = cache / index.relative_to(src)
            if dst.exists():
                continue
            dst.parent.mkdir(parents=True, exist_ok=True)
            for f in [*index.parent.glob(f"{index.stem}.*.nbc"), index]:
                tmp = dst.parent / f".{f.name}.{os.getpid()}.tmp"
                shutil.copyfile(f, tmp)
                os.replace(tmp, dst.parent / f.name)
    except OSError:
        return


def configured_cache_dir() -> Path:
    """Where the environment says this kernel version is cached (see the module docstring);
    :func:`kernel_cache_dir` is where it actually is."""
    return _cache_root() / _VERSION_DIR


def _choose_cache_dir() -> Path:
    """The cache directory of this kernel version, seeded from the install-time kernels; a
    private temporary directory (one warning) when the configured one cannot be written."""
    root = _cache_root()
    cache = configured_cache_dir()
    if not _writable_dir(cache):
        fallback = Path(tempfile.gettempdir()) / f"mkf_ros-{os.getuid()}" / _VERSION_DIR
        if not _writable_dir(fallback):
            fallback = Path(tempfile.mkdtemp(prefix="mkf_ros-kernels-")) / _VERSION_DIR
            fallback.mkdir()
        warnings.warn(f"mkf_ros: kernel cache directory {root} is not writable; using {fallback} "
                      "(set MKF_ROS_CACHE_DIR to a writable directory to keep compiled kernels)",
                      RuntimeWarning, stacklevel=2)
        cache = fallback
    _seed(cache)
    return cache


_CACHE_DIR = _choose_cache_dir()


def kernel_cache_dir() -> Path:
    """Where this version of the kernels is cached (exists once something was compiled)."""
    return _CACHE_DIR


class KernelCacheLocator(caching._SourceFileBackedLocatorMixin, caching._CacheLocator):
    """numba cache locator for mkf_ros kernels (see the module docstring)."""

    def __init__(self, py_func: FunctionType, py_file: str) -> None:
        self._py_file = py_file
        self._lineno = py_func.__code__.co_firstlineno
        rel = Path(py_file).resolve().parent.relative_to(_PACKAGE_DIR)
        self._cache_path = str(kernel_cache_dir() / rel)

    def get_cache_path(self) -> str:
        return self._cache_path

    def get_source_stamp(self) -> str:
        return KERNEL_HASH

    @classmethod
    def from_function(cls, py_func: FunctionType, py_file: str) -> KernelCacheLocator | None:
        if Path(py_file).resolve() not in _KERNEL_FILES:
            return None  # not hashed (not ours, or not using jit): numba's usual locators

        self = cls(py_func, py_file)
        try:
            self.ensure_cache_path()
        except OSError:
            return None
        return self


def _prune_old_caches(root: Path, keep_days: float = 7.0) -> None:
    """Best effort: remove caches of other kernel versions unused for ``keep_days``."""
    import time

    try:
        for d in root.glob("numba-*"):
            old = time.time() - d.stat().st_mtime > keep_days * 86400
            if d.name != _VERSION_DIR and old:
                shutil.rmtree(d, ignore_errors=True)
    except OSError:
        pass


def precompile(root: Path) -> None:
    """Compile every kernel into ``root/numba-<hash>/`` (the install-time step; see the module
    docstring), dropping other versions there. Runs :func:`mkf_ros.api.warmup` in a child
    process whose cache is ``root``."""
    import subprocess

    env = dict(os.environ, MKF_ROS_CACHE_DIR=str(root), PYTHONWARNINGS="ignore")
    env["PYTHONPATH"] = os.pathsep.join(filter(None, [str(_PACKAGE_DIR.parent),
                                                      env.get("PYTHONPATH")]))
    subprocess.run([sys.executable, "-c", "import mkf_ros.api as a; a.warmup()"], env=env,
                   check=True)
    _prune_old_caches(root, keep_days=0.0)


_prune_old_caches(_cache_root())

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
