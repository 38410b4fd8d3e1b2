"""The starts of a multi-start fit (least squares or likelihood), side by side on a CPU's
cores.

A fit's starts are independent solves of one compiled function. The first runs alone (its
call compiles the solver); the others then run in threads, as many at a time as the process
has cores (`usable_cores`: one inside a Dask worker), since a compiled call releases the
interpreter. Each solve is the same compiled program on the same inputs, so the estimates
are those of the starts run one after another, bit for bit. `greybox fit`'s memory
pre-check counts one solve at a time, so the starts side by side may together take at most
`SIDE_BY_SIDE_BYTES` more (each solve's working set from `problem.solve_bytes`); on an
accelerator they run one after another (one device, nothing to share).

Measured (2-core CPU): the micro-robot folder's 4-start fit, warm, 3.4 -> 2.6 s;
`benchmarks/compare.py` (four chevron candidates, three of them multi-start) 67.5 -> 54.3 s
wall at the same processor time (87 and 85 s), every AIC and verdict identical.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

from greybox._platform import on_accelerator, usable_cores

SIDE_BY_SIDE_BYTES = 1e9  # working memory the starts run side by side may add, together


def run_starts(
    solve: Callable, starts: Sequence, announce: Callable, report: Callable, solve_bytes: float
) -> list:
    """[solve(start) for start in starts], with `announce(i)` before start i is begun and
    `report(i, output)` after it has ended, both called from this thread in start order;
    `solve_bytes`: one solve's working memory."""
    announce(0)
    runs = [solve(starts[0])]
    report(0, runs[0])
    rest = range(1, len(starts))
    fit_in = int(SIDE_BY_SIDE_BYTES // max(float(solve_bytes), 1.0))
    workers = 1 if on_accelerator() else min(len(rest), usable_cores(), fit_in)
    if workers <= 1:
        for i in rest:
            announce(i)
            runs.append(solve(starts[i]))
            report(i, runs[-1])
        return runs
    pool = ThreadPoolExecutor(workers, thread_name_prefix="greybox-start")
    try:
        futures = []
        for i in rest:
            announce(i)
            futures.append(pool.submit(solve, starts[i]))
        for i, future in zip(rest, futures):
            runs.append(future.result())
            report(i, runs[-1])
    finally:  # an interrupt: the starts not yet begun are dropped, not waited for
        pool.shutdown(wait=False, cancel_futures=True)
    return runs
