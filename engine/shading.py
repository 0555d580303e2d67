"""Building blocks the engine's shading kernels share (reference renderer, view pass, relighting).

- :class:`DualKernel`: one kernel source compiled twice, parallel and serial (both nogil), so a
  caller that runs several pipelines in Python threads picks the serial one;
- :func:`phong_pow`: ``cos^s`` of the Phong lobe without 0/0 or overflow for huge exponents.
"""

from __future__ import annotations

import math
import types

import numba as nb

from engine import _numba_setup  # noqa: F401  (numba's configuration before any kernel)


class DualKernel:
    """One kernel source, compiled twice: ``par`` (parallel over prange, for a single pipeline) and
    ``ser`` (serial, nogil, for several pipelines in threads: the workqueue threading layer must not
    be entered from two threads at once). Both release the GIL, so one pipeline's kernel runs while
    another holds the GIL (e.g. inside Embree). Use as a decorator or ``DualKernel(fn)``; call
    ``.pick(serial)``."""

    def __init__(self, fn):
        self.par = nb.njit(cache=True, parallel=True, nogil=True, error_model="numpy")(fn)
        ser = types.FunctionType(fn.__code__, fn.__globals__, fn.__name__ + "_serial", fn.__defaults__,
                                 fn.__closure__)
        ser.__qualname__ = fn.__qualname__ + "_serial"  # its own on-disk cache entry
        ser.__module__ = fn.__module__
        ser.__doc__ = fn.__doc__
        self.ser = nb.njit(cache=True, nogil=True, error_model="numpy")(ser)

    def pick(self, serial: bool):
        """The serial compilation when ``serial``, else the parallel one."""
        return self.ser if serial else self.par


@nb.njit(cache=True, inline="always", error_model="numpy")
def phong_pow(c, s):
    """``c^s`` for a cosine c and a Phong exponent s >= 0: 0 for c <= 0, 1 for c >= 1 (no 0/0 at
    c = 0, s = 0 and no overflow for huge s; docs/hard-cases.md #8), else ``exp(s log c)``."""
    if c <= 0.0:
        return 0.0
    if c >= 1.0:
        return 1.0
    return math.exp(s * math.log(c))
