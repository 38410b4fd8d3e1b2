"""Shared synthetic data for the core tests (kept small so JAX compiles stay shared)."""

import contextlib

import jax
import numpy as np

import greybox
from greybox._model.waveforms import PulseTrain
from greybox._simulate.synthetic import CameraDefects, record

# (power mW, period s) of the thesis's six stitched estimation runs
THESIS_RUNS = ((5, 0.2), (10, 0.4), (10, 0.6), (15, 0.8), (20, 1.0), (30, 0.5))


def chevron_runs(
    model,
    *,
    runs=THESIS_RUNS,
    duration_s=6.0,
    seed=0,
    burst_run=None,
    defects=None,
    role="estimation",
):
    """Pulse-train runs recorded by a defective camera; returns (experiments, clean readings)."""
    exps, cleans = [], []
    for i, (p_mw, period) in enumerate(runs):
        d = defects or CameraDefects()
        if burst_run == i:
            d = CameraDefects(d.fps, d.jitter_s, d.noise_m, d.drop_fraction, 6, 2e-6)
        wave = PulseTrain(p_mw * 1e-3, period, 0.5, int(np.ceil(duration_s / period)))
        e, c = record(model, wave, name=f"run{i + 1}", defects=d, seed=seed * 100 + i, role=role)
        exps.append(e)
        cleans.append(c)
    return exps, cleans


def two_run_chevron(seed):
    """A small chevron device (`population.Device`): two 3-pulse runs (10 and 20 mW, 0.3 s
    period) of a camera-read chevron whose absorptance is drawn around 0.6 (tau 45 ms)."""
    spec = greybox.get_device("chevron_laser")
    rng = np.random.default_rng(seed)
    model = greybox.devices.with_camera(spec.model(), exposure_s=10e-3)
    truth = greybox.parameters.set_values(
        model, ["absorptance", "thermal.tau_s"], [0.6 * np.exp(0.1 * rng.normal()), 0.045]
    )
    runs = [
        record(
            truth,
            PulseTrain(p, 0.3, n_pulses=3, delay_s=0.05, tail_s=0.2),
            name=f"r{j}",
            defects=CameraDefects(noise_m=0.05e-6),
            seed=seed * 10 + j,
        )[0]
        for j, p in enumerate((0.01, 0.02))
    ]
    return greybox.population.device_from_spec(spec, f"d{seed}", runs, model=model)


# a two-run chevron experiment.toml (estimation + validation) for loader and docs tests
GOOD_TOML = """\
[experiment]
device = "chevron_laser"
description = "two small runs"

[camera]
fps = 30
exposure_ms = 10
um_per_px = 0.645

[[runs]]
name = "est"
file = "est.csv"
role = "estimation"
waveform = { type = "pulse_train", power_mW = 20, period_ms = 400, n_pulses = 3, delay_ms = 200 }

[[runs]]
name = "val"
file = "val.csv"
role = "validation"
waveform = { type = "pulse_train", power_mW = 10, period_ms = 400, n_pulses = 3, delay_ms = 200 }
"""


@contextlib.contextmanager
def backend_compiles():
    """The names of the programs XLA compiles while the block runs (`jax.monitoring`'s
    backend-compile events), the listener removed on exit."""
    names = []

    def listen(event, duration, **kw):
        if event == "/jax/core/compile/backend_compile_duration":
            names.append(kw.get("fun_name", ""))

    jax.monitoring.register_event_duration_secs_listener(listen)
    try:
        yield names
    finally:
        jax.monitoring.unregister_event_duration_listener(listen)
