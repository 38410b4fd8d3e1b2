"""One BLAS thread for the small linear algebra of a fit.

A fit calls LAPACK on tall, narrow matrices: the compiled solver's steps (jaxlib's LAPACK is
scipy's OpenBLAS) and the host's assembly (the identifiability QR, the model-error least
squares, the HAC meat), a few thousand rows by a few columns. OpenBLAS splits a call over its
threads once rows x columns passes about 9,000 elements, and on a machine whose cores are busy
(XLA's own threads, other processes) each split call waits for its threads: on 2 shared cores
a 3,072 x 8 QR took 24 ms instead of 0.3 ms, and a warm ZOH fit of the chevron set (six runs,
2,004 frames) 450 ms instead of 57 ms. Up to `SMALL` elements the work is too little to gain
from threads, so `fit` and `fit_batch` (their solves and assembly) run under
`small_blas(size)`, which holds BLAS to one thread there (threadpoolctl, restored on exit);
above it, it changes nothing.
Results are the same LAPACK routines' (to rounding).
"""

from __future__ import annotations

import contextlib
import functools

from threadpoolctl import ThreadpoolController

SMALL = 1 << 22  # elements (32 MB of float64) up to which one thread is faster in practice


@functools.cache
def _controller() -> ThreadpoolController:
    """The process's thread pools, inspected once (~0.3 ms; a limit from it costs ~3 us)."""
    return ThreadpoolController()


def small_blas(size: int):
    """Context manager: one BLAS thread when the largest matrix has at most SMALL elements."""
    if int(size) > SMALL:
        return contextlib.nullcontext()
    return _controller().limit(limits=1, user_api="blas")
