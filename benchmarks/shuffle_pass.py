"""The residual tests' shuffle pass: numpy (what greybox runs) vs one compiled JAX kernel.

The largest single cost of a batch's residual tests (issue 24, item 3) is the permutation
null of the Ljung-Box test: for every run, r(1..h) of 999 within-run shuffles of its
residuals on the frame grid (`greybox._estimate.residuals._permuted_autocorrelation`,
single precision, blocked to stay in cache). This script times that pass on `--runs`
synthetic runs of ~50 frames with 5 % dropped (a batch of 512 six-run devices is 3,072), and
the same work as one jitted kernel on JAX's default backend: the same cached shuffle orders
(a table of the distinct order matrices, one index per run, as a batch's devices share
them), each run's shuffles gathered, placed on its grid and its h lag products summed,
vmapped over 16 runs and `lax.map`ped over the rest. Both give the same r(k) to single
precision (`max_abs_diff`). Reported: `numpy_s`, `compiled_s` (warm), `compiled_first_s`
(compile included), `compiled_speedup` = numpy_s / compiled_s, `backend`.

Measured (2-core CPU, quiet, 2026-11-27; 3,072 runs): numpy 0.82-0.90 s, compiled 1.46-1.60 s
(first call 2.0 s; compiled_speedup 0.56): on a CPU, compiling the residual tests would not
make a batch faster, it would only move their time into compiled code. On an accelerator
this kernel is what would scale (not measured: no device was lent).

Usage: .venv/bin/python benchmarks/shuffle_pass.py [--runs 3072] [--smoke]
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

from greybox._estimate import residuals as R  # noqa: E402

SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"
LAGS = 10  # the test's lags (`residuals.TEST_LAG`)
PER_CALL = 16  # runs vmapped together inside the kernel


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
    return [job for _, jobs in R._pending_runs(specs, shuffles) for job in jobs]


def kernel_inputs(jobs, shuffles: int) -> tuple:
    """(values, slots, order index, order table, pair counts, bias) of `jobs`, padded."""
    width = max(j.g.size for j in jobs)
    n_max = max(int(j.occ.sum()) for j in jobs)
    n_pad = -len(jobs) % PER_CALL
    count = len(jobs) + n_pad
    vals = np.zeros((count, n_max), np.float32)
    slots = np.full((count, n_max), width, np.int32)  # padding lands in a dropped column
    npairs, bias = np.ones((count, LAGS)), np.zeros((count, 1))
    index, keys = np.zeros(count, np.int32), {}
    for i, job in enumerate(jobs):
        s = np.flatnonzero(job.occ)
        vals[i, : s.size], slots[i, : s.size] = job.unit[s], s
        npairs[i, : job.npairs.size] = np.maximum(job.npairs, 1)
        bias[i] = 1.0 / (job.n - 1)
        index[i] = keys.setdefault((job.key, s.size), len(keys))
    table = np.zeros((len(keys), shuffles, n_max), np.int32)
    for (key, n), k in keys.items():
        table[k, :, :n] = R._shuffle_orders(key, n, shuffles)
        table[k, :, n:] = np.arange(n, n_max)
    return width, (vals, slots, index, table, npairs, bias)


def compiled_pass(width: int, shuffles: int):
    """The jitted kernel: r(1..LAGS) (runs, shuffles, LAGS) of every run's shuffles."""

    def one(v, sl, order, npr, b):
        grid = jnp.zeros((shuffles, width + 1), jnp.float32).at[:, sl].set(v[order])[:, :width]
        sums = [jnp.sum(grid[:, k:] * grid[:, : width - k], axis=1) for k in range(1, LAGS + 1)]
        return jnp.stack(sums, axis=1) / npr + b

    @jax.jit
    def run(vals, slots, index, table, npairs, bias):
        def chunk(a):
            v, sl, ix, npr, b = a
            return jax.vmap(lambda *x: one(x[0], x[1], table[x[2]], x[3], x[4]))(v, sl, ix, npr, b)

        parts = [x.reshape(-1, PER_CALL, *x.shape[1:]) for x in (vals, slots, index, npairs, bias)]
        out = jax.lax.map(chunk, tuple(parts))
        return out.reshape(-1, shuffles, LAGS)

    return run


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
        R._permuted_autocorrelation(jobs, args.shuffles)
        times.append(time.perf_counter() - t0)
    numpy_s = min(times)
    reference = np.stack([job.out[1:] for job in jobs])
    width, inputs = kernel_inputs(jobs, args.shuffles)
    run = compiled_pass(width, args.shuffles)
    inputs = jax.device_put(inputs)
    t0 = time.perf_counter()
    jax.block_until_ready(run(*inputs))
    first_s = time.perf_counter() - t0
    times = []
    for _ in range(3):
        t0 = time.perf_counter()
        out = jax.block_until_ready(run(*inputs))
        times.append(time.perf_counter() - t0)
    compiled_s = min(times)
    got = np.asarray(out)[: len(jobs)]
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
