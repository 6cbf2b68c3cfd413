"""How a kernel is compiled and cached: the decorators (:func:`jit`, :func:`jit_inline`,
:func:`unit`) and numba's cache location. What gets compiled, when, and how long it takes is
:mod:`mkf_ros.kernels`.

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
The directory is chosen when the first kernel is compiled or loaded, not at import.

The install-time compile (:func:`mkf_ros.kernels.precompile`) puts the kernels into the package
itself (``mkf_ros/_kernels/numba-<hash>/``). A user cache that lacks a kernel is seeded from there
(a file copy, well under a second), so a new user, container or cache directory starts in
seconds. A cache directory that cannot be written is not an error: the kernels go to a private
temporary directory instead (seeded the same way) and one warning says where it looked.

Compile units. numba links the machine code of every compiled function into each compiled
function that calls it, directly or through others, and optimises and compiles it there again
(measured: 3–10 s for each caller of the sensor step). The large kernels are therefore
units (:func:`unit`): each is compiled once, on its own, as a C callable (a numba ``cfunc``),
and its callers receive it as an argument and call it through its address (a few nanoseconds
per call). Its callers' compile no longer includes it, and the units compile independently of each
other.
"""

from __future__ import annotations

import contextvars
import copy
import hashlib
import os
import shutil
import sys
import tempfile
import threading
import warnings
from collections.abc import Callable
from pathlib import Path
from types import FunctionType, SimpleNamespace
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


def prune_old_caches(root: Path, keep_days: float = 7.0) -> None:
    """Best effort: remove caches of other kernel versions unused for ``keep_days``."""
    import time

    try:
        for d in root.glob("numba-*"):
            old = time.time() - d.stat().st_mtime > keep_days * 86400
            if d.name != _VERSION_DIR and old:
                shutil.rmtree(d, ignore_errors=True)
    except OSError:
        pass


_CACHE_DIR: list[Path] = []


def kernel_cache_dir() -> Path:
    """Where this version of the kernels is cached: chosen (and seeded from the install-time
    kernels, and caches of other versions unused for a week removed) on the first call, which
    is the first kernel compiled or loaded."""
    if not _CACHE_DIR:
        prune_old_caches(_cache_root())
        _CACHE_DIR.append(_choose_cache_dir())
    return _CACHE_DIR[0]


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


if KernelCacheLocator not in caching.CacheImpl._locator_classes:
    caching.CacheImpl._locator_classes.insert(0, KernelCacheLocator)

_NUMBA_VERSION = tuple(int(x) for x in numba.__version__.split(".")[:2])
#: Whether kernels run as plain Python (``NUMBA_DISABLE_JIT=1``).
JIT_DISABLED = bool(vars(numba.config)["DISABLE_JIT"])


_CACHE_SETUP = threading.Lock()


class _Dispatcher(CPUDispatcher):
    """numba's dispatcher, compiling one version per argument *types* for calls from compiled
    code too: numba compiles a separate version of a function for each constant (literal)
    argument of a compiled caller (``f(x, True)`` and ``f(x, False)``: two versions; measured:
    up to 10 of one small kernel, a quarter of the compile time). Its cache is set up on the
    first compile or load."""

    def get_call_template(self, args: Any, kws: Any) -> Any:
        return super().get_call_template(tuple(types.unliteral(a) for a in args),
                                         {k: types.unliteral(v) for k, v in kws.items()})

    _cache_wanted = False

    def enable_caching(self) -> None:
        """Caching from the first compile or load on (:meth:`compile`), not from the
        decoration: numba's cache asks for its directory when it is set up, and importing
        the kernels touches no disk."""
        self._cache_wanted = True

    def compile(self, sig: Any) -> Any:
        if self._cache_wanted:  # set up once, before any thread compiles or loads (the
            with _CACHE_SETUP:  # two-way smoother's passes call the same kernels at once)
                if self._cache_wanted:
                    super().enable_caching()
                    self._cache_wanted = False
        return super().compile(sig)


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
        # the C address is the first field of numba's FunctionType value (``addr`` up to
        # numba 0.58, ``c_addr`` since); the others (the Python object, the jit address)
        # stay null: nothing calls a unit but through its C address
        llty = context.get_value_type(ft)
        addr = builder.inttoptr(args[0], llty.elements[0])
        return builder.insert_value(cgutils.get_null_value(llty), addr, 0)

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
#: inline such a call). numba before 0.59 copies the inlined function statement by statement,
#: each copy taking the function's whole variable scope along (time and memory quadratic in its
#: size: 80 CPU-s for :func:`~mkf_ros.core.filter.output` alone, past 8 GB for the sensor
#: step); there these are ordinary kernels, which LLVM may still inline (the same arithmetic in
#: the same order: the same results).
INLINE_AT_IR_LEVEL = _NUMBA_VERSION >= (0, 59)
jit_inline = _kernel("always" if INLINE_AT_IR_LEVEL else "never")


_INLINER_MEMO: contextvars.ContextVar[dict | None] = contextvars.ContextVar(
    "mkf_ros_inliner_memo", default=None)


def _inliner_deepcopy(x: Any, memo: dict | None = None) -> Any:
    """``copy.deepcopy`` for numba's IR inliner, with one memo per inlined call
    (:func:`share_inliner_memo`)."""
    return copy.deepcopy(x, _INLINER_MEMO.get() if memo is None else memo)


def share_inliner_memo() -> bool:
    """numba's IR inliner (``InlineWorker.inline_ir``, numba ≥ 0.59) copies the inlined
    function twice, block by block, each block with a fresh ``copy.deepcopy`` memo: every
    block takes its own copy of the function's whole variable scope (every variable of the
    function and of everything inlined into it), time and memory quadratic in its size
    (numba issue #8989): a quarter of the sensor step's compile. This gives the copies of one
    inlined call one memo, so that the scope is copied once per copy, as ``copy.deepcopy`` of
    the whole function would. The inlined code is the same: the filters' outputs are
    bit-identical, the sensor step's machine code too (the MUKF's differs in the order of two
    calls and its stack layout); the sensor step compiles in about a quarter less CPU time and
    0.1 GB less memory. Returns whether it applied (not on a numba that does not inline at IR
    level or whose inliner is laid out otherwise: that one compiles as before). Called where
    the package compiles (:mod:`mkf_ros.kernels`), not at import: numba stays as it is for a
    program that only imports the package."""
    if not INLINE_AT_IR_LEVEL:
        return False
    from numba.core import inline_closurecall as ic

    worker = getattr(ic, "InlineWorker", None)
    inline_ir = getattr(worker, "inline_ir", None)
    if getattr(inline_ir, "_mkf_ros_shared_memo", False):
        return True  # applied before
    if getattr(ic, "copy", None) is not copy or worker is None or inline_ir is None:
        return False

    def inline_ir_shared(self: Any, *args: Any, **kwargs: Any) -> Any:
        token = _INLINER_MEMO.set({})
        try:
            return inline_ir(self, *args, **kwargs)
        finally:
            _INLINER_MEMO.reset(token)

    inline_ir_shared._mkf_ros_shared_memo = True  # type: ignore[attr-defined]
    # the inliner's module reference to ``copy`` (its only use: that deepcopy)
    ic.copy = SimpleNamespace(  # type: ignore[assignment]
        deepcopy=_inliner_deepcopy, copy=copy.copy)
    worker.inline_ir = inline_ir_shared
    return True

