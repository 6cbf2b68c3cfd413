"""The one place that decides how kernels are compiled.

Every numerical kernel in :mod:`mkf_ros.core` is a plain Python function decorated with
:func:`jit`. With numba available they are compiled once (and cached on disk); with
``NUMBA_DISABLE_JIT=1`` they run as ordinary Python, which is how a researcher can step through
the equations in a debugger.
"""

from __future__ import annotations

import numba

#: Compile options shared by every kernel: no Python objects, cached, GIL released.
jit = numba.njit(cache=True, nogil=True, error_model="numpy")
