"""Many devices: a loop of `greybox.fit` calls vs one vmapped batch vs Dask (issue 19).

Synthetic chevron-laser devices (six short pulse-train runs each, 30 fps camera with jitter,
noise and dropped frames, from `greybox.record`) whose absorptance and thermal time constant
are drawn from a known log-normal population. For 8, 64 and 512 devices it measures devices
fitted per second by

(a) a Python loop of `greybox.fit` calls, one per device: timed on the first `--loop-sample`
    devices only (8 by default) and extrapolated per device (each call compiles its own
    solver, because a device's starting values are part of its problem's static structure);
(b) `fit_batch` (one compiled, vmapped solver; compile time included);
(c) `fit_distributed` on a Dask `LocalCluster` with 2 worker processes (worker start-up and
    compile included);

checks that the batch and Dask results agree with single-device `fit` / with each other, and
fits the population model to the batch estimates (recovery z-scores of the known median and
spread). The last line is one JSON object (fits per second at the largest size,
`batch_speedup` = batch / loop, `peak_rss_mb` of this process and of its children).

Usage (repository root):  .venv/bin/python benchmarks/many_devices.py [--sizes 8 64 512]
"""

from __future__ import annotations

import argparse
import json
import resource
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402

import greybox  # noqa: E402

SPEC = greybox.get_device("chevron_laser")
M_PER_PX = 0.645e-6
POPULATION = {"absorptance": (0.62, 0.08), "thermal.tau_s": (0.045, 0.15)}  # median, log-sd
RUNS = [(5, 200), (10, 200), (10, 300), (15, 400), (20, 600), (30, 800)]  # mW, ms
SPAN_S = 1.4  # pulses per run: short runs, ~50 frames each


def camera_model():
    return greybox.with_camera(SPEC.model(), exposure_s=10e-3, m_per_px=M_PER_PX)


def waveform(power_mw, period_ms):
    n = max(1, int(SPAN_S * 1e3 // period_ms))
    return greybox.PulseTrain(
        power_mw * 1e-3, period_ms * 1e-3, duty=0.5, n_pulses=n, delay_s=0.1, tail_s=0.2
    )


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
        dev_model = greybox.set_values(model, list(vals), list(vals.values()))
        exps = []
        for j, wave in enumerate(waves):
            offset = (312.0 + rng.uniform(-4, 4)) * M_PER_PX
            run_model = greybox.set_values(dev_model, ["camera.offset_m"], [offset])
            defects = greybox.CameraDefects(fps=30.0, noise_m=0.05e-6, drop_fraction=0.05)
            e, _ = greybox.record(
                run_model, wave, name=f"r{j}", defects=defects, seed=int(rng.integers(2**31))
            )
            exps.append(e)
        name = f"chevron{k:04d}"
        devices.append(greybox.device_from_spec(SPEC, name, exps, model=model))
        truth[name] = vals
    return devices, truth


def max_rel_diff(a, b):
    """Largest relative difference over every parameter value of two {name: FitResult}."""
    worst = 0.0
    for name in a:
        x, y = np.asarray(a[name].raw), np.asarray(b[name].raw)
        va = np.array([p.value for p in a[name].parameters])
        vb = np.array([p.value for p in b[name].parameters])
        worst = max(worst, float(np.max(np.abs(va - vb) / np.maximum(np.abs(vb), 1e-300))))
        del x, y
    return worst


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[8, 64, 512])
    ap.add_argument("--loop-sample", type=int, default=8)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--no-dask", action="store_true")
    args = ap.parse_args(argv)
    say = lambda m: print(m, file=sys.stderr, flush=True)  # noqa: E731

    biggest = max(args.sizes)
    t0 = time.perf_counter()
    all_devices, truth = synthetic_devices(biggest, seed=19)
    say(f"generated {biggest} devices x {len(RUNS)} runs in {time.perf_counter() - t0:.1f} s")
    frames = [e.n_frames for e in all_devices[0].experiments]

    # (a) loop of fit calls on a sample
    sample = all_devices[: args.loop_sample]
    t0 = time.perf_counter()
    single = {d.name: greybox.fit(d.model, d.experiments, d.free) for d in sample}
    loop_s = (time.perf_counter() - t0) / len(sample)
    loop_rate = 1.0 / loop_s
    say(f"loop: {loop_s:.2f} s per device (sample of {len(sample)}, extrapolated)")

    rows, batch_res = [], None
    for n in sorted(args.sizes):
        devs = all_devices[:n]
        jax.clear_caches()  # each size pays its own compile, as a fresh process would
        t0 = time.perf_counter()
        batch_res = greybox.fit_batch(devs, SPEC.free_parameters())
        batch_s = time.perf_counter() - t0
        row = {
            "devices": n,
            "loop_fits_per_s": loop_rate,
            "loop_s_extrapolated": loop_s * n,
            "batch_s": batch_s,
            "batch_fits_per_s": n / batch_s,
            "batch_chunk": batch_res.chunk_size,
            "batch_calls": batch_res.n_calls,
            "bytes_per_solve": batch_res.bytes_per_item,
        }
        common = [k for k in single if k in batch_res.results]
        row["batch_vs_fit_max_rel"] = max_rel_diff(
            {k: batch_res[k] for k in common}, {k: single[k] for k in common}
        )
        if not args.no_dask:
            t0 = time.perf_counter()
            dask_res = greybox.fit_distributed(devs, SPEC.free_parameters(), n_workers=args.workers)
            dask_s = time.perf_counter() - t0
            row["dask_s"] = dask_s
            row["dask_fits_per_s"] = n / dask_s
            row["dask_vs_batch_max_rel"] = max_rel_diff(dask_res.results, batch_res.results)
        row["batch_speedup"] = row["batch_fits_per_s"] / loop_rate
        say(json.dumps(row))
        rows.append(row)

    # population recovery from the largest batch
    kinds = {"absorptance": "random", "thermal.tau_s": "random"}
    pop = greybox.population_from_batch(batch_res.results, kinds)
    recovery = {}
    for path, (med, sd) in POPULATION.items():
        p = pop.parameters[path]
        recovery[path] = {
            "median": p.median,
            "median_true": med,
            "z_median": (p.log_mu - np.log(med)) / p.log_mu_se,
            "omega": p.omega,
            "omega_true": sd,
            "z_omega": (p.omega - sd) / p.omega_se,
            "new_device_95": p.new_device[1:],
        }
    n_valid = sum(r.valid for r in batch_res.results.values())
    say(json.dumps({"population": recovery, "flagged": pop.outliers, "valid": n_valid}))

    last = rows[-1]
    self_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    child_mb = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1024
    out = {
        "devices": last["devices"],
        "runs_per_device": len(RUNS),
        "frames_per_run": frames,
        "loop_fits_per_s": round(loop_rate, 4),
        "loop_note": f"timed on {len(sample)} devices, extrapolated per device",
        "batch_fits_per_s": round(last["batch_fits_per_s"], 3),
        "dask_fits_per_s": round(last.get("dask_fits_per_s", float("nan")), 3),
        "batch_speedup": round(last["batch_speedup"], 2),
        "peak_rss_mb": round(self_mb, 1),
        "peak_rss_child_mb": round(child_mb, 1),
        "by_size": {
            r["devices"]: {
                k: round(v, 4) if isinstance(v, float) else v
                for k, v in r.items()
                if k != "devices"
            }
            for r in rows
        },
        "population_z": {
            k: {"median": round(v["z_median"], 2), "omega": round(v["z_omega"], 2)}
            for k, v in recovery.items()
        },
    }
    print(json.dumps(out))


if __name__ == "__main__":
    main()
