"""numpy's exp, expm1 and log computed by the C library, as the compiled kernels compute them.

A kernel (``stage.engine.jit``) is held to its numpy reference bit for bit: the same
operations in the same order. Its ``math.exp``, ``math.expm1`` and ``math.log`` are the C
library's, and numpy's are its own vectorised code, which on CPUs with AVX-512 differs from
the C library's in the last bit for some inputs (numpy 1.26 on CI's machines: about a quarter
of them; 2.4: a few per cent). Inside ``c_library_math()`` numpy's three functions are the C
library's, element by element, so a reference computed there is what the kernel must give
to the bit.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np

_NUMPY = {"exp": np.exp, "expm1": np.expm1, "log": np.log}


def _element(name: str):
    c, npf = getattr(math, name), _NUMPY[name]

    def one(x: float) -> float:
        try:
            return c(x)
        except (ValueError, OverflowError):      # log(0), log(-1), exp(1000): numpy's value
            with np.errstate(all="ignore"):
                return float(npf(x))

    each = np.vectorize(one, otypes=[float])

    def call(x, out=None):
        got = each(x)
        if out is None:
            return got if np.ndim(got) else float(got)
        out[...] = got
        return out
    return call


@contextlib.contextmanager
def c_library_math():
    """numpy's exp, expm1 and log replaced by the C library's while inside."""
    try:
        for name in _NUMPY:
            setattr(np, name, _element(name))
        yield
    finally:
        for name, f in _NUMPY.items():
            setattr(np, name, f)
