"""Experiment folders: a TOML description plus one CSV per run -> a model and `Experiment`s.

The format is documented in ``experiments/README.md``. Loading checks everything a fit
relies on and raises `greybox.InputError` with ``file:line: field: what is wrong and how to
fix it`` (TOML lines for description problems, CSV lines with the header as line 1 for data
problems). Units are converted to SI here, once, through the device's channel declarations;
the library never sees a file unit. The device comes from its spec (`greybox.get_device`):
a built-in name, an installed package, or the user's own file next to the experiment.
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np

from greybox._channels import PIXELS
from greybox._data import Experiment
from greybox._device import check_method, with_camera
from greybox._errors import InputError
from greybox._freeparams import FreeParameter
from greybox._parameters import check_scalar_path
from greybox._registry import DeviceNotFound, ResolvedDevice, resolve
from greybox._spec import DeviceSpecError
from greybox._waveforms import from_samples, stack_channels
from greybox.io._csv import CsvTable, channel_column, check_increasing, read_csv, time_column
from greybox.io._toml import TOML_NAME, TomlDocument
from greybox.io._waveform_spec import (
    WAVEFORM_TYPES,
    check_log_against_description,
    waveform_from_description,
)

ROLES = ("estimation", "validation")
_TOP_KEYS = {"experiment", "model", "camera", "fit", "runs"}
_EXPERIMENT_KEYS = {"device", "description", "settings"}
_CAMERA_KEYS = {"fps", "exposure_ms", "um_per_px"}
_FIT_KEYS = {"method", "loss", "n_starts", "seed", "max_steps", "free"}
_FREE_KEYS = {
    "path",
    "unit",
    "lower",
    "upper",
    "per_run",
    "prior_median",
    "prior_log_sd",
    "initial",
    "scale",
}
_RUN_KEYS = {"name", "file", "role", "waveform", "settings", "y_column", "t_start_s", "notes"}

# --------------------------------------------------------------------------------------
# The experiment set


@dataclasses.dataclass(frozen=True)
class RunInfo:
    """What the report says about one run's file (the numbers live in its `Experiment`)."""

    name: str
    role: str
    file: str
    y_column: str
    n_rows: int
    n_valid: int
    waveform: str  # one-line description of the input
    input_source: str  # "described", "logged" or "described (log checked)"


@dataclasses.dataclass(frozen=True)
class ExperimentSet:
    """A loaded experiment folder: everything `greybox fit` needs, in SI.

    - `device`: the resolved device (`spec`, where it came from, its module); `options`: the
      structural options from [model] with defaults filled in; `model`: the device built
      with those options, the [camera] settings and the fixed [experiment] settings.
    - `camera`: the [camera] values given, in SI ({"fps", "exposure_s", "m_per_px"}, each
      optional); `fixed`: {path: SI value} applied to every run.
    - `estimation`, `validation`: `Experiment`s by role; `runs`: `RunInfo` per run.
    - `free`: `FreeParameter`s to fit; `fit_options`: keyword arguments for `greybox._fit`.
    """

    name: str
    directory: Path
    description: str
    device: ResolvedDevice
    options: dict
    model: object
    camera: dict
    fixed: dict
    estimation: tuple
    validation: tuple
    runs: tuple
    free: tuple
    fit_options: dict

    def run_info(self, name: str) -> RunInfo:
        return next(r for r in self.runs if r.name == name)

    @property
    def spec(self):
        return self.device.spec

    @property
    def device_name(self) -> str:
        return self.device.spec.name


def configure_model(spec, options: dict, camera: dict, fixed: dict):
    """`spec`'s model built with `options`, the given camera settings and fixed values applied.

    `camera` may hold "m_per_px" and "exposure_s" (SI); absent ones keep the device default.
    """
    from greybox._parameters import set_values

    model = with_camera(
        spec.model(options), exposure_s=camera.get("exposure_s"), m_per_px=camera.get("m_per_px")
    )
    return set_values(model, list(fixed), [float(v) for v in fixed.values()])


