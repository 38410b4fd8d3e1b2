"""Many devices: a loop of `greybox.fit` calls vs one compiled batch (issues 19 and 24).

Synthetic chevron-laser devices (six short pulse-train runs each, 30 fps camera with jitter,
noise and dropped frames, from `greybox.waveforms.record`) whose absorptance and thermal time
constant are drawn from a known log-normal population. It measures

(a) `loop_fits_per_s`: a Python loop of `greybox.fit` over NEW devices of one structure
    (`--loop-sample` of them, default 12: a few fits of ~20 ms each timed together swing
    with any pause of the machine), after a first fit whose time (compile included)
    is reported apart (`loop_first_fit_s`). Start values, scales, bounds and priors are
    inputs of the compiled solver, not part of it, so a new device of a known structure costs
    its solve (issue 24, item 1; this rate was 0.21 fits/s when each new device compiled
    again); `own_numbers_fits_per_s`: the same devices again, each with numbers of its own
    (the per-run offsets' scale left to be derived from the device's own start, tau's upper
    bound 1.5-2.5 s), which must compile nothing either (2026-11-28, 12 devices: 0.79
    fits/s when bounds and scales were static fields, a compile per device; 57-58 since);
    `loop_with_bands_per_s`: the same devices through a notebook's steps, each fitted, the
    band of its response to a new waveform and tau's delta-method interval (`notebook_loop`;
    2026-11-28, 12 devices, two runs each: 2.3 and 2.6 per s on 204297b, where the band and
    the delta method compiled at every call, 24 and 30 per s since);
(b) `batch_fits_per_min`: `fit_batch` of `--devices` devices (default 512), warm: a first
    call of the same batch compiles (`batch_first_s`, reported apart), the second is timed;
(c) `solve_share`: the fraction of the warm batch's wall time spent inside compiled code:
    the batched solver (`_batch._solve_many`, waited for, `solve_s`) and the vmapped fitted
    models (`_batch._fitted_models`, `models_s`), both run back to back by the calling
    thread; beside it the host phases (`prepare_s`: the problems made, `plan_s` of it
    before any solve (`_batch._plan`: checks, schedules padded jointly), the rest
    (`_batch._build`, in blocks of 64 devices) in the host thread, the first block before the
    first solve and the others beside it; `residual_tests_s`: the residual tests of each
    wave of devices in one vectorised pass; `sandwich_s`: the model-error regressions and
    HAC meats of each wave, stacked; `scores_s`: the fit %, outliers and noise ceilings of
    each wave's runs, stacked; `assemble_s`: the per-device `_fit._assemble`). These run in
    `fit_batch`'s host thread while the next wave solves, so the phases add up to more than
    the wall time; `host_overlap_s` is by how much. The plan is all that precedes the first
    solve (2026-11-29, alternating runs: `plan_s` 0.13 -> 0.075 and `solve_share`
    0.785-0.802 -> 0.798-0.852 once it found the schedules' widths and left their stacking to
    the blocks, the first block a quarter);
(c') `compiled_alone_s`: the same compiled calls run alone (`compiled_alone`: every wave's
    starts, re-fits and models back to back, problems built beforehand, no host work), and
    `compiled_alone_share` = that over the batch's wall time: beside the host thread the
    solves run slower (they share the two cores), and `solve_share` counts that slowdown
    as compiled time, so this is the stricter figure of how much of the batch is the work
    only compiled code can do;
(d) optionally (`--dask`) `fit_distributed` on a Dask `LocalCluster` of `--workers` processes,
    and the client's gathering of results from a worker (`gather_figures`): as
    `fit_distributed` ships them against Dask's own way with objects (2026-11-27, 128
    devices x 24 copies: 0.77-0.83 against 1.41-1.42 ms a result, `dask_gather_speedup`
    1.70-1.85; 2026-11-29, 64 devices x 24, alternating with 6177155: 0.79-0.81 -> 0.42 ms
    a result, with the collector paused over the whole gathering, protocol 4 and results
    without their devices' own runs: `greybox._estimate.distributed`);

(d') with `--dask`, a call made again (`dask_again`): its new workers compiling every
    program again against loading them from the client's compile cache (2026-11-29, 64
    devices, two workers: 7.85 -> 3.90 s, `dask_again_speedup` 2.01, the same raw vectors);

(e) optionally (`--process N`; 3 in `--smoke`) `fit_batch` with process noise
    (`process_noise_batch`: the likelihood back end, batched) of N scalar Ornstein-Uhlenbeck
    devices of 193-208 frames, two starts each, warm: `process_fits_per_min`
    (`process_first_s` the first call, compile included; `process_converged`;
    `process_groups`, 1 since the records are padded to bucketed lengths: 2026-11-28, 32
    devices, 13 groups and a first call of 31.9 s on 204297b, 1 group and 6.0 s since;
    warm 1,538 -> 1,386 fits/min, the padded steps' cost);

and checks that the batch agrees with the single fits of the loop (`batch_vs_fit_max_rel`)
and that the population model recovers the known median and spread from the batch
(z-scores). `backend` is JAX's default backend; `load_average` the 1-minute load at the end.

Usage (repository root): .venv/bin/python benchmarks/many_devices.py [--devices 512] [--smoke]
Last line: one JSON object.

Measured (issue 24, CPU, 2 cores shared with other jobs; wall times swing with the load, so the
host phases are also given as main-thread CPU). Before the assembly work (main at 771b2ab) vs
after: 512 devices, main-thread CPU 10.3 -> 6.6 s, of which assembly with the residual tests
7.2 -> 4.0 s (14 -> 7.8 ms per device; load 6.0 and 4.9); 128 devices at load ~3.5:
1416 -> 2033 fits/min, host phases 2.1 -> 1.6 s wall (the warm solve was 15-24 s of wall
for 512 devices at those loads). Results are unchanged (same estimates,
statistics and p-values; population z-scores identical).
Quiet machine (load 1.0), after the block-structured Jacobian and the batched expm of issue
25: loop 32.1 fits/s (first fit 4.4 s), batch of 512 2,674 fits/min (11.5 s warm), of which
the vmapped solve 4.1 s (7,400 fits/min alone) and the host 7.0 s (prepare 1.7, residual tests
2.0, models 0.3, assembly 3.0): solve_share 0.36. The host is the bottleneck now.
Then (load 0.9): the host work of each wave overlapping the next wave's solves, chunks of 64,
no eager JAX on the host: loop 47.7 fits/s (first fit 2.1 s), batch of 512 **5,881 fits/min**
(5.22 s warm), solve 3.03 s + models 0.35 s: solve_share 0.65. The host phases (prepare 0.66
s, then residual tests and assembly in the host thread) are ~5 s of interpreter time that
one lock serialises, so the wall time is now about the host's, and compiled code fills 65 %
of it; 0.8 would need the residual tests and the assembly compiled as well. Same estimates
(batch_vs_fit_max_rel 9.6e-14) and population z-scores as before.
Then (load 0.66), after a stalled start with nothing left to gain counts as converged: all
512 devices valid (506 before), 5,630 fits/min (5.46 s warm), solve_share 0.69, the compiled
calls alone 2.57 s (compiled_alone_share 0.47): the solves run ~1.2x slower beside the
host thread than alone.
Then (2026-11-26, alternating runs of main at 030f403 and this change, loads 1.0-1.3, the
machine slower than the day before): a chunk's solves one after another (`lax.map`) on the
CPU instead of vmapped. Before: 7.47 and 7.71 s warm (4,115 and 3,984 fits/min),
compiled alone 3.2-4.4 s, solve_share 0.66-0.71. After: 6.66 and 6.03 s (4,615 and 5,095
fits/min), compiled alone 2.05-2.10 s, solve_share 0.33-0.40, batch_vs_fit_max_rel 0.0 (each
solve is bit for bit `fit`'s). The batch is now the host thread's time (prepare ~1, residual
tests ~2.7, assembly ~2.2 s), which is why solve_share fell as the solves got faster.
Then (2026-11-27, alternating runs of 31fecb3 and this change, loads 1.1-1.4): the host work
as stacked passes over runs (residual tests, HAC, scoring), results without their shuffle
matrices. Before: 4,781 and 4,130 fits/min (6.43 and 7.44 s warm), solve_share 0.37 and
0.33, residual tests 2.7-3.0 s, assembly 2.3-2.8 s, prepare 1.2 s, peak RSS 1,035 MB. After:
6,881 and 5,524 fits/min (4.47 and 5.56 s), solve_share 0.44 and 0.47, residual tests
1.9-2.3 s, assembly 1.4-2.0 s, prepare 0.9-1.0 s, peak RSS 828 MB, result_kb_per_device
34.5 (was ~323); batch_vs_fit_max_rel 0.0 and the population z-scores unchanged.
Then (2026-11-27, quiet: load 0.98, main at 3576b88): loop 39.4 fits/s (first fit 2.36 s),
batch of 512 7,793 fits/min (3.94 s warm), solve 1.45 + models 0.44 s: solve_share 0.48;
host phases prepare 0.76, residual tests 1.59, assembly 1.27 s (1.57 s of them overlapped).
The wall time is the host's interpreter work; 0.8 still needs it compiled.
Then (2026-11-27, alternating runs of 39c54ed and this change, loads 1.1-1.4): the library's
compiled functions built for a fast compile (`greybox/_compile.py`), the batch solver with
XLA's default code generation (compiled fast, its solves ran 18-33 % slower): batch of 512
6,210 and 6,791 -> 6,207 and 6,444 fits/min, its compiled calls alone the same (256 devices,
four calls each: 0.80-1.02 s before, 0.80-1.06 s after), the first fit 2.4-3.1 -> 1.6-2.1 s
(a loop of 12 new devices: ~20 ms a fit either way); `batch_vs_fit_max_rel` 9.6e-14 (was
0.0: a single fit's solver and the batch's are now compiled with different options, so they
agree to rounding, no longer bit for bit; the batch's own independence of its size is
unchanged, tests/test_batch_independence.py).
Then (2026-11-27, a quiet machine, load 0.2-1.8, main at 0a429ec): fewer interpreter steps
around the compiled calls (one transfer per chunk, one flatten per device to group the
structures, the residual pooling as one stacked pass): the warm batch 3.31 -> 3.14 s (medians
of alternating runs), batch of 512 9,448 and 9,661 fits/min, solve_share 0.46 and 0.47, loop
55 and 57 fits/s; bit-identical results. What bounds it (py-spy --gil): about 2.7 s of
interpreter work per 512 devices (residual tests ~1.3, assembly ~1.1, prepare ~0.45 s) holds
the interpreter lock against ~1.4 s of compiled work, and nothing in it is more than ~5 %.
Then (2026-11-27, quiet, load 1.1-1.2): `--loop-sample` 3 -> 12 by default. Three fits of
~20 ms timed together swung between 22.6 and 59 fits/s from run to run; twelve gave 43.0 and
42.8 fits/s. Over those twelve, `batch_vs_fit_max_rel` is 1.9e-9 (9.6e-14 over three): one
device (chevron0006) ends its single fit and its batch solve a rounding step apart, 1.2e-10
relative on its absorptance, 2e-8 of that estimate's standard error. Batch of 512: 9,373 and
8,509 fits/min, solve_share 0.48 and 0.44.
Then (2026-11-27, alternating runs of 279a271 and e85f4ca/2c50f28, loads 0.8-1.5): the
model-error regressions and HAC meats of a wave as stacked passes (`sandwich_s`, beside
`assemble_s` now) and the shuffle pass without its block-wide temporaries: warm batch 4.47,
4.29, 5.75, 4.89 s -> 4.21, 3.98, 4.71, 4.08 s (6,867-7,160 -> 7,292-7,712 fits/min in the
quieter pair), solve_share 0.43-0.47 -> 0.47-0.50; the sandwich and assembly of 512 devices
1.36-1.78 s -> 1.19-1.16 s of host-thread wall. Same estimates (batch_vs_fit_max_rel 1.9e-9
either way), the same population z-scores, 512/512 valid. A warm batch now uses 4.96 s of
CPU in 3.66-3.73 s of wall: 1.34 of the 2 cores. The rest is the interpreter lock: the
host work (its numpy calls included, which hold the lock between their short C loops) is
one chain, and the compiled solves are the only work that runs beside it. 0.8 needs that
chain under ~2.4 s (compiled residual tests and assembly, or the host work in a process).
Then (2026-11-28, load ~1.1): process noise, 128 devices (`--devices 16 --process 128`):
2,124 and 2,193 fits/min warm (first call 5.5 s), all converged. Against the code before
the devices were assembled in a host thread while the next chunk solves (the same 128
devices, eight warm calls each, alternating: medians 4.5 and 4.9 s before, 4.3 and 3.7 s
after; fastest 3.99 and 4.32 s before, 3.52 and 3.53 s after), the same results.
Then (2026-11-28, alternating runs of d14b629 and this change, loads 1.1-1.2): every run of
the batch's devices built and padded in one pass (`greybox._simulate.schedules`), each wave's
run scores stacked (`scores_s`) and the per-run portmanteau statistics by test lag: warm
batch 3.52 and 4.05 s -> 3.07 and 3.39 s (8,723 and 7,579 -> 10,015 and 9,064 fits/min),
prepare 0.70-0.72 -> 0.37-0.53 s, solve_share 0.58-0.59 -> 0.60-0.63 (0.66-0.67 in two
other runs), the same results (batch_vs_fit_max_rel 1.9e-9, 512/512 valid). The host's
interpreter-held work is still the longer chain: 0.8 is not reached on two cores.
Then (2026-11-28, three alternating runs of 011b1ab and 3badd02, loads 1.0-1.3): the batch
with Python's cyclic garbage collector paused (`greybox/_collector.py`): 10,942, 10,424,
11,337 -> 10,922, 11,787, 11,793 fits/min, the same results (1.9e-9, 512/512 valid).
solve_share fell, 0.68-0.73 -> 0.59-0.62: it is the main thread's wait on compiled calls,
and that wait had held the collector's pauses (the host thread's walks of the heap, under
the interpreter lock, delayed the main thread's return from each call: `models_s` 0.50-0.69
-> 0.23-0.26 s). compiled_alone_share, the compiled work timed alone over the batch's wall,
0.50-0.52 -> 0.51-0.58, is the figure that rose with the throughput.
With the residual tests' p-values in unmasked passes and the shuffles held in one array as
well (1403e38), three alternating runs against 80e954b (loads 1.1-1.4): 7,835, 9,627, 8,821
-> 10,044, 10,454, 10,705 fits/min; residual_tests_s 1.53-1.78 -> 1.23-1.35; solve_share
0.55-0.68 -> 0.59-0.61; compiled_alone_share 0.46-0.50 -> 0.51-0.59; the same results.
With the problems built in blocks by the host thread ahead of the waves (2026-11-29, four
alternating pairs against 74fc79d, four warm batches each): walls 2.51-3.28 s before and
2.37-3.03 s after, within this machine's noise; solve_share 0.62-0.64 -> 0.67-0.69 (0.72 in
a full run: solve_s 1.30 -> 1.55 s, the solves slower beside the build), compiled_alone_share
0.55 -> 0.57; the same estimates to the bit. Its gain is the first progress line of a large
batch (2,048 devices: 2.3-2.5 -> 1.4-1.6 s), not the throughput.
With the residual tests' shuffles in two stages (2026-11-29: 99 a test, the other 900 only
where those leave p below 0.11; every p-value below 0.011 and every verdict unchanged), two
alternating runs against 5ec65c4: residual_tests_s 1.35 and 1.20 -> 0.61 and 0.71;
10,361 and 11,629 -> 14,582 and 12,562 fits/min; solve_share 0.71 and 0.66 -> 0.73 and
0.68; compiled_alone_share 0.57 and 0.58 -> 0.68 and 0.63; the same estimates
(batch_vs_fit_max_rel 1.2e-14). The host thread is still the longer chain.
With a wave's problems sent to the device once for all its calls (`_batch._Rows`), numpy
solver settings and the fitted models unflattened by the host thread (2026-11-29, three
rounds of six warm batches alternating with 3491738, medians): solve_share 0.716, 0.721,
0.721 -> 0.742, 0.751, 0.740 (models_s 0.235 -> 0.06-0.07 s), walls 2.15, 2.12, 2.10 ->
2.14, 2.09, 2.13 s; two full runs after: 13,948 and 13,790 fits/min, solve_share 0.749 and
0.728, compiled_alone_share 0.64, batch_vs_fit_max_rel 1.2e-14, 512/512 valid.
With less host work (the HAC meats as BLAS products, one pass per device for the noise guess
and NaN zeroing, a faster plan) and the batch's last wave split in 32, 16 and 16 devices
(`_batch._tapered`: the host thread now keeps up, and the last wave's assembly is the only
stretch with nothing compiled running), 2026-11-29, two rounds of six warm batches
alternating with cdbd33a, medians: solve_share 0.755, 0.736 -> 0.783, 0.790; walls within
the machine's swings. With the wave's noise re-estimated in one stacked pass and each block's
stack sent to the device by the host thread (`_batch._build_ahead`): two full runs, 15,437
and 15,700 fits/min, solve_share 0.826 and 0.803, compiled_alone_share 0.69 and 0.71,
batch_vs_fit_max_rel 1.2e-14, 512/512 valid.
With each solve's end point taken from the optimiser's last evaluation (4b6a7ea: no second
simulation with its derivative), three alternating full runs against 42cf7c1 (2026-11-29):
15,212, 15,166, 14,537 -> 15,505, 15,252, 14,921 fits/min; solve_s 1.49-1.58 -> 1.49-1.52 s;
solve_share 0.789, 0.812, 0.807 -> 0.807, 0.796, 0.775 (the compiled part is the smaller
one now, so the share falls at the same or a shorter wall); batch_vs_fit_max_rel 1.2e-14.
"""

