"""Does a solve's result depend on the batch it rides in? 8 solves alone and inside 1,000.

The chevron problems of `benchmarks/gpu_many_devices.py` (a recorded pool, every further
device a copy with fresh noise) are solved through the compiled chunk solver
(`_batch._solve_many`; vmapped on an accelerator, and on a CPU with `--vmapped`) twice:
the first `--small` of them in one call of that size, and all `--large` in one call.
Inside `jax.vmap`, Levenberg-Marquardt's while loop runs until every member has stopped;
a member that has stopped must keep its iterate, step count, damping and verdict frozen.
Reported: the largest relative difference of the raw estimates (`max_rel`), how many of
the small batch's step counts and verdicts differ inside the large one (`steps_differ`,
`ok_differ`; all should be 0), and the step counts' spread in the large batch (its members
do stop at different steps). `tests/test_batch_independence.py` is the same check at 8
against 64, both ways.

Measured (2-core CPU, 2026-11-26): one solve after another (a CPU's chunks): max_rel 0.0,
no step count differs. `--vmapped` (an accelerator's path: vmapped, the Householder step
QR): max_rel 1.0e-11 and one step count of 8 differs (16 alone, 13 inside 1,000), all
verdicts the same; vmapped with LAPACK's QR instead: 0.0. XLA does not promise that a
vmapped reduction sums in the same order whatever the batch size, so on an accelerator a
solve is batch-independent to rounding, not bit for bit (an H200, 64 solves alone against
inside 10,923: 8.2e-9, 5 of 64 counts; `gpu_many_devices.py`).

Usage: .venv/bin/python benchmarks/batch_independence.py [--large 1000] [--smoke]
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import gpu_many_devices as gpu  # noqa: E402
import many_devices as md  # noqa: E402

import greybox._platform  # noqa: E402
from greybox._estimate import batch as _batch  # noqa: E402
from greybox._estimate import fit as _fit  # noqa: E402

SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--small", type=int, default=8)
    ap.add_argument("--large", type=int, default=1000)
    ap.add_argument("--pool", type=int, default=16)
    ap.add_argument(
        "--vmapped",
        action="store_true",
        help="on a CPU, solve as an accelerator does (vmapped, its step QR); a CPU's own "
        "chunks run their solves one after another, which cannot depend on the batch",
    )
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args(argv)
    if args.vmapped:
        greybox._platform.on_accelerator = lambda: True
    if args.smoke:
        args.large, args.pool = 16, 4
    free = tuple(md.SPEC.free_parameters())
    pool, cleans = gpu.pool_devices(args.pool)
    prepared, (group,) = _batch._prepare(
        pool, free, None, "huber", 1.5, 4.0, None, 1, 0, (1e-8, 1e-10, 16384)
    )
    rows, noisy = gpu.replicated_readings(group, cleans, args.large)
    stacked = jax.tree.map(lambda x: np.take(x, rows, axis=0), group.stacked)
    stacked = eqx.tree_at(lambda p: p.y, stacked, noisy)
    raw = np.stack([prepared[r].raw0 for r in rows])
    sig = np.stack([prepared[r].sigma0 for r in rows])
    opts = _fit.solver_settings(1e-6, 1e-6, 200)  # as `fit_batch` passes them
    small = jax.tree.map(lambda x: x[: args.small], stacked)
    t0 = time.perf_counter()
    alone = gpu.solve_all(group, small, raw[: args.small], sig[: args.small], args.small, opts)
    t_small = time.perf_counter() - t0
    t0 = time.perf_counter()
    inside = gpu.solve_all(group, stacked, raw, sig, args.large, opts)
    t_large = time.perf_counter() - t0
    diff = np.abs(alone["raw"] - inside["raw"][: args.small])
    out = {
        "backend": jax.default_backend(),
        "mode": "vmapped" if greybox._platform.on_accelerator() else "one after another",
        "small": args.small,
        "large": args.large,
        "max_rel": float(np.max(diff / np.maximum(np.abs(alone["raw"]), 1e-12))),
        "steps_differ": int(np.sum(alone["steps"] != inside["steps"][: args.small])),
        "ok_differ": int(np.sum(alone["ok"] != inside["ok"][: args.small])),
        "steps_small": [int(s) for s in alone["steps"]],
        "steps_large_min_max": [int(inside["steps"].min()), int(inside["steps"].max())],
        "not_ok_large": int(np.sum(~inside["ok"].astype(bool))),
        "small_s": round(t_small, 2),
        "large_s": round(t_large, 2),
        "load_average": round(os.getloadavg()[0], 2),
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