def _settings(doc: TomlDocument, table, model, *path) -> dict:
    """{dotted path: SI value} from a TOML table, each path checked against the model."""

    if not isinstance(table, dict):
        raise doc.error(
            "must be a table of path = value (SI units), e.g. { initial_rise_K = 0.0 }", *path
        )
    out = {}
    for key, value in table.items():
        flat = _flatten(value, key) if isinstance(value, dict) else {key: value}
        for k, v in flat.items():
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
                raise doc.error(f"{v!r} must be a finite number (SI units)", *path, key)
            try:
                check_scalar_path(model, k)
            except ValueError as err:
                raise doc.error(
                    f"{str(err).split(': ', 1)[-1]} (`greybox describe DEVICE` lists the "
                    "parameters)",
                    *path,
                    key,
                ) from None
            out[k] = float(v)
    return out


def _flatten(table: dict, prefix: str) -> dict:
    out = {}
    for k, v in table.items():
        if isinstance(v, dict):
            out.update(_flatten(v, f"{prefix}.{k}"))
        else:
            out[f"{prefix}.{k}"] = v
    return out


def _free_parameters(doc: TomlDocument, entries, spec, options: dict, model, fixed: dict) -> tuple:
    """[fit] free: paths from the device's parameter table (a bare path takes the standard
    fit's settings, or the table's bounds), or tables that define a free parameter (bounds,
    prior) in full. Absent: the device's standard list."""
    defaults = {p.path: p for p in spec.free_parameters(options)}
    if entries is None:
        return tuple(defaults.values())
    if not isinstance(entries, list) or not entries:
        raise doc.error(
            "must be a non-empty list of parameter paths (or tables); leave it "
            "out for the device's standard fit",
            "fit",
            "free",
        )
    table = {p.path: p for p in spec.parameter_table(options)}
    allowed = ", ".join(table)
    out, seen = [], set()
    for i, e in enumerate(entries):
        where = ("fit", "free", i)
        path = e if isinstance(e, str) else (e.get("path") if isinstance(e, dict) else None)
        if isinstance(e, dict):
            doc.check_keys(e, _FREE_KEYS, *where)
            path = doc.string(e, "path", *where, required=True)
        elif not isinstance(e, str):
            raise doc.error(f"{e!r}: give a quoted parameter path or a table", *where)
        if path not in table:
            raise doc.error(
                f"{path!r} is not a parameter of {spec.name}; the parameters are: {allowed}",
                *(where if isinstance(e, str) else (*where, "path")),
            )
        try:
            check_scalar_path(model, path)
        except ValueError as err:
            raise doc.error(str(err).split(": ", 1)[-1], *where) from None
        info = table[path]
        if isinstance(e, str):
            fp = defaults.get(path) or FreeParameter(
                path,
                unit=info.unit,
                lower=info.lower,
                upper=info.upper if info.lower is not None else None,
            )
        else:
            unit = doc.string(e, "unit", *where, default=info.unit)
            per_run = e.get("per_run", False)
            if not isinstance(per_run, bool):
                raise doc.error(f"{per_run!r} must be true or false", *where, "per_run")
            kw = {
                k: doc.number(e, k, *where)
                for k in ("lower", "upper", "prior_median", "prior_log_sd", "initial")
            }
            scale = doc.number(e, "scale", *where, positive=True)
            if scale is not None:
                kw["scale"] = scale
            try:
                fp = FreeParameter(path, unit=unit, per_experiment=per_run, **kw)
                if kw["initial"] is not None:
                    fp.check_value(kw["initial"])
            except ValueError as err:
                raise doc.error(str(err).split(": ", 1)[-1], *where, "path") from None
        if path in seen:
            raise doc.error(f"{path!r} is listed twice", *where)
        if path in fixed:
            raise doc.error(
                f"{path!r} is also fixed in [experiment] settings; fit it or fix it", *where
            )
        seen.add(path)
        out.append(fp)
    return tuple(out)


