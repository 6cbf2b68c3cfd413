"""The simulator's one compiled kernel: the attitude integration of :mod:`mkf_ros.sim.motion`
carried across chunks of the fine rate grid.

It reproduces, operation for operation, the blocked prefix product the simulator has always
used (blocks of ``b = isqrt(M)`` fine steps for a recording of ``M`` steps: a sequential product
inside each block, the block's attitude at its start, a "head", chained from the block totals
and renormalised, and each output ``normalize(head ⊗ prefix)``), so a recording does not depend
on how it is cut into chunks and is bit for bit the whole-recording result. The state carried
from one chunk to the next is the current head and the prefix product inside the current block.
"""

from __future__ import annotations

import math

import numpy as np

from mkf_ros.core._jit import jit


@jit
def integrate_chunk(dq: np.ndarray, j0: int, block: int, every: int, head: np.ndarray,
                    prefix: np.ndarray, out: np.ndarray) -> int:
    """Advance the attitude over the fine steps ``j0 .. j0 + len(dq) - 1`` of a recording
    whose prefix product uses blocks of ``block`` steps.

    ``dq`` (F, 4): the step rotations; ``head`` (4,) and ``prefix`` (4,): the carried state
    (updated in place; at ``j0 = 0`` the head is the initial attitude and ``prefix`` is unused).
    The attitude after every fine step ``j`` with ``(j + 1) % every == 0`` (the sample instants)
    is written to the next row of ``out``; returns the number of rows written."""
    hw, hx, hy, hz = head[0], head[1], head[2], head[3]
    pw, px, py, pz = prefix[0], prefix[1], prefix[2], prefix[3]
    k = 0
    for i in range(dq.shape[0]):
        j = j0 + i
        qw, qx, qy, qz = dq[i, 0], dq[i, 1], dq[i, 2], dq[i, 3]
        if j % block == 0:
            if j > 0:  # the block that ended moves the head (renormalised)
                hw, hx, hy, hz = (hw * pw - hx * px - hy * py - hz * pz,
                                  hw * px + hx * pw + hy * pz - hz * py,
                                  hw * py + hy * pw + hz * px - hx * pz,
                                  hw * pz + hz * pw + hx * py - hy * px)
                s = 1.0 / math.sqrt(hw * hw + hx * hx + hy * hy + hz * hz)
                hw, hx, hy, hz = hw * s, hx * s, hy * s, hz * s
            pw, px, py, pz = qw, qx, qy, qz
        else:
            pw, px, py, pz = (pw * qw - px * qx - py * qy - pz * qz,
                              pw * qx + px * qw + py * qz - pz * qy,
                              pw * qy + py * qw + pz * qx - px * qz,
                              pw * qz + pz * qw + px * qy - py * qx)
        if (j + 1) % every == 0:
            ow = hw * pw - hx * px - hy * py - hz * pz
            ox = hw * px + hx * pw + hy * pz - hz * py
            oy = hw * py + hy * pw + hz * px - hx * pz
            oz = hw * pz + hz * pw + hx * py - hy * px
            n = np.sqrt(ow * ow + ox * ox + oy * oy + oz * oz)
            out[k, 0] = ow / n
            out[k, 1] = ox / n
            out[k, 2] = oy / n
            out[k, 3] = oz / n
            k += 1
    head[0], head[1], head[2], head[3] = hw, hx, hy, hz
    prefix[0], prefix[1], prefix[2], prefix[3] = pw, px, py, pz
    return k
