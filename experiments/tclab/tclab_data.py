"""Load the TCLab experiment folders next to this file into greybox objects.

A small reader for exactly what these folders use (logged heater inputs, T1/T2 in degC or K,
known settings); the general experiment-folder loader reads the same files.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

import greybox

from greybox.blackbox import UniformData
from greybox._data import Experiment
from greybox._waveforms import from_samples
tclab = greybox.device_module("tclab")

HERE = Path(__file__).resolve().parent


def _column(header: list[str], channel, path: Path) -> tuple[int, str]:
    for unit in channel.units:
        if f"{channel.name}_{unit}" in header:
            return header.index(f"{channel.name}_{unit}"), unit
    raise ValueError(
        f"{path}: no column for {channel.name}; add one of {', '.join(channel.column_names())}"
    )


def load_run(path: Path, *, name: str, role: str, settings: dict) -> Experiment:
    """One run CSV -> `Experiment` (y in K, inputs in % held from each logged sample)."""
    with open(path) as f:
        header = f.readline().strip().split(",")
    data = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    if "t_s" not in header:
        raise ValueError(f"{path}: needs a t_s column (time in s)")
    t = data[:, header.index("t_s")]
    u = np.column_stack(
        [
            tclab.INPUTS[k].to_si(data[:, i], unit)
            for k, (i, unit) in enumerate(_column(header, c, path) for c in tclab.INPUTS)
        ]
    )
    y = np.column_stack(
        [
            tclab.OUTPUTS[k].to_si(data[:, i], unit)
            for k, (i, unit) in enumerate(_column(header, c, path) for c in tclab.OUTPUTS)
        ]
    )
    inputs = from_samples(t, u, name=f"{path.name}: H1/H2")
    return Experiment(
        name=name,
        t_s=t,
        y=y,
        inputs=inputs,
        t_start_s=float(t[0]),
        role=role,
        settings={k: float(v) for k, v in settings.items()},
    )


def load_folder(folder: str | Path) -> dict[str, Experiment]:
    """{run name: Experiment} for an experiment folder (device must be "tclab")."""
    folder = Path(folder)
    spec = tomllib.loads((folder / "experiment.toml").read_text())
    if spec["experiment"]["device"] != tclab.NAME:
        raise ValueError(f"{folder}/experiment.toml: device is not {tclab.NAME!r}")
    runs = {}
    for run in spec["runs"]:
        if run.get("waveform", {}).get("type") != "logged":
            raise ValueError(f"{folder}/experiment.toml: run {run['name']}: TCLab runs are logged")
        runs[run["name"]] = load_run(
            folder / run["file"],
            name=run["name"],
            role=run["role"],
            settings=run.get("settings", {}),
        )
    return runs


def uniform(exp: Experiment, dt_s: float = 1.0) -> UniformData:
    """Samples as a uniform record for the black-box models (u in %, y in degC).

    The logged samples are taken as uniform at `dt_s` (as the paper's ARX did; the 1-heater
    estimation run's spacing varies 0.99-1.02 s, which this ignores).
    """
    u = np.asarray(exp.inputs(exp.t_s)).reshape(exp.n_frames, -1)
    return UniformData(u, exp.y - 273.15, dt_s, name=exp.name)