def _camera(doc: TomlDocument, data: dict) -> dict:
    cam = doc.table(data, "camera", required=False)
    doc.check_keys(cam, _CAMERA_KEYS, "camera")
    fps = doc.number(cam, "fps", "camera", positive=True, unit="frames/s")
    exposure_ms = doc.number(
        cam, "exposure_ms", "camera", nonneg=True, unit="ms (0 = instantaneous)"
    )
    um_per_px = doc.number(cam, "um_per_px", "camera", positive=True, unit="um per pixel")
    if fps is not None and exposure_ms is not None and exposure_ms > 1e3 / fps * 1.0001:
        raise doc.error(
            f"{exposure_ms:g} ms is longer than one frame interval (1/fps = "
            f"{1e3 / fps:g} ms); check fps and exposure_ms",
            "camera",
            "exposure_ms",
        )
    return {
        "fps": fps,
        "exposure_s": None if exposure_ms is None else exposure_ms * 1e-3,
        "m_per_px": None if um_per_px is None else um_per_px * 1e-6,
    }


def _read_outputs(doc: TomlDocument, table: CsvTable, outputs, camera: dict, y_choice, run: str):
    """(readings (N, n_y) in SI, column names); px columns need [camera] um_per_px."""
    ys, cols = [], []
    for ch in outputs:
        col = channel_column(
            table,
            ch,
            required=True,
            choose=y_choice if len(outputs) == 1 else None,
            choose_hint=f' with y_column = "..." in run {run!r} of {doc.file}',
        )
        unit = col[len(ch.name) + 1 :]
        v = table.numbers(col, allow_missing=True, what=f"{ch.name} reading in {unit}")
        if not np.isfinite(v).any():
            raise InputError(
                f"every reading is empty or NaN ({v.size} rows); a run needs at "
                "least one tracked frame (check the tracker output)",
                file=table.file,
                line=table.lines[0],
                field=col,
            )
        if unit == PIXELS and camera["m_per_px"] is None:
            raise InputError(
                f"pixel readings need the image scale: add um_per_px to [camera] "
                f"in {doc.file} (or give {ch.name}_um)",
                file=table.file,
                line=1,
                field=col,
            )
        ys.append(ch.to_si(v, unit, camera["m_per_px"]))
        cols.append(col)
    return np.column_stack(ys), cols


def _check_frame_rate(
    doc: TomlDocument, table: CsvTable, t: np.ndarray, valid: np.ndarray, fps: float | None
) -> None:
    """Frame intervals must match [camera] fps within 3x (catches t_s written in ms)."""
    if fps is None or valid.sum() < 3:
        return
    interval = float(np.median(np.diff(t[valid])))
    expected = 1.0 / fps
    if not expected / 3 <= interval <= 3 * expected:
        hint = (
            " (t_s looks like milliseconds: divide by 1000)"
            if 300 * expected <= interval <= 3000 * expected
            else ""
        )
        raise InputError(
            f"median frame interval {interval:g} s does not match 1/fps = "
            f"{expected:g} s from [camera] fps in {doc.file}{hint}; t_s must be "
            "seconds and fps the camera's frame rate",
            file=table.file,
            line=table.lines[0],
            field="t_s",
        )


