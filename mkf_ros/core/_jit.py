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

Compile units. numba links the machine code of every compiled function into each compiled
function that calls it, directly or through others, and optimises and compiles it there again
(measured: 3–10 s for each caller of the sensor step). The large kernels are therefore
units (:func:`unit`): each is compiled once, on its own, as a C callable (a numba ``cfunc``),
and its callers receive it as an argument and call it through its address (a few nanoseconds
per call). Its callers' compile no longer includes it, and the units compile independently of each
other, so :func:`precompile` spreads them over processes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import sys
import tempfile
import warnings
from collections.abc import Callable
from pathlib import Path
from types import FunctionType
from typing import Any

import numba
from numba.core import caching, cgutils, types
from numba.core.registry import CPUDispatcher
from numba.extending import intrinsic

_PACKAGE_DIR = Path(__file__).resolve().parents[1]
_MARKER = "from mkf_ros.core._jit import"
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


#: The compiled loops that take the units (:func:`mkf_ros.api.compile_entries`), and their
#: compile times on the reference machine (``./run bench compile_time --tasks``).
_ENTRY_COSTS = {"estimate": 11.0, "filter": 2.0, "stream": 20.0}


def compile_tasks() -> tuple[list[str], list[str]]:
    """The install-time compile as two lists of tasks: first every :class:`Unit`
    (``"unit:MODULE.NAME"``) and the compiled loops that take them (``"entries:PART"``,
    :func:`mkf_ros.api.compile_entries`), independent of each other, largest first (so that
    the processes end together); then ``"warmup:all"`` (:func:`mkf_ros.api.warmup`: loads
    them all and compiles whatever they missed; and the simulator's integration kernel,
    :mod:`mkf_ros.sim._integrate`)."""
    import mkf_ros.api  # noqa: F401  (defines every unit)

    costs = {f"unit:{u.__module__}.{u.__qualname__}": u.cost for u in UNITS}
    costs.update({f"entries:{p}": c for p, c in _ENTRY_COSTS.items()})
    return sorted(costs, key=lambda t: -costs[t]), ["warmup:all"]


def run_compile_task(task: str) -> tuple[str, float, float, int]:
    """One task of :func:`compile_tasks` in this process: ``(task, wall s, CPU s, peak RSS
    in KiB of this process)``."""
    import resource
    import time

    t0, c0 = time.perf_counter(), time.process_time()
    import mkf_ros.api as api

    kind, name = task.split(":", 1)
    if kind == "unit":
        _ = next(u for u in UNITS if f"{u.__module__}.{u.__qualname__}" == name).compiled
    elif kind == "entries":
        api.compile_entries(name)
    else:
        api.warmup()
        import numpy as np

        from mkf_ros.sim.motion import integrate

        integrate(np.array([1.0, 0.0, 0.0, 0.0]), np.zeros((2, 3)), 0.01)  # the simulator's
    return (task, time.perf_counter() - t0, time.process_time() - c0,
            resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)


def compile_jobs() -> int:
    """Processes of the install-time compile: ``$MKF_ROS_COMPILE_JOBS``, else the CPUs this
    process may use, at most 2 (each takes up to ~0.5 GB)."""
    env = os.environ.get("MKF_ROS_COMPILE_JOBS", "")
    if env.strip().isdigit() and int(env) > 0:
        return int(env)
    try:
        n = len(os.sched_getaffinity(0))
    except AttributeError:  # pragma: no cover (not Linux)
        n = os.cpu_count() or 1
    return max(1, min(2, n))


def precompile(root: Path, jobs: int | None = None,
               report: Callable[[tuple[str, float, float, int]], object] | None = None) -> None:
    """Compile every kernel into ``root/numba-<hash>/`` (the install-time step; see the module
    docstring), dropping other versions there: the tasks of :func:`compile_tasks`, each in a
    fresh process whose cache is ``root``, ``jobs`` at a time (:func:`compile_jobs`).
    ``report`` receives each task's result (:func:`run_compile_task`)."""
    import concurrent.futures
    import multiprocessing

    units, entries = compile_tasks()
    jobs = jobs or compile_jobs()
    saved = {k: os.environ.get(k) for k in ("MKF_ROS_CACHE_DIR", "PYTHONWARNINGS")}
    os.environ.update(MKF_ROS_CACHE_DIR=str(root), PYTHONWARNINGS="ignore")
    try:
        for phase in (units, entries):
            with concurrent.futures.ProcessPoolExecutor(
                    max_workers=jobs, mp_context=multiprocessing.get_context("spawn"),
                    max_tasks_per_child=1) as pool:
                for result in pool.map(run_compile_task, phase):
                    if report is not None:
                        report(result)
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
    _prune_old_caches(root, keep_days=0.0)


_prune_old_caches(_cache_root())

if KernelCacheLocator not in caching.CacheImpl._locator_classes:
    caching.CacheImpl._locator_classes.insert(0, KernelCacheLocator)

