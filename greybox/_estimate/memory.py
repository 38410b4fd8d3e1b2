"""One memory model for every command that fits: `fit`, `compare`, `fit-many`, `design`.

The peak resident memory of a fit is a fixed base (the interpreter, JAX, XLA's compiled
code) plus a working set that grows with the problem. The working set of one solve (one
device, one start) is dominated by forward-mode sensitivities: every raw parameter carries
one tangent through every state of every ZOH interval and every output of every frame, and
Levenberg-Marquardt keeps the Jacobian and copies of it:

    working = 8 B x FACTOR x [ (p + 1) x sim + 3 x rows x p + 4 x rows ]
    sim     = runs x ( intervals x (x^2 + x u + x + u) + frames x (x + y) )
    rows    = runs x frames x y  (+ priors)

with p raw parameters, x states, u inputs, y outputs. `BASE_BYTES` and `FACTOR` are
calibrated against the measured peak RSS of `greybox fit` child processes
(benchmarks/memory.py, the figures drawn in the fitting process; its last line reports
estimate / measured for five sizes: 0.98 to 1.20 for chevron-laser folders of 2,000 x 1 to
150,000 x 2 frames, 0.45 to 1.08 GB estimated; recalibrated when the solve stopped
simulating its end point a second time: 0.38 to 1.12 GB measured, where the base of 0.50 GB
had put the smallest size at 1.33).
Pure: numbers in, numbers out.
"""

from __future__ import annotations

import math

BASE_BYTES = 0.45e9  # peak RSS of a tiny fit: Python, NumPy, JAX/XLA and the compiled solver
FACTOR = 4.0  # XLA temporaries and copies per byte of the formula (benchmarks/memory.py)
INTERVALS_PER_FRAME = 2  # ZOH intervals per frame when only the frame count is known


def solve_bytes(
    *,
    runs: int,
    frames: int,
    states: int,
    outputs: int,
    inputs: int,
    raw: int,
    intervals: int | None = None,
    priors: int = 0,
    associative_scan: bool = False,
) -> float:
    """Working bytes of one solve (see the module docstring); `frames`/`intervals` per run,
    padded to the longest run."""
    intervals = INTERVALS_PER_FRAME * frames if intervals is None else intervals
    x, u, y, p = states, inputs, outputs, raw
    rows = runs * frames * y + priors
    sim = runs * (intervals * (x * x + x * u + x + u) + frames * (x + y))
    if associative_scan:  # its up- and down-sweeps keep about two more copies of the maps
        sim += runs * intervals * 2 * (x * x + x)
    return 8.0 * FACTOR * ((p + 1) * sim + 3 * rows * p + 4 * rows)


def peak_bytes(working: float, items: int = 1) -> float:
    """Peak resident bytes of a process solving `items` solves of `working` bytes at once."""
    return BASE_BYTES + items * working


def format_gb(n: float) -> str:
    return f"{n / 1e9:.2f} GB" if math.isfinite(n) else "unbounded"
