"""The residual tests' shuffle pass: numpy's blocks (a CPU) vs the compiled kernel (an accelerator).

The largest single cost of a batch's residual tests (issue 24, item 3) is the permutation
null of the Ljung-Box test: for every run, r(1..h) of 999 within-run shuffles of its
residuals on the frame grid (`greybox._estimate.residuals._permuted_autocorrelation`,
single precision). greybox runs it as numpy blocks that stay in cache on a CPU
(`residuals._numpy_shuffles`) and as one jitted kernel on an accelerator
(`greybox._estimate.shuffle_kernel.fill`: the same cached shuffle orders, a table of the
distinct ones, each run's shuffles gathered, placed on its grid and its h lag products
summed, runs vmapped in blocks). This script times both on `--runs` synthetic runs of ~50
frames with 5 % dropped (a batch of 512 six-run devices is 3,072) on JAX's default backend;
the kernel's time includes packing its inputs and bringing its result back. Both give the
same r(k) to single precision (`max_abs_diff`). Reported: `numpy_s`, `compiled_s` (warm),
`compiled_first_s` (compile included), `compiled_speedup` = numpy_s / compiled_s, `backend`.

Measured (2-core CPU, quiet, 2026-11-27; 3,072 runs, the kernel then in this script): numpy
0.82-0.90 s, compiled 1.46-1.60 s (first call 2.0 s; compiled_speedup 0.56), which is why a
CPU runs numpy's blocks. 2026-11-28, the kernel moved into the library and sized for an
accelerator (blocks of ~500 runs vmapped together, sizes rounded up to powers of two): numpy
0.90-0.92 s, compiled 4.00 s (first call 4.5-4.6 s, of it 0.14 s packing the inputs;
compiled_speedup 0.23), max_abs_diff 1.7e-7. On an accelerator: not measured (no device was
lent to this session); run this script there. 2026-11-28, numpy's pass taking the jobs of one
shuffle stream and count of values (one run of many devices) one after another, so each
cached order table is gathered from while it is in cache: numpy 0.87 -> 0.68-0.74 s (the
gathers 0.25 -> 0.14 s), the same r(k). 2026-11-29: a test's shuffles now come in two stages
(99 each, the other 900 only where those leave p below 0.11: `residuals._shuffle_tests`),
so a batch draws about a third of the shuffles this script times; the two ways of running a
pass are compared here on a full 999, as before.

Usage: .venv/bin/python benchmarks/shuffle_pass.py [--runs 3072] [--smoke]
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

from greybox._estimate import residuals as R  # noqa: E402
from greybox._estimate import shuffle_kernel  # noqa: E402

SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"
LAGS = 10  # the test's lags (`residuals.TEST_LAG`)


def synthetic_jobs(n_runs: int, shuffles: int, seed: int = 0) -> list:
    """The shuffle jobs of `n_runs` runs of 50-53 frames at 30 fps, 5 % dropped, white
    residuals; six run keys (as six runs per device)."""
    rng = np.random.default_rng(seed)
    specs = []
    for j in range(n_runs):
        t = np.arange(50 + rng.integers(0, 4)) / 30.0
        t = t[rng.random(t.size) > 0.05]
        e = rng.standard_normal((t.size, 1))
        specs.append((f"r{j % 6}", t, e, np.ones_like(e, bool), None, 25, LAGS, (0, j % 6)))
    return [job for _, jobs in R._pending_runs(specs, shuffles)[0] for job in jobs]


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=int, default=3072)
    ap.add_argument("--shuffles", type=int, default=R.PERMUTATIONS)
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args(argv)
    if args.smoke:
        args.runs, args.shuffles = 32, 99
    jobs = synthetic_jobs(args.runs, args.shuffles)
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        R._numpy_shuffles(jobs, range(args.shuffles))
        times.append(time.perf_counter() - t0)
    numpy_s = min(times)
    reference = np.stack([job.out[1:] for job in jobs])
    orders = R._orders_of(range(args.shuffles), args.shuffles)
    t0 = time.perf_counter()
    shuffle_kernel.fill(jobs, range(args.shuffles), orders)
    first_s = time.perf_counter() - t0
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        shuffle_kernel.fill(jobs, range(args.shuffles), orders)
        times.append(time.perf_counter() - t0)
    compiled_s = min(times)
    got = np.stack([job.out[1:] for job in jobs])
    diff = float(np.nanmax(np.abs(got - reference)))
    print(
        json.dumps(
            {
                "backend": jax.default_backend(),
                "runs": len(jobs),
                "shuffles": args.shuffles,
                "numpy_s": round(numpy_s, 4),
                "compiled_s": round(compiled_s, 4),
                "compiled_first_s": round(first_s, 3),
                "compiled_speedup": round(numpy_s / compiled_s, 3),
                "max_abs_diff": diff,
            }
        )
    )


if __name__ == "__main__":
    main()
