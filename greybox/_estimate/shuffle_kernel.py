"""The residual tests' shuffle pass as one compiled kernel: what runs on an accelerator.

`residuals._permuted_autocorrelation` fills, for every run and output of a fit or a batch of
devices, r(1..h) of its within-run shuffles (the first 99, then the rest of the 999 where
those leave the test undecided). On a CPU numpy does it (blocks that stay in
cache; a jitted kernel on XLA's CPU back end took 1.5-4.0 s, by how many runs it vmaps
together, where numpy took 0.8-0.9 s for 3,072 runs, `benchmarks/shuffle_pass.py`). On an
accelerator that numpy pass was the largest share of a batch's host work (an H200 box,
`fit_distributed` with 15 workers: 7.9 of the 14.3 ms a device took), while the kernel is a
few gathers and products per run, so there a batch's pass runs compiled
(`residuals._compiled_shuffles`).

The kernel does what the numpy blocks do, with the same shuffles: each job's occupied values
(unit variance, single precision), the cached rank orders of its stream
(`residuals._shuffle_orders`, one table of the distinct ones, shared by the runs of every
device whose stream and number of readings agree), each shuffle placed back on the job's
occupied slots (the gaps stay where they are), its lagged products summed, divided by the
pair counts, plus the mean-removal bias 1 / (n - 1). Sizes are rounded up (powers of two), so
the waves of a batch share a few compiled shapes; padding is inert (zero values, a slot past
the grid's end, unit pair counts). Single precision, as numpy's pass: the r(k) agree to
~1e-7, and a p-value could differ only where a shuffle's Q ties the observed one to ~1e-6.
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jax_jit

BLOCK_ELEMENTS = 1 << 25  # grid elements (single precision) of the runs vmapped together
CALL_ELEMENTS = 1 << 26  # elements of one call's order table and of its results, each


def _pow2(n: int, least: int = 1) -> int:
    """The least power of two >= n (and >= `least`)."""
    return max(least, 1 << max(int(n) - 1, 0).bit_length())


def _pow2_within(n: int) -> int:
    """The largest power of two <= n (1 for n < 2)."""
    return 1 << (max(int(n), 1).bit_length() - 1)


def fill(jobs, shuffles: range, orders) -> None:
    """Write rows 1 + `shuffles` of each job's `out` (r(1..h_j) of those of its shuffles);
    `orders(key, n)` gives the (len(shuffles), n) rank orders of those shuffles of a stream
    (`residuals._orders_of`: slices of `residuals._shuffle_orders`, or a draw of the same
    stream where that declines to cache)."""
    b = len(shuffles)
    if not jobs or not b:
        return
    width = _pow2(max(job.g.size for job in jobs), 16)
    n_max = _pow2(max(job.order_key[1] for job in jobs), 16)
    h = max(job.npairs.size for job in jobs)
    rows = slice(1 + shuffles.start, 1 + shuffles.stop)
    for part in _calls(jobs, b, n_max, h):
        _fill_call(part, b, orders, width, n_max, h, rows)


def _calls(jobs, b: int, n_max: int, h: int):
    """`jobs` in calls whose order table (distinct streams x B x n_max) and results (runs x
    B x h, padded) stay within CALL_ELEMENTS each: long runs with readings dropped at random
    (a stream per run and reading count) must not make one table of gigabytes. One call for
    a batch's wave of short runs (64 chevron devices: 384 runs, ~60 streams)."""
    max_keys = max(1, CALL_ELEMENTS // (b * n_max))
    max_jobs = _pow2_within(CALL_ELEMENTS // (b * h))  # a power of two: padded, at most this
    part, keys = [], set()
    for job in sorted(jobs, key=lambda j: j.order_key):
        key = job.order_key
        if part and (len(part) == max_jobs or (key not in keys and len(keys) == max_keys)):
            yield part
            part, keys = [], set()
        part.append(job)
        keys.add(key)
    yield part


def _fill_call(jobs, b: int, orders, width: int, n_max: int, h: int, rows: slice) -> None:
    """One kernel call for `jobs` (grids of at most `width` slots, at most `n_max` readings,
    `h` lags, `b` shuffles): inputs padded to powers of two, the result written into `rows`
    of each job's `out`."""
    per_call = min(_pow2_within(BLOCK_ELEMENTS // (b * (width + 1))), _pow2(len(jobs)))
    count = per_call * _pow2(-(-len(jobs) // per_call))
    vals = np.zeros((count, n_max), np.float32)
    slots = np.full((count, n_max), width, np.int32)  # padding lands past the grid's end
    npairs, bias = np.ones((count, h), np.float32), np.zeros((count, 1), np.float32)
    index, keys = np.zeros(count, np.int32), {}
    for i, job in enumerate(jobs):
        s = job.slot_runs[0]
        vals[i, : s.size], slots[i, : s.size] = job.unit[s], s
        npairs[i, : job.npairs.size] = np.maximum(job.npairs, 1)
        bias[i] = 1.0 / (job.n - 1)
        index[i] = keys.setdefault(job.order_key, len(keys))
    table = np.zeros((_pow2(len(keys)), b, n_max), np.int32)
    for (key, n), k in keys.items():
        table[k, :, :n] = orders(key, n)
        table[k, :, n:] = np.arange(n, n_max)  # padding values (zeros) stay in padding slots
    out = np.asarray(_kernel(width, h, per_call)(vals, slots, index, table, npairs, bias))
    for i, job in enumerate(jobs):
        job.out[rows, : job.npairs.size] = out[i, :, : job.npairs.size]


@functools.cache
def _kernel(width: int, h: int, per_call: int):
    """The jitted pass for grids of `width` slots and `h` lags, `per_call` runs vmapped
    together and the blocks of them one after another (`lax.map`: bounded memory)."""

    def one(v, sl, order, npr, bias):
        b = order.shape[0]
        grid = jnp.zeros((b, width + 1), jnp.float32).at[:, sl].set(v[order])[:, :width]
        sums = [jnp.sum(grid[:, k:] * grid[:, : width - k], axis=1) for k in range(1, h + 1)]
        return jnp.stack(sums, axis=1) / npr + bias

    @jax_jit
    def run(vals, slots, index, table, npairs, bias):
        def block(a):
            return jax.vmap(lambda v, sl, ix, npr, bi: one(v, sl, table[ix], npr, bi))(*a)

        parts = [x.reshape(-1, per_call, *x.shape[1:]) for x in (vals, slots, index, npairs, bias)]
        out = jax.lax.map(block, tuple(parts))
        return out.reshape(-1, table.shape[1], h)

    return run
