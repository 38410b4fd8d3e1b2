"""Load the TCLab experiment folders next to this file into greybox objects.

Through the public experiment-folder loader (`greybox.io.load_experiment_set`), so the paper
comparison reads exactly what `greybox fit` reads: initial temperatures from each sensor's
first reading (the device's rule), heater levels held from each logged sample.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

import greybox
from greybox import Experiment
from greybox.blackbox import UniformData
from greybox.io import load_experiment_set

tclab = greybox.device_module("tclab")

HERE = Path(__file__).resolve().parent


def load_folder(folder: str | Path) -> dict[str, Experiment]:
    """{run name: Experiment} for an experiment folder (device must be "tclab").

    Each run carries its known settings (the initial readings, by the device's rule). The
    ambient is not a run setting: it belongs to the model (the paper's fixed 23 C in
    `tclab.SPEC.model()`, as the comparison table uses; `[model] ambient = "first_reading"`
    computes it inside the model from these readings and the sensor offsets)."""
    fs = load_experiment_set(folder)
    if fs.device_name != tclab.NAME:
        raise ValueError(f"{folder}/experiment.toml: device is not {tclab.NAME!r}")
    return {e.name: e for e in fs.estimation + fs.validation}


def uniform(exp: Experiment, dt_s: float = 1.0) -> UniformData:
    """Samples as a uniform record for the black-box models (u in %, y in degC).

    The logged samples are taken as uniform at `dt_s` (as the paper's ARX did; the 1-heater
    estimation run's spacing varies 0.99-1.02 s, which this ignores).
    """
    u = np.asarray(exp.inputs(exp.t_s)).reshape(exp.n_frames, -1)
    return UniformData(u, exp.y - 273.15, dt_s, name=exp.name)
