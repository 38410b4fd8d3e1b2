"""Many chevron fits on an accelerator: 32,768 devices, and the same estimates as the CPU.

Meant for one GPU (H100/H200; one device window, under 8 minutes); `--smoke` runs the same
path on a CPU at the smallest size. The devices are those of `benchmarks/many_devices.py`
(six short pulse-train runs each): `--pool` of them are recorded by `greybox.waveforms.record` with
their parameters drawn from the known population, and every further device is one of them
with fresh measurement noise on the same clean signal and dropped frames (so that making
32,768 devices takes seconds, not the half hour of recording each).

Measured, on the default JAX backend (`backend`):

- `solve_fits_per_min`: `--devices` Levenberg-Marquardt solves (one start per device, at the
  first noise scale) through the compiled, vmapped solver, chunked by the device's memory
  (`_batch.device_budget`, chunks evened out); the problems are stacked once (the replicated
  devices gather the pool's rows and add their noise in one numpy operation); a first chunk
  alone compiles (`solve_first_chunk_s`, compile and that chunk's solves), then every chunk
  is timed warm;
- `batch_fits_per_min`: complete `fit_batch` fits (everything it returns) of `--complete`
  devices, warm (the first call, reported as `batch_first_s`, compiles);
- `cpu_agreement_max_rel`: the largest relative difference of any parameter estimate between
  `fit_batch` on this backend and on the CPU (`jax.devices("cpu")`) for the first
  `--check` devices (target 1e-6);
- `batch_independence_max_rel`, `batch_independence_steps_differ`: the first 64 solves
  inside the big batch against the same solves in a batch of 64 (a solve must not depend
  on the batch it rides in);
- with `--process N` (not in `--smoke`): `process_fits_per_min`, `fit_batch` with process
  noise (the batched likelihood back end) of N scalar Ornstein-Uhlenbeck devices, warm, and
  `process_cpu_agreement_max_rel` against the CPU for the first `--check`;
- `step_qr_speedup`: one chunk of solves, warm, with LAPACK's QR in each Levenberg-Marquardt
  step (`lx.QR`, `solve_chunk_lapack_qr_s`) over the same chunk with this backend's own
  (`householder.lm_linear_solver`: the vectorised Householder QR on an accelerator,
  `solve_chunk_warm_s`).
- `shuffle_pass`: how this process runs a batch's residual tests (999 shuffles per run;
  from 2026-11-29 99, and the other 900 where those leave p below 0.11): "compiled" on an
  accelerator for a pass of a batch's size (`greybox._estimate.shuffle_kernel`, from
  2026-11-28; the figures below predate it and ran numpy's blocks there), "numpy" on a CPU.

Each phase prints its figures as soon as it ends (a `partial` line on stderr), so a run cut
off by its device window still reports what it measured.

Measured on one NVIDIA H200 (jax 0.11.2, float64; 2026-11-26, two runs in one session):

| | LAPACK step QR (before) | Householder step QR |
|---|---|---|
| 32,768 solves, warm (3 chunks of 10,923) | 77.5 s: 25,384 solves/min | 4.6 s: 426,974 solves/min |
| first chunk (compile + solve) | 33.3 s | 9.8 s |
| one chunk warm, same run (`step_qr_speedup`) | 30.3 s | 1.4 s (21.9x) |
| complete `fit_batch` of 1,024, warm | 21.0 s: 2,922 fits/min | 13.6 s: 4,509 fits/min |
| agreement with the CPU (16 devices) | 5.2e-15 | 2.0e-13 (CPU: LAPACK QR, sequential scan) |
| 64 solves alone vs in the big batch | 8.9e-16, 1 step count differs | 8.2e-9, 5 differ |

All 32,768 solves converged in both. A third run (same day, same kind of card, `--devices 1024
--complete 64 --check 4 --process 512`): 1,024 solves 481,333/min (one chunk), the step QR
17.0x LAPACK's at that chunk; process noise: 512 Ornstein-Uhlenbeck devices, two starts
each, 1,086 complete fits/min warm (28.3 s; first call 35.2 s), all converged, the CPU's
estimates to 5.6e-13 (the 2-core CPU here: 503 fits/min at 128 devices). In that run
`benchmarks/batch_independence.py` (8 solves alone and inside 1,000, vmapped) gave 0.0 and no
step count differing. The complete batch is bound by its host phases
(prepare 2.8 s, residual tests 5.8 s, assembly 3.6 s of interpreter time for 1,024 devices,
against 0.1 s of solving): 4,509 complete fits/min, not the 50,000 the issue asks for.

Then (2026-11-27, H200 box, jax 0.11.2), the host work written as stacked passes over runs
(residual tests, HAC, scoring), results without their shuffle matrices, shuffle blocks in
threads. One call, `--devices 2048 --complete 2048 --check 4`, 31fecb3 against this work
before the threads: complete fits 4,209 -> 6,320 /min (warm 29.2 -> 19.4 s; residual tests
12.2 -> 8.6 s, assembly 11.0 -> 5.2 s, prepare 3.3 s in both). With the threads (a later
call): 7,050 /min at 2,048 (residual tests 6.2 s) and 7,189 /min at 8,192 (warm 68 s: prepare
12.2, residual tests 27.4, models 5.7, assembly 18.9, solves 0.9 s); the CPU's estimates to
5.2e-15; 8,192 solves 512,119 /min, all converged. Still host-bound, ~7 ms of interpreter
work per device: 50,000 /min needs the assembly compiled and vmapped (issue 24, item 3).

With `--workers N` every one of the `--devices` is also fitted completely by
`fit_distributed` on a local cluster of N worker processes (`--worker-platforms`: `default`,
the GPU shared by all workers, and/or `cpu`), a first call and a second, warm
(`workers_<platform>_fits_per_min`; `_first_s`; `_cpu_agreement_max_rel` against the CPU's
`fit_batch` of the first `--check`). Measured (2026-11-27, H200 box, 16 cores, jax 0.11.2,
`XLA_PYTHON_CLIENT_PREALLOCATE=false`, `--devices 32768 --complete 1024 --check 4 --workers
15 --worker-platforms default,cpu --skip-qr`): the GPU shared by 15 workers, 32,768 complete
fits at 14,006 /min warm (140.4 s; first call 144.2 s; chunks of 273; all valid; the CPU's
estimates to 5.5e-15), against one process's 6,697 /min at 1,024 in the same call; 15
CPU-only workers: 10,530 /min on their first call (186.7 s: over `FIRST_CALL_LIMIT_S`, so not
timed again). Fifteen independent processes running a warm `fit_batch` of 96 devices on
that CPU gave 34,755 /min together (one alone 4,456): most of the gap is likely Dask's own
work (not measured apart).

Then (2026-11-27, H200 box, jax 0.11.2, one call: `--devices 32768 --complete 256 --check 4
--workers 15 --skip-qr`, then `--devices 8192 --complete 64 --check 2 --workers 15` with
NVIDIA MPS started), the workers timing their own tasks (`_busy_share`,
`_worker_ms_per_device`, the warm call's `_worker_phases_s` summed over workers): 32,768
solves warm in 4.3 s (456,412 /min, first chunk 9.7 s, all converged; the 64 alone 8.2e-9
of the same in the big batch, 6 step counts differ); one process's complete `fit_batch` of
256, 6,964 /min; the CPU's estimates to 5.2e-15. Fifteen workers sharing the card: 32,768
complete fits in 155.1 s on the first call (12,679 /min; chunks of 546; all valid; the CPU's
estimates to 5.2e-15; over `FIRST_CALL_LIMIT_S`, so not timed warm), the workers busy 38 % of
the time (27.3 ms of worker time a device); with MPS, 8,192 in 35.6 s warm (13,798 /min),
busy 22 %, 14.3 ms a device, of which the residual tests 7.9 ms (each worker ran 8 shuffle
threads, 120 on the 16 cores; one process with the box to itself: 3.7), prepare 2.1,
assembly 1.3, sandwich 0.9,
the fitted models 0.8 and the solves 0.5 ms. `nvidia-smi dmon`: the card's SMs at 0 %
nearly throughout. So neither the card nor the workers' fitting bounded the cluster, but
its client: Dask wrote each result's ~150 arrays as frames of their own (2.1 ms a result on
the worker) and the client unpickled them with its garbage collector walking its growing
heap (0.74-1.7 ms a result). Changed after that call, measured on the 2-core CPU only (no
second device window was lent): a task's results go back as one pickle (1.15 ms a result to
write), unpickled with the collector paused (0.43-0.50 ms), a result's run models as their
leaves (13 % less to read), eight tasks a worker (the client's gathering overlaps the
fitting), a worker's host work on one core (`greybox._platform.one_core`) and accelerator
workers' chunks from the card's memory (`distributed.worker_budget`); the client's whole
gathering, `many_devices.py --dask`: 0.77-0.83 ms a result, against 1.41 as Dask ships
objects. With the workers at the single process's ~9 ms a device and the client at ~0.8 ms
a result, 15 workers would be past 50,000 /min; not yet shown. Then (2026-11-28, no device
lent): a batch's residual shuffles run as one compiled kernel on an accelerator
(`shuffle_pass`; the 7.9 ms above were numpy's pass), not yet timed there either.

Then (2026-11-29, H200 box, jax 0.11.2, MPS started, `--devices 32768 --complete 2048 --check
4 --workers 15 --worker-platforms default,cpu --skip-qr`, main at 6177155): fifteen workers
sharing the card, 32,768 complete fits in 69.4 s on the first call and 60.2 s warm (32,634
/min), all valid, the CPU's estimates to 3.0e-15; fifteen CPU-only workers 24,865 /min warm;
one process's complete `fit_batch` of 2,048 15,815 /min (warm 7.8 s). The workers were busy
36 % of the time (9.85 ms of worker time a device): the client bounded the cluster, at 1.8
ms a result. On the 2-core CPU, with tasks that return a fixed pickle of 256 results in
place of fitting (the client alone, py-spy), a fifth of its gathering was the collector's
full collections (the collector, back on between tasks, walked every result gathered so far,
again and again) and a sixth the payloads' by-value pickler (cloudpickle); protocol 5 made a
memoryview and a buffer per array (397 objects the collector tracks per result, 139 with
protocol 4; unpickling 0.40 against 0.34 ms), and a quarter of each result's bytes were its
device's runs, which the client holds already. After the collector paused over the whole
gathering (each task's new objects examined once), protocol 4, the standard pickler
(cloudpickle only for what refers to a `__main__`), results without their devices' runs
(the client's own objects put back, as `fit_batch` gives them) and results fetched from the
workers straight: 0.93 -> 0.54-0.57 ms a result on that stand-in. The same call on the box
(`--complete 256`, a second device window of the same day): **32,768 complete fits in 24.8 s
warm, 79,177 /min** (first call 43.9 s, 44,745 /min), all valid, the CPU's estimates to
3.0e-15, workers busy 61 % (6.94 ms a device); fifteen CPU-only workers 49,863 /min warm
(first call 56.0 s); the 64 solves alone vs in the big batch 2.9e-10 (6 step counts differ).

Usage: .venv/bin/python benchmarks/gpu_many_devices.py [--devices 32768] [--workers 15] [--smoke]
On a lent GPU machine (no package registry there; its image holds jax, equinox, diffrax,
optimistix, lineax, numpy, scipy and matplotlib): carry as wheels dask and distributed
2026.8.0, tornado 6.6.1, tblib 3.2.2, zict 3.0.0, locket 1.0.0, partd 1.4.2, pint 0.25.3,
flexcache 0.3, flexparser 0.4 and platformdirs 4.14.8, install them with `pip install
--no-index --no-deps --target /tmp/site`, start MPS (`nvidia-cuda-mps-control -d`, as in the
runs above), then `PYTHONPATH=/tmp/site:$PWD XLA_PYTHON_CLIENT_PREALLOCATE=false python3
benchmarks/gpu_many_devices.py --devices 32768 --complete 256 --check 4 --workers 15
--worker-platforms default,cpu --skip-qr` (about 4 minutes); before it,
`benchmarks/shuffle_pass.py` (seconds) times the shuffle kernel against numpy on the box.
Last line: one JSON object.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import lineax as lx  # noqa: E402
import numpy as np  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))

import many_devices as md  # noqa: E402

import greybox  # noqa: E402
from greybox._estimate import batch as _batch  # noqa: E402
from greybox._estimate import fit as _fit  # noqa: E402
from greybox._model import householder  # noqa: E402
from greybox._platform import on_accelerator  # noqa: E402

SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"
NOISE_M = 0.05e-6
DROP = 0.05
FIRST_CALL_LIMIT_S = 180.0  # a distributed first call slower than this is not timed again


def pool_devices(n_pool, seed=24):
    """(devices, clean readings per device and run): `n_pool` recorded chevrons."""
    rng = np.random.default_rng(seed)
    model = md.camera_model()
    waves = [md.waveform(p, per) for p, per in md.RUNS]
    devices, cleans = [], []
    for k in range(n_pool):
        vals = {p: med * np.exp(sd * rng.normal()) for p, (med, sd) in md.POPULATION.items()}
        dev = greybox.parameters.set_values(model, list(vals), list(vals.values()))
        exps, clean = [], []
        for j, wave in enumerate(waves):
            offset = (312 + rng.uniform(-4, 4)) * md.M_PER_PX
            run = greybox.parameters.set_values(dev, ["camera.offset_m"], [offset])
            defects = greybox.waveforms.CameraDefects(fps=30.0, noise_m=NOISE_M, drop_fraction=DROP)
            seed_k = int(rng.integers(2**31))
            e, c = greybox.waveforms.record(run, wave, name=f"r{j}", defects=defects, seed=seed_k)
            exps.append(e)
            clean.append(c)
        devices.append(
            greybox.population.device_from_spec(md.SPEC, f"pool{k:04d}", exps, model=model)
        )
        cleans.append(clean)
    return devices, cleans


def replicated_readings(group, cleans, n_devices, seed=7):
    """(pool row of each device, readings (n_devices, E, N, n_y)): device k is pool device
    k mod P with fresh noise on its clean readings (its own dropped frames kept, zero like
    the padded frames), one vectorised draw for all of them."""
    rows = np.arange(n_devices) % len(group.members)
    clean = np.zeros_like(group.stacked.y)  # (P, E, N, n_y)
    for p, runs in enumerate(cleans):
        for e, c in enumerate(runs):
            clean[p, e, : c.shape[0]] = c
    w = np.take(group.stacked.w, rows, axis=0)
    noisy = clean[rows] + np.random.default_rng(seed).normal(0.0, NOISE_M, w.shape)
    return rows, np.where(w > 0, noisy, 0.0)


def solve_all(group, stacked, raw, sig, chunk, opts):
    """Every row through `_batch._solve_many` in chunks of `chunk` (the last one padded with
    copies of its last row, so that one compiled function serves every chunk)."""
    n = raw.shape[0]
    outs = []
    for c in range(math.ceil(n / chunk)):
        idx = np.arange(c * chunk, min((c + 1) * chunk, n))
        idx = np.concatenate([idx, np.full(chunk - idx.size, idx[-1])])
        rows = jax.tree.map(lambda x: jnp.asarray(np.take(x, idx, axis=0)), stacked)
        raw_c, sig_c = jnp.asarray(raw[idx]), jnp.asarray(sig[idx])
        index = jnp.arange(chunk)  # item k solves row k
        out = jax.device_get(_batch._solve_many(rows, index, group.static, raw_c, sig_c, *opts))
        keep = min(chunk, n - c * chunk)
        outs.append({k: v[:keep] for k, v in out.items() if k in ("raw", "steps", "ok", "cost")})
    return {k: np.concatenate([o[k] for o in outs]) for k in outs[0]}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=32768)
    ap.add_argument("--pool", type=int, default=64)
    ap.add_argument("--complete", type=int, default=1024, help="devices of the full fit_batch")
    ap.add_argument("--check", type=int, default=16, help="devices compared with the CPU")
    ap.add_argument(
        "--process",
        type=int,
        default=0,
        help="also fit this many process-noise (Ornstein-Uhlenbeck) devices with fit_batch(..., "
        "noise=...) and compare the first --check with the CPU (0: skip; not in --smoke)",
    )
    ap.add_argument(
        "--workers",
        type=int,
        default=0,
        help="also fit all --devices completely with fit_distributed on a local cluster of "
        "this many worker processes sharing this machine (0: skip; needs the extra "
        "`distributed`)",
    )
    ap.add_argument(
        "--worker-platforms",
        default="default",
        help="comma-separated JAX platforms of those workers, each timed: default (JAX's "
        "choice: the GPU, shared), cpu",
    )
    ap.add_argument("--skip-qr", action="store_true", help="skip the step-QR comparison")
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args(argv)
    if args.smoke:
        args.devices, args.pool, args.complete, args.check = 16, 4, 2, 2
        args.workers = 0
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    t_start = time.perf_counter()
    out = {
        "backend": jax.default_backend(),
        "device": str(jax.devices()[0].device_kind),
        # how this process runs a batch's residual shuffles (`residuals._compiled_shuffles`)
        "shuffle_pass": "compiled" if on_accelerator() else "numpy",
    }

    def partial(**figures):  # each phase's figures as soon as it ends: a run cut off by its
        out.update(figures)  # device window still reports what it measured
        say("partial " + json.dumps(out))

    free = tuple(md.SPEC.free_parameters())

    t0 = time.perf_counter()
    pool, cleans = pool_devices(args.pool)
    say(f"recorded {args.pool} pool devices in {time.perf_counter() - t0:.1f} s")
    prepared, groups = _batch._prepare(
        pool, free, None, "huber", 1.5, 4.0, None, 1, 0, (1e-8, 1e-10, 16384)
    )
    (group,) = groups
    rows, noisy = replicated_readings(group, cleans, args.devices)
    stacked = jax.tree.map(lambda x: np.take(x, rows, axis=0), group.stacked)
    stacked = eqx.tree_at(lambda p: p.y, stacked, noisy)
    raw = np.stack([prepared[r].raw0 for r in rows])
    sig = np.stack([prepared[r].sigma0 for r in rows])
    budget, max_chunk = _batch.device_budget()
    b = _batch.bytes_per_item(prepared[0].problem)
    chunk = _batch.chunk_size_for(b, budget, args.devices, max_chunk)
    opts = _fit.solver_settings(1e-6, 1e-6, 200)  # as `fit_batch` passes them
    say(f"{args.devices} problems stacked; chunks of {chunk} (~{b * chunk / 1e9:.2f} GB each)")

    t0 = time.perf_counter()  # one chunk first: the compile, reported apart
    head = jax.tree.map(lambda x: x[:chunk], stacked)
    solve_all(group, head, raw[:chunk], sig[:chunk], chunk, opts)
    first_chunk_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    solved = solve_all(group, stacked, raw, sig, chunk, opts)
    solve_s = time.perf_counter() - t0
    say(f"solved {args.devices} in {solve_s:.1f} s warm (first chunk {first_chunk_s:.1f} s)")
    partial(
        devices=args.devices,
        solve_fits_per_min=round(60.0 * args.devices / solve_s, 1),
        solve_s=round(solve_s, 2),
        solve_first_chunk_s=round(first_chunk_s, 2),
        solve_chunk=int(chunk),
        solves_ok=int(np.sum(solved["ok"])),
    )

    # the first 64 solves again in a batch of their own
    n_ind = min(64, args.devices)
    sub = jax.tree.map(lambda x: x[:n_ind], stacked)
    alone = solve_all(group, sub, raw[:n_ind], sig[:n_ind], n_ind, opts)
    diff = np.abs(alone["raw"] - solved["raw"][:n_ind])
    ind_rel = float(np.max(diff / np.maximum(np.abs(alone["raw"]), 1e-12)))
    steps_differ = int(np.sum(alone["steps"] != solved["steps"][:n_ind]))
    partial(batch_independence_max_rel=ind_rel, batch_independence_steps_differ=steps_differ)

    # complete fits (everything fit_batch returns), warm
    complete = [_device_from_rows(pool, cleans, k, rows, noisy) for k in range(args.complete)]
    t0 = time.perf_counter()
    greybox.fit_batch(complete, free)
    batch_first_s = time.perf_counter() - t0
    with md.PhaseTimer() as phases:
        t0 = time.perf_counter()
        res = greybox.fit_batch(complete, free)
        batch_s = time.perf_counter() - t0
    say(f"fit_batch of {args.complete}: first {batch_first_s:.1f} s, warm {batch_s:.1f} s")
    partial(
        complete_devices=args.complete,
        batch_fits_per_min=round(60.0 * args.complete / batch_s, 1),
        batch_first_s=round(batch_first_s, 2),
        batch_solve_share=round((phases.t["solve"] + phases.t["models"]) / batch_s, 3),
        batch_phases_s={k: round(v, 2) for k, v in phases.t.items()},
    )

    # the same estimates on the CPU
    check = complete[: args.check]
    with jax.default_device(jax.devices("cpu")[0]):
        cpu = greybox.fit_batch(check, free)
    worst = md.max_rel_diff({n: res[n] for n in cpu.results}, cpu.results)

    partial(cpu_agreement_max_rel=worst, cpu_check_devices=len(check))
    if args.workers:
        every = [_device_from_rows(pool, cleans, k, rows, noisy) for k in range(args.devices)]
        for platform in args.worker_platforms.split(","):
            figures = distributed_batch(every, free, args.workers, platform, cpu, say)
            partial(**figures)
        del every
    if args.process:
        partial(**process_batch(args.process, args.check, say))

    if not args.skip_qr:
        # last (it clears the compiled functions): one chunk, warm, with this backend's step
        # QR and with LAPACK's (`lx.QR`, what every backend used before)
        head_s = {}
        for name, solver in (("default", None), ("lapack", lx.QR)):
            head_s[name] = _warm_chunk_s(group, head, raw[:chunk], sig[:chunk], chunk, opts, solver)
        out.update(
            solve_chunk_warm_s=round(head_s["default"], 3),
            solve_chunk_lapack_qr_s=round(head_s["lapack"], 3),
            step_qr_speedup=round(head_s["lapack"] / head_s["default"], 2),
        )
    out.update(
        total_s=round(time.perf_counter() - t_start, 1),
        load_average=round(os.getloadavg()[0], 2),
    )
    print(json.dumps(out))


def distributed_batch(devices, free, n_workers, platform, cpu, say) -> dict:
    """Complete fits of every device by `fit_distributed` on a local cluster of `n_workers`
    processes whose JAX uses `platform` ("default": JAX's choice, so the GPU, shared), the
    first call (worker start-up and compiles) and a second, warm, on the same cluster; the
    estimates of the devices in `cpu` (the CPU's `fit_batch`) compared."""
    from greybox._estimate import distributed as dist

    plat = None if platform == "default" else platform
    key = f"workers_{platform}"
    t0 = time.perf_counter()
    client, cluster = dist.start_client("local", n_workers, platform=plat)
    start_s = time.perf_counter() - t0
    quiet = lambda _m: None  # noqa: E731
    here = str(Path(__file__).resolve().parent)
    try:
        times = []
        for call in range(2):
            if call:  # the warm call's phases, timed on every worker
                client.run(_start_worker_phases, here)
            t0 = time.perf_counter()
            res = dist.fit_distributed(
                devices,
                free,
                client=client,
                n_workers=n_workers,
                worker_platform=plat or jax.default_backend(),
                progress=quiet,
            )
            times.append(time.perf_counter() - t0)
            say(f"{key}: {len(devices)} complete fits in {times[-1]:.1f} s")
            if times[0] > FIRST_CALL_LIMIT_S:  # too slow to time twice in one device window
                break
        phases = {}
        if len(times) > 1:
            for worker_phases in client.run(_worker_phases).values():
                for k, v in worker_phases.items():
                    phases[k] = phases.get(k, 0.0) + v
    finally:
        client.close()
        cluster.close()
    worst = md.max_rel_diff({n: res[n] for n in cpu.results}, cpu.results)
    return {
        f"{key}_devices": len(devices),
        f"{key}_n": n_workers,
        f"{key}_fits_per_min": round(60.0 * len(devices) / times[-1], 1),
        f"{key}_warm_s": round(times[1], 2) if len(times) > 1 else None,
        f"{key}_first_s": round(times[0], 2),
        f"{key}_cluster_start_s": round(start_s, 2),
        f"{key}_chunk": res.chunk_size,
        f"{key}_valid": int(sum(r.valid for r in res.results.values())),
        f"{key}_cpu_agreement_max_rel": worst,
        # the workers' share of the cluster's time spent on their tasks (unpickling the
        # devices, fit_batch), and their phases summed over workers (seconds; warm call):
        # what is not theirs is the client's and Dask's (pickling, gathering)
        f"{key}_busy_share": round(sum(res.worker_s) / (n_workers * times[-1]), 3),
        f"{key}_worker_ms_per_device": round(1e3 * sum(res.worker_s) / len(devices), 2),
        f"{key}_worker_phases_s": {k: round(v, 1) for k, v in phases.items()},
    }


def _start_worker_phases(bench_dir):
    """On a worker: time `fit_batch`'s phases from now on (`many_devices.PhaseTimer`)."""
    sys.path.insert(0, bench_dir)
    import many_devices

    many_devices.WORKER_PHASES = many_devices.PhaseTimer().__enter__()


def _worker_phases():
    """On a worker: the phases timed since `_start_worker_phases` (empty if never started)."""
    import many_devices

    timer = getattr(many_devices, "WORKER_PHASES", None)
    return dict(timer.t) if timer is not None else {}


def process_batch(n, n_check, say) -> dict:
    """`many_devices.process_noise_batch` of `n` devices (its figures), and the first
    `n_check` again on the CPU (`process_cpu_agreement_max_rel`)."""
    from tests import ou_device as od

    devices, res, figures = md.process_noise_batch(n, say)
    check = devices[:n_check]
    noise = greybox.ProcessNoise(od.STRUCTURE)
    with jax.default_device(jax.devices("cpu")[0]):
        cpu = greybox.fit_batch(check, od.FREE, noise=noise, n_starts=2)
    worst = md.max_rel_diff({n: res[n] for n in cpu.results}, cpu.results)
    return {**figures, "process_cpu_agreement_max_rel": worst}


def _warm_chunk_s(group, head, raw, sig, chunk, opts, solver=None):
    """Seconds of one chunk of solves, warm; `solver` (a lineax solver class) replaces the
    Levenberg-Marquardt step's QR (`householder.lm_linear_solver`) for this timing only."""
    saved = householder.lm_linear_solver
    swap = solver is not None and not isinstance(saved(), solver)  # a CPU's own is lx.QR
    if swap:
        householder.lm_linear_solver = solver
        jax.clear_caches()  # a new trace picks the replacement up
    try:
        solve_all(group, head, raw, sig, chunk, opts)  # compiles (if it must)
        t0 = time.perf_counter()
        solve_all(group, head, raw, sig, chunk, opts)
        return time.perf_counter() - t0
    finally:
        if swap:
            householder.lm_linear_solver = saved
            jax.clear_caches()


def _device_from_rows(pool, cleans, k, rows, noisy):
    """Device k of the replicated set as a `greybox.population.Device` (for `fit_batch`)."""
    base = pool[rows[k]]
    exps = []
    for e_i, e in enumerate(base.experiments):
        y = noisy[k, e_i, : e.n_frames]
        y = np.where(np.isfinite(e.y), y, np.nan)
        exps.append(greybox.Experiment(e.name, e.t_s, y, e.inputs))
    return greybox.population.Device(f"dev{k:05d}", base.model, tuple(exps), free=base.free)


if __name__ == "__main__":
    main()