def _read_inputs(
    doc: TomlDocument,
    table: CsvTable,
    entry: dict,
    t: np.ndarray,
    inputs,
    camera: dict,
    path: tuple,
    csv_name: str,
):
    """(waveform in SI, text, source) from the run's `waveform` and/or logged columns."""
    desc = entry.get("waveform")
    if desc is not None and not isinstance(desc, dict):
        raise doc.error(
            'must be a table such as { type = "pulse_train", power_mW = 20, '
            'period_ms = 500, duty = 0.5, n_pulses = 10 } or { type = "logged" }',
            *path,
            "waveform",
        )
    kind = None if desc is None else desc.get("type")
    if desc is not None and kind not in WAVEFORM_TYPES:
        raise doc.error(
            f"{kind!r} is not a waveform type; use one of "
            f"{', '.join(repr(k) for k in WAVEFORM_TYPES)}",
            *path,
            "waveform",
            "type",
        )
    if kind == "logged" and len(desc) > 1:
        extra = next(k for k in desc if k != "type")
        raise doc.error(
            "a logged waveform takes no other keys (the levels come from the CSV)",
            *path,
            "waveform",
            extra,
        )
    logged = {}
    for ch in inputs:
        col = channel_column(table, ch, required=kind == "logged")
        if col is not None:
            unit = col[len(ch.name) + 1 :]
            v = table.numbers(
                col, nonneg=True, what=f"logged {ch.description or ch.name} in {unit}"
            )
            logged[ch.name] = (col, unit, ch.to_si(v, unit))
    if desc is None and len(logged) < len(inputs):
        names = " and ".join(ch.column_names()[0] for ch in inputs)
        raise doc.error(
            f'no input waveform: describe it (waveform = {{ type = "pulse_train", '
            f"power_mW = ..., period_ms = ..., duty = 0.5, n_pulses = ... }}) or log "
            f'it in {csv_name} ({names}) with waveform = {{ type = "logged" }}',
            *path,
            "waveform",
        )
    end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
    if kind is None or kind == "logged":
        waves = [
            from_samples(t, logged[ch.name][2], end_s=end, name=logged[ch.name][0]) for ch in inputs
        ]
        text = (
            f"logged in {', '.join(logged[ch.name][0] for ch in inputs)} "
            f"({t.size} samples, each held until the next)"
        )
        wave = waves[0] if len(waves) == 1 else stack_channels(waves)
        return wave, text, "logged"
    if len(inputs) != 1:
        raise doc.error(
            f"a {kind} waveform describes one input, but {inputs[0].name}.. has "
            f"{len(inputs)} ({', '.join(c.name for c in inputs)}); log them in the "
            'CSV and use type = "logged"',
            *path,
            "waveform",
            "type",
        )
    ch = inputs[0]
    wave, text = waveform_from_description(desc, ch, doc.error, (*path, "waveform"))
    if ch.name not in logged:
        return wave, text, "described"
    col, unit, values = logged[ch.name]
    slack = max(
        1.0 / camera["fps"] if camera["fps"] else 0.0,
        camera["exposure_s"] or 0.0,
        float(np.median(np.diff(t))) if t.size > 1 else 0.0,
    )
    ref = f"{doc.file}:{doc.where.line(*path, 'waveform')}"
    check_log_against_description(table, col, values, t, wave, ch, unit, slack, ref)
    return wave, text, "described (log checked)"


def _load_run(
    doc: TomlDocument,
    i: int,
    entry: dict,
    directory: Path,
    spec,
    model,
    camera: dict,
    names: set,
):
    path = ("runs", i)
    if not isinstance(entry, dict):
        raise doc.error("each run is a [[runs]] table", *path)
    doc.check_keys(entry, _RUN_KEYS, *path)
    name = doc.string(entry, "name", *path, required=True)
    if name in names:
        raise doc.error(f"run name {name!r} is used twice; names must be unique", *path, "name")
    if not re.fullmatch(r"[A-Za-z0-9_.\-]+", name):
        raise doc.error(
            f"{name!r}: use letters, digits, '_', '-' or '.' only (it names figure files)",
            *path,
            "name",
        )
    role = doc.string(entry, "role", *path, required=True, choices=ROLES)
    rel = doc.string(entry, "file", *path, required=True)
    csv_path = (directory / rel).resolve()
    if not csv_path.is_relative_to(directory.resolve()):
        raise doc.error(
            f"{rel!r} lies outside the experiment folder; copy the run's CSV into the "
            "folder and name it relative to it (links that leave the folder are refused too)",
            *path,
            "file",
        )
    if not csv_path.is_file():
        raise doc.error(
            f"{rel} does not exist; put the run's CSV there or fix the "
            "file name (relative to the experiment folder)",
            *path,
            "file",
        )
    t_start = doc.number(entry, "t_start_s", *path, default=0.0)
    settings = _settings(doc, entry.get("settings", {}), model, *path, "settings")
    y_choice = doc.string(entry, "y_column", *path)

    table = read_csv(csv_path)
    t = time_column(table)
    check_increasing(table, t)
    y, y_cols = _read_outputs(doc, table, spec.outputs, camera, y_choice, name)
    valid = np.all(np.isfinite(y), axis=1)
    _check_frame_rate(doc, table, t, valid, camera["fps"])
    wave, text, source = _read_inputs(
        doc, table, entry, t, tuple(spec.inputs), camera, path, csv_path.name
    )
    try:
        exp = Experiment(
            name,
            t,
            y if y.shape[1] > 1 else y[:, 0],
            wave,
            t_start_s=t_start,
            role=role,
            settings=settings,
        )
    except ValueError as err:
        raise InputError(str(err), file=table.file) from None
    info = RunInfo(
        name, role, str(csv_path), ",".join(y_cols), t.size, int(valid.sum()), text, source
    )
    return exp, info