from __future__ import annotations

import argparse
import dataclasses
import inspect
import json
import os
import pickle
import resource
import sys
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import greybox  # noqa: E402
from greybox._collector import collector_paused  # noqa: E402
from greybox._estimate import batch as _batch  # noqa: E402
from greybox._estimate import fit as _fit  # noqa: E402

SPEC = greybox.get_device("chevron_laser")
M_PER_PX = 0.645e-6
POPULATION = {"absorptance": (0.62, 0.08), "thermal.tau_s": (0.045, 0.15)}  # median, log-sd
RUNS = [(5, 200), (10, 200), (10, 300), (15, 400), (20, 600), (30, 800)]  # mW, ms
SPAN_S = 1.4  # pulses per run: short runs, ~50 frames each
SMOKE_HELP = "smallest setting (a few seconds): checks that the script still runs"


def camera_model():
    return greybox.devices.with_camera(SPEC.model(), exposure_s=10e-3, m_per_px=M_PER_PX)


def waveform(power_mw, period_ms):
    n = max(1, int(SPAN_S * 1e3 // period_ms))
    return greybox.PulseTrain(
        power_mw * 1e-3, period_ms * 1e-3, duty=0.5, n_pulses=n, delay_s=0.1, tail_s=0.2
    )


def _own_numbers(free, i: int) -> tuple:
    """`free` with numbers of a device's own: no explicit scale on the per-run offsets (each
    derives it from its own start) and tau's upper bound 1.5-2.5 s."""
    def own(p):
        if p.path == "camera.offset_m":
            return dataclasses.replace(p, scale=None)
        if p.path == "thermal.tau_s":
            return dataclasses.replace(p, upper=1.5 + (i % 11) / 10)
        return p

    return tuple(own(p) for p in free)


NEW_WAVE = greybox.PulseTrain(15e-3, 0.25, duty=0.3, n_pulses=4, delay_s=0.1, tail_s=0.3)


def _tau(model):
    return model.thermal.tau_s


def notebook_loop(devices, fitted) -> float:
    """Devices per second through what a notebook does with each new device of a structure:
    its fit, the band of its response to a new waveform, and tau's interval by the delta
    method (the first device, whose fit is in `fitted`, warms the band and delta method;
    the rest are timed). Each compiled once per structure: a band and the delta method
    compiled again at every call before 2026-11-28 (0.25-0.29 s a band)."""
    t = np.linspace(0.0, 1.5, 46)

    def steps(result):
        result.posterior.band(NEW_WAVE, t)
        greybox.uncertainty.delta_method(
            _tau, result.model, result.free, result.raw, result.covariance_raw
        )

    steps(fitted[devices[0].name])
    t0 = time.perf_counter()
    for d in devices[1:]:
        steps(greybox.fit(d.model, d.experiments, d.free))
    return (len(devices) - 1) / (time.perf_counter() - t0)


def synthetic_devices(n, seed=0, population=POPULATION, runs=RUNS, outlier=None):
    """(devices, truth): `n` chevrons with parameters drawn from `population`; `outlier`
    = (index, {path: factor}) multiplies one device's true values."""
    rng = np.random.default_rng(seed)
    model = camera_model()
    waves = [waveform(p, per) for p, per in runs]
    devices, truth = [], {}
    for k in range(n):
        vals = {p: med * np.exp(sd * rng.normal()) for p, (med, sd) in population.items()}
        if outlier is not None and k == outlier[0]:
            vals = {p: v * outlier[1].get(p, 1.0) for p, v in vals.items()}
        dev_model = greybox.parameters.set_values(model, list(vals), list(vals.values()))
        exps = []
        for j, wave in enumerate(waves):
            offset = (312.0 + rng.uniform(-4, 4)) * M_PER_PX
            run_model = greybox.parameters.set_values(dev_model, ["camera.offset_m"], [offset])
            defects = greybox.waveforms.CameraDefects(fps=30.0, noise_m=0.05e-6, drop_fraction=0.05)
            e, _ = greybox.waveforms.record(
                run_model, wave, name=f"r{j}", defects=defects, seed=int(rng.integers(2**31))
            )
            exps.append(e)
        name = f"chevron{k:04d}"
        devices.append(greybox.population.device_from_spec(SPEC, name, exps, model=model))
        truth[name] = vals
    return devices, truth


class PhaseTimer:
    """Wall time spent in `_batch._solve_many` (waited for), `_batch._plan` and `_batch._build`
    (the two parts of preparing the problems), the vectorised residual tests of every
    device (`_batch.analyse_residuals`), the fitted models (`_batch._fitted_models`, waited
    for), the sandwich meats of each wave of devices (`_fit._sandwich_meats`), the runs'
    scores of each wave (`_fit._scored_runs_many`) and the per-device `_fit._assemble` while
    active: the module attributes are wrapped, then restored."""

    NAMES = {
        "solve": ("_solve_many", True),
        "plan": ("_plan", False),
        "build": ("_build", False),
        "residual_tests": ("analyse_residuals", False),
        "models": ("_fitted_models", True),
    }

    def __init__(self):
        self.t = dict.fromkeys([*self.NAMES, "sandwich", "scores", "assemble"], 0.0)

    def _wrap(self, key, fn, block=False):
        def timed(*a, **k):
            t0 = time.perf_counter()
            out = fn(*a, **k)
            if block:
                out = jax.block_until_ready(out)
            self.t[key] += time.perf_counter() - t0
            return out

        return timed

    def __enter__(self):
        self.saved = {name: getattr(_batch, name) for name, _ in self.NAMES.values()}
        self.saved_fit = {
            "assemble": _fit._assemble,
            "sandwich": _fit._sandwich_meats,
            "scores": _fit._scored_runs_many,
        }
        for key, (name, block) in self.NAMES.items():
            setattr(_batch, name, self._wrap(key, self.saved[name], block=block))
        _fit._assemble = self._wrap("assemble", _fit._assemble)
        _fit._sandwich_meats = self._wrap("sandwich", _fit._sandwich_meats)
        _fit._scored_runs_many = self._wrap("scores", _fit._scored_runs_many)
        return self

    def __exit__(self, *exc):
        for name, fn in self.saved.items():
            setattr(_batch, name, fn)
        _fit._assemble = self.saved_fit["assemble"]
        _fit._sandwich_meats = self.saved_fit["sandwich"]
        _fit._scored_runs_many = self.saved_fit["scores"]


def compiled_alone(devices, free, chunk) -> float:
    """Wall time of the batch's compiled work alone: every wave's starts, re-fits at the
    estimated noise and fitted models (`_batch._solve_wave`) run back to back by one thread,
    in chunks of `chunk`, on problems built beforehand, with no residual tests, no assembly
    and no host thread (warm: compiled by the batch before)."""
    d = {k: v.default for k, v in inspect.signature(greybox.fit_batch).parameters.items()}
    solver = (d["solver_rtol"], d["solver_atol"], d["solver_max_steps"])  # as the timed batch
    prepared, groups = _batch._prepare(
        devices, tuple(free), d["method"], d["loss"], d["huber_c"], d["student_nu"],
        d["sigma"], d["n_starts"], d["seed"], solver,
    )
    max_steps = 200 if d["max_steps"] is None else d["max_steps"]  # fit_batch's own default
    opts, counter, quiet = (d["rtol"], d["atol"], max_steps), [0], lambda _m: None
    t0 = time.perf_counter()
    for group in groups:
        starts = [len(prepared[i].starts) for i in group.members]
        for wave in _batch._waves(group.members, starts, chunk):
            _batch._solve_wave(prepared, wave, chunk, opts, quiet, "", counter)
    return time.perf_counter() - t0


def gather_figures(results, devices, copies=24) -> dict:
    """Milliseconds a result that a client spends gathering results from a worker: `copies`
    times `results` (of `devices`), held on one worker of a local cluster, gathered back (a)
    as `fit_distributed` ships them (one pickle a task without the devices' own runs,
    unpickled as it arrives with the garbage collector paused: `dask_gather_ms_per_result`)
    and (b) as Dask ships Python objects of its own accord (each array a frame of its own,
    through the scheduler, the collector on: `dask_gather_objects_ms_per_result`, the
    baseline; gathered straight from the worker, as `fit_distributed`'s client does, Dask's
    many frames took 3.5x as long). With many workers
    this gathering, not the fitting, bounded the cluster (benchmarks/gpu_many_devices.py)."""
    from greybox._estimate import distributed as dist

    client, cluster = dist.start_client("local", 1, platform="cpu")
    try:
        blob = dist._encoded_results(results, devices)
        runs = {d.name: d.experiments for d in devices}
        held = client.scatter([(blob, 0.0)] * copies, direct=True, hash=False)
        t0 = time.perf_counter()
        with collector_paused():
            got = [dist._unpickled_results(part, runs) for part in client.gather(held)]
        ours = time.perf_counter() - t0
        held = client.scatter([results] * copies, direct=True, hash=False)
        t0 = time.perf_counter()
        plain = client.gather(held, direct=False)  # as a client gathers by default
        objects = time.perf_counter() - t0
    finally:
        client.close()
        cluster.close()
    assert len(got) == len(plain) == copies and list(got[0][0]) == list(results)
    n = copies * len(results)
    return {
        "dask_gather_ms_per_result": round(1e3 * ours / n, 3),
        "dask_gather_objects_ms_per_result": round(1e3 * objects / n, 3),
        "dask_gather_speedup": round(objects / ours, 2),
    }


def dask_again(devices, free, workers, say, repeats=2) -> dict:
    """A `fit_distributed` call made again: each call starts new worker processes, which
    compile every program again unless they share the client's compile cache
    (`distributed.compile_cache_settings`, from 2026-11-29). The client is given a cache
    folder of its own (a temporary one), a first call fills it, then calls alternate with
    the settings withheld from the workers (`dask_again_uncached_s`, the baseline: as
    before) and sent (`dask_again_cached_s`); medians, `dask_again_speedup` their ratio,
    `dask_again_same_result` whether every raw vector is the same to the bit."""
    import tempfile

    from greybox._estimate import distributed as dist

    folder = tempfile.mkdtemp(prefix="greybox-bench-cache-")
    saved = {name: getattr(jax.config, name) for name in dist.CACHE_SETTINGS}
    jax.config.update("jax_compilation_cache_dir", folder)  # what the workers are sent
    settings = dist.compile_cache_settings
    times, raws = {"uncached": [], "cached": []}, []
    try:
        greybox.population.fit_distributed(devices, free, n_workers=workers)  # fills it
        for _ in range(repeats):
            for kind in ("uncached", "cached"):
                withheld = lambda: {}  # noqa: E731 (the workers compile, as before)
                dist.compile_cache_settings = settings if kind == "cached" else withheld
                t0 = time.perf_counter()
                res = greybox.population.fit_distributed(devices, free, n_workers=workers)
                times[kind].append(time.perf_counter() - t0)
                raws.append({n: r.raw for n, r in res.results.items()})
                say(f"fit_distributed again, {kind}: {times[kind][-1]:.1f} s")
    finally:
        dist.compile_cache_settings = settings
        for name, value in saved.items():
            jax.config.update(name, value)
    med = {k: float(np.median(v)) for k, v in times.items()}
    same = all(all(np.array_equal(r[n], raws[0][n]) for n in r) for r in raws)
    return {
        "dask_again_uncached_s": round(med["uncached"], 2),
        "dask_again_cached_s": round(med["cached"], 2),
        "dask_again_speedup": round(med["uncached"] / med["cached"], 2),
        "dask_again_same_result": bool(same),
    }


def max_rel_diff(a, b):
    """Largest relative difference over every parameter value of two {name: FitResult}."""
    worst = 0.0
    for name in a:
        va = np.array([p.value for p in a[name].parameters])
        vb = np.array([p.value for p in b[name].parameters])
        worst = max(worst, float(np.max(np.abs(va - vb) / np.maximum(np.abs(vb), 1e-300))))
    return worst


def process_noise_batch(n, say, n_starts=2):
    """(devices, warm `BatchResult`, figures) of `fit_batch` with process noise (the
    likelihood back end, batched) of `n` scalar Ornstein-Uhlenbeck devices of 193-208 frames
    each, as a wafer's records differ (tests/ou_device.py; readings from the numpy simulator
    tests/ou_reference.py, parameters spread around its truth), `n_starts` starts each: a
    first call compiles (`process_first_s`), the second is timed (`process_fits_per_min`);
    `process_groups`: the compiled groups they formed (one: the records are padded to one
    bucketed length)."""
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
    from tests import ou_device as od
    from tests import ou_reference as ou

    rng = np.random.default_rng(11)
    start = {"Ci": 2.5e6, "Rea": 6.0e-3, "q": 3.0e-6, "sd": 0.06}
    devices = []
    for k in range(n):
        truth = {p: v * np.exp(0.2 * rng.normal()) for p, v in ou.TRUTH.items()}
        y = ou.simulate(truth, 193 + int(rng.integers(0, 16)), 1000 + k)
        devices.append(greybox.population.Device(f"ou{k:05d}", od.model(start), [od.experiment(y)]))
    noise = greybox.ProcessNoise(od.STRUCTURE)
    t0 = time.perf_counter()
    greybox.fit_batch(devices, od.FREE, noise=noise, n_starts=n_starts)
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    res = greybox.fit_batch(devices, od.FREE, noise=noise, n_starts=n_starts)
    warm_s = time.perf_counter() - t0
    say(f"process-noise fit_batch of {n}: first {first_s:.1f} s, warm {warm_s:.2f} s")
    figures = {
        "process_devices": n,
        "process_fits_per_min": round(60.0 * n / warm_s, 1),
        "process_first_s": round(first_s, 2),
        "process_converged": int(sum(r.status == "converged" for r in res.results.values())),
        "process_groups": res.groups,
    }
    return devices, res, figures


def population_z(results):
    """Recovery z-scores of the known population median and spread from batch estimates."""
    kinds = {"absorptance": "random", "thermal.tau_s": "random"}
    pop = greybox.population.population_from_batch(results, kinds)
    out = {}
    for path, (med, sd) in POPULATION.items():
        p = pop.parameters[path]
        out[path] = {
            "median": round(float((p.log_mu - np.log(med)) / p.log_mu_se), 2),
            "omega": round(float((p.omega - sd) / p.omega_se), 2),
        }
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--devices", type=int, default=512)
    ap.add_argument("--loop-sample", type=int, default=12)
    ap.add_argument("--dask", action="store_true", help="also time fit_distributed")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--process",
        type=int,
        default=None,
        help="also time fit_batch with process noise of this many Ornstein-Uhlenbeck devices "
        "(default: none; 3 in --smoke)",
    )
    ap.add_argument("--smoke", action="store_true", help=SMOKE_HELP)
    args = ap.parse_args(argv)
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731
    runs = RUNS
    if args.smoke:
        args.devices, args.loop_sample, runs = 4, 1, RUNS[:2]
        args.process = 3 if args.process is None else min(args.process, 3)

    t0 = time.perf_counter()
    devices, _ = synthetic_devices(args.devices + args.loop_sample + 1, seed=19, runs=runs)
    say(f"generated {len(devices)} devices x {len(runs)} runs in {time.perf_counter() - t0:.1f} s")
    free = SPEC.free_parameters()

    # (a) loop of fit calls over new devices of one structure, the first one apart
    loop_devs = devices[: args.loop_sample + 1]
    single = {}
    t0 = time.perf_counter()
    d = loop_devs[0]
    single[d.name] = greybox.fit(d.model, d.experiments, d.free)
    first_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    for d in loop_devs[1:]:
        single[d.name] = greybox.fit(d.model, d.experiments, d.free)
    loop_s = time.perf_counter() - t0
    loop_rate = args.loop_sample / loop_s
    say(f"loop: first fit {first_s:.2f} s, then {loop_s / args.loop_sample:.2f} s per new device")
    t0 = time.perf_counter()
    for i, d in enumerate(loop_devs[1:]):
        greybox.fit(d.model, d.experiments, _own_numbers(d.free, i))
    own_rate = args.loop_sample / (time.perf_counter() - t0)
    say(f"loop, each device with its own bounds and scales: {own_rate:.1f} fits/s")
    with_bands_rate = notebook_loop(loop_devs, single)
    say(f"loop of a notebook's steps per device (fit, band, delta method): {with_bands_rate:.1f}/s")

    # (b, c) the batch: a first call compiles, the second is timed phase by phase
    batch_devs = devices[: args.devices]
    t0 = time.perf_counter()
    greybox.fit_batch(batch_devs, free)
    batch_first_s = time.perf_counter() - t0
    with PhaseTimer() as phases:
        t0 = time.perf_counter()
        batch = greybox.fit_batch(batch_devs, free)
        batch_s = time.perf_counter() - t0
    alone_s = compiled_alone(batch_devs, free, batch.chunk_size)
    say(
        f"batch: first call {batch_first_s:.1f} s, warm {batch_s:.2f} s; phases {phases.t}; "
        f"its compiled work alone {alone_s:.2f} s"
    )
    common = [k for k in single if k in batch.results]
    agree = max_rel_diff({k: batch[k] for k in common}, {k: single[k] for k in common})

    out = {
        "backend": jax.default_backend(),
        "devices": args.devices,
        "runs_per_device": len(runs),
        "frames_per_run": [e.n_frames for e in devices[0].experiments],
        "loop_fits_per_s": round(loop_rate, 4),
        "own_numbers_fits_per_s": round(own_rate, 4),
        "loop_with_bands_per_s": round(with_bands_rate, 4),
        "loop_first_fit_s": round(first_s, 3),
        "loop_sample": args.loop_sample,
        "batch_fits_per_min": round(60.0 * args.devices / batch_s, 1),
        "batch_s": round(batch_s, 3),
        "batch_first_s": round(batch_first_s, 3),
        "solve_share": round((phases.t["solve"] + phases.t["models"]) / batch_s, 3),
        "solve_s": round(phases.t["solve"], 3),
        "prepare_s": round(phases.t["plan"] + phases.t["build"], 3),
        "plan_s": round(phases.t["plan"], 3),
        "residual_tests_s": round(phases.t["residual_tests"], 3),
        "models_s": round(phases.t["models"], 3),
        "sandwich_s": round(phases.t["sandwich"], 3),
        "scores_s": round(phases.t["scores"], 3),
        "assemble_s": round(phases.t["assemble"], 3),
        "host_overlap_s": round(sum(phases.t.values()) - batch_s, 3),
        "compiled_alone_s": round(alone_s, 3),
        "compiled_alone_share": round(alone_s / batch_s, 3),
        "batch_chunk": batch.chunk_size,
        "batch_calls": batch.n_calls,
        "bytes_per_solve": batch.bytes_per_item,
        "batch_vs_fit_max_rel": agree,
        "batch_valid": int(sum(r.valid for r in batch.results.values())),
        # what one device's complete result holds (pickled: as fit_distributed ships it)
        "result_kb_per_device": round(
            np.mean([len(pickle.dumps(r)) for r in list(batch.results.values())[:8]]) / 1e3, 1
        ),
    }
    if args.dask:
        t0 = time.perf_counter()
        dask_res = greybox.population.fit_distributed(batch_devs, free, n_workers=args.workers)
        dask_s = time.perf_counter() - t0
        out["dask_fits_per_min"] = round(60.0 * args.devices / dask_s, 1)
        out["dask_vs_batch_max_rel"] = max_rel_diff(dask_res.results, batch.results)
        out.update(gather_figures(dict(batch.results), batch_devs))
        out.update(dask_again(batch_devs, free, args.workers, say))
    if args.process:
        out.update(process_noise_batch(args.process, say)[2])
    if args.devices >= 8:
        out["population_z"] = population_z(batch.results)
    out["peak_rss_mb"] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
    out["load_average"] = round(os.getloadavg()[0], 2)
    print(json.dumps(out))


if __name__ == "__main__":
    main()