#: Whether kernels run as plain Python (``NUMBA_DISABLE_JIT=1``).
JIT_DISABLED = bool(vars(numba.config)["DISABLE_JIT"])


class _Dispatcher(CPUDispatcher):
    """numba's dispatcher, compiling one version per argument *types* for calls from compiled
    code too: numba compiles a separate version of a function for each constant (literal)
    argument of a compiled caller (``f(x, True)`` and ``f(x, False)``: two versions; measured:
    up to 10 of one small kernel, a quarter of the compile time)."""

    def get_call_template(self, args: Any, kws: Any) -> Any:
        return super().get_call_template(tuple(types.unliteral(a) for a in args),
                                         {k: types.unliteral(v) for k, v in kws.items()})


_OPTIONS = {"nopython": True, "nogil": True, "error_model": "numpy"}


def _kernel(inline: str) -> Callable[[Callable], Callable]:
    def decorate(fn: Callable) -> Callable:
        if JIT_DISABLED:
            return fn
        disp = _Dispatcher(py_func=fn, locals={}, targetoptions=dict(_OPTIONS, inline=inline))
        disp.enable_caching()
        return disp
    return decorate


#: Compile options shared by every kernel: no Python objects, cached, GIL released, one
#: version per argument types (:class:`_Dispatcher`).
jit = _kernel("never")


#: Every :class:`Unit`, in the order their modules defined them.
UNITS: list[Unit] = []


class Unit:
    """A kernel compiled on its own (see "Compile units" above): calling it from Python runs
    the Python function; :attr:`compiled` is the compiled C callable (compiled, or loaded from
    the cache, on first use) that compiled callers take as an argument of type :attr:`type`
    (numba ``FunctionType``). With ``NUMBA_DISABLE_JIT=1`` :attr:`compiled` is the Python
    function itself."""

    def __init__(self, py_func: Callable, signature: numba.core.typing.templates.Signature,
                 cost: float) -> None:
        self.py_func = py_func
        self.cost = cost
        self.signature = signature
        self.type = numba.types.FunctionType(signature)
        self._compiled: object = None
        self.__name__ = py_func.__name__
        self.__qualname__ = py_func.__qualname__
        self.__doc__ = py_func.__doc__
        self.__module__ = py_func.__module__
        UNITS.append(self)

    def __call__(self, *args: object) -> object:
        return self.py_func(*args)

    @property
    def compiled(self) -> object:
        if JIT_DISABLED:
            return self.py_func
        if self._compiled is None:
            self._compiled = numba.cfunc(self.signature, cache=True, error_model="numpy")(
                self.py_func)
        return self._compiled


def _function_at(typingctx: Any, addr: Any, fntype: Any) -> tuple:
    """``function_at(address, FUNCTION_TYPE)`` in compiled code: the compiled unit at that
    address (an int64, ``Unit.compiled.address``) as a value of the numba ``FunctionType`` given
    (a unit's :attr:`Unit.type`). Lets Python hand compiled code its units as an array of
    addresses: numba types that in well under a microsecond, where it types a tuple of units
    anew at every call (measured: 11 µs per unit)."""
    ft = fntype.instance_type

    def codegen(context: Any, builder: Any, sig: Any, args: tuple) -> Any:
        fn = cgutils.create_struct_proxy(ft)(context, builder)
        fn.c_addr = builder.inttoptr(args[0], fn.c_addr.type)
        return fn._getvalue()

    return ft(addr, fntype), codegen


function_at: Any = intrinsic(_function_at)


def tuple_type(members: list, cls: type) -> types.Type:
    """The numba type of an instance of the namedtuple class ``cls`` with members of these
    types (as ``numba.typeof`` gives it: uniform members make a ``NamedUniTuple``)."""
    if all(m == members[0] for m in members):
        return types.NamedUniTuple(members[0], len(members), cls)
    return types.NamedTuple(members, cls)


def unit(signature: numba.core.typing.templates.Signature,
         cost: float = 1.0) -> Callable[[Callable], Unit]:
    """Decorator: the function as a :class:`Unit` of the given numba signature; ``cost``, its
    compile time in seconds on the reference machine (``./run bench compile_time --tasks``),
    orders the install-time compile (the largest first, so that the processes end together)."""
    return lambda fn: Unit(fn, signature, cost)
#: The same, inlined into every compiled caller at numba IR level (a Python call still gets a
#: normal compiled function): for kernels and helpers on the per-sample hot paths. A call between
#: compiled functions increfs and decrefs every array argument (atomic operations, together
#: more than the arithmetic of a 6-state update, ~0.3 µs for a call with many arrays); inlined,
#: numba prunes most of those pairs. Costs compile time at every call site (numba types the
#: inlined code again there). Not for functions with more than 30 parameters (numba cannot
#: inline such a call).
jit_inline = _kernel("always")