def load_experiment_set(directory) -> ExperimentSet:
    """Load and check an experiment folder (``experiment.toml`` + run CSVs).

    Raises `InputError` (``file:line: field: problem and fix``) for the first problem.
    """
    from greybox._fit import LOSSES

    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(
            f"{directory} is not a folder; give the experiment folder that holds {TOML_NAME}",
            file=str(directory),
            field="EXPERIMENT_DIR",
        )
    doc = TomlDocument(directory / TOML_NAME)
    data = doc.data
    doc.check_keys(data, _TOP_KEYS)
    exp = doc.table(data, "experiment")
    doc.check_keys(exp, _EXPERIMENT_KEYS, "experiment")
    device_ref = doc.string(exp, "device", "experiment", required=True)
    try:
        device = resolve(device_ref, base_dir=directory)
    except (DeviceNotFound, DeviceSpecError) as err:
        raise doc.error(str(err), "experiment", "device") from None
    spec = device.spec
    model_table = doc.table(data, "model", required=False)
    try:
        options = spec.resolve_options(model_table)
    except ValueError as err:
        key = str(err).split(":", 1)[0]
        raise doc.error(
            f"{str(err).split(': ', 1)[-1]} (`greybox describe {spec.name}` lists the options)",
            "model",
            key,
        ) from None
    description = doc.string(exp, "description", "experiment", default="")
    camera = _camera(doc, data)
    try:
        base = configure_model(spec, options, camera, {})
    except ValueError as err:
        raise doc.error(f"cannot build the model ({err})", "model") from None
    fixed = _settings(doc, exp.get("settings", {}), base, "experiment", "settings")
    model = configure_model(spec, options, camera, fixed)

    fitopt = doc.table(data, "fit", required=False)
    doc.check_keys(fitopt, _FIT_KEYS, "fit")
    method = doc.string(fitopt, "method", "fit")
    try:
        method = check_method(model, method)
    except ValueError as err:
        raise doc.error(str(err).split(": ", 1)[-1], "fit", "method") from None
    fit_options = {
        "method": method,
        "loss": doc.string(fitopt, "loss", "fit", default="huber", choices=LOSSES),
        "n_starts": doc.integer(fitopt, "n_starts", "fit", default=1),
        "seed": doc.integer(fitopt, "seed", "fit", default=0, minimum=0),
        "max_steps": doc.integer(fitopt, "max_steps", "fit", default=200),
    }
    free = _free_parameters(doc, fitopt.get("free"), spec, options, model, fixed)

    runs = data.get("runs")
    if not isinstance(runs, list) or not runs:
        raise doc.error(
            "no runs; add one [[runs]] table per CSV (name, file, role, waveform)", "runs"
        )
    experiments, infos, names = [], [], set()
    for i, entry in enumerate(runs):
        e, info = _load_run(doc, i, entry, directory, spec, model, camera, names)
        names.add(e.name)
        experiments.append(e)
        infos.append(info)
    estimation = tuple(e for e in experiments if e.role == "estimation")
    validation = tuple(e for e in experiments if e.role == "validation")
    if not estimation or sum(int(e.mask.all(axis=1).sum()) for e in estimation) == 0:
        raise doc.error(
            "the estimation set has zero frames: no run has role = "
            '"estimation" (with tracked frames); mark at least one run for '
            "estimation",
            "runs",
            0,
            "role",
        )
    if spec.start_values is not None:
        free = tuple(spec.start_values(model, free, estimation))
    return ExperimentSet(
        name=directory.resolve().name,
        directory=directory,
        description=description,
        device=device,
        options=options,
        model=model,
        camera=camera,
        fixed=fixed,
        estimation=estimation,
        validation=validation,
        runs=tuple(infos),
        free=free,
        fit_options=fit_options,
    )
