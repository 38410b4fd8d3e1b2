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

from greybox._model.data import Experiment
from greybox._model.device import check_method, default_method, with_camera
from greybox._model.errors import InputError
from greybox._model.freeparams import FreeParameter
from greybox._model.parameters import check_scalar_path
from greybox._model.plausibility import (
    out_of_range_settings,
    parse_physical_ranges,
    physical_ranges,
)
from greybox._model.spec import DeviceSpecError
from greybox._model.waveforms import from_samples, stack_channels
from greybox._registry import DeviceNotFound, ResolvedDevice, resolve
from greybox.io._csv import (
    CsvTable,
    channel_numbers,
    check_increasing,
    find_column,
    read_csv,
    time_column,
)
from greybox.io._noise_table import NOISE_MODELS, REFUSED_WITH_PROCESS, parse_noise
from greybox.io._toml import TOML_NAME, TomlDocument, excerpt
from greybox.io._waveform_spec import (
    WAVEFORM_TYPES,
    check_log_against_description,
    waveform_from_description,
)

ROLES = ("estimation", "validation")
MAX_RUNS = 1000
MAX_STARTS = 1000
MAX_FIT_STEPS = 100_000
MAX_SOLVER_STEPS = 10_000_000  # [fit] solver_max_steps (and params.json's model.solver)
MAX_PROBLEM_BYTES = 4e9  # estimated working memory of a fit (GREYBOX_MAX_PROBLEM_GB overrides)
_TOP_KEYS = {"experiment", "model", "camera", "fit", "runs", "columns", "data", "candidates"}
_TOP_KEYS |= {"noise"}  # [noise]: the process-noise structure (greybox/io/_noise_table.py)
_TOP_KEYS |= {"physical_ranges"}  # overrides of the device's physical ranges (_plausibility)
_TOP_KEYS |= {"csv"}  # [csv] delimiter: the cell separator of every run file (else detected)
# the delimiter as written in [csv] (a tab may be spelled out: TOML's "\t" or "tab")
_DELIMITER_SPELLINGS = {",": ",", ";": ";", "\t": "\t", "comma": ",", "semicolon": ";", "tab": "\t"}
# a candidate carries a whole structure: options, free list (with bounds and priors), known
# values (settings over [experiment] settings), [fit] settings over [fit], its own [noise]
_CANDIDATE_KEYS = {"name", "model", "free", "settings", "fit", "noise", "nests"}
# how a run's file is read and its clock and inputs interpreted: [data] for every run, or
# the same keys in a [[runs]] table for that run (a run's `columns` mapping is merged
# over [columns] key by key)
_DATA_KEYS = {
    "header",
    "columns",
    "time_origin",
    "input_delay_s",
    "input_applied",
    "constant_inputs",
}
TIME_ORIGINS = ("first_row", "file")
INPUT_APPLIED = ("at_reading", "before_reading")
MAX_ERRORS = 20  # loader problems listed together before the rest are only counted
_EXPERIMENT_KEYS = {"device", "description", "settings"}
_CAMERA_KEYS = {"fps", "exposure_ms", "um_per_px", "noise_um"}
_NOISE_UNITS = {"px": None, "um": 1e-6, "nm": 1e-9, "m": 1.0}  # per-frame sigma columns
_FIT_KEYS = {"method", "loss", "n_starts", "seed", "max_steps", "solver_max_steps", "free"}
_FIT_KEYS |= {"noise_model"}  # "none" (least squares) or "process" (Kalman-filter likelihood)
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
_RUN_KEYS = {
    "name",
    "file",
    "role",
    "waveform",
    "settings",
    "y_column",
    "t_start_s",
    "notes",
} | _DATA_KEYS


def accepted_keys() -> dict:
    """{table: set of keys} that experiment.toml may hold ("" = the top level); each is
    documented in experiments/README.md (tests/test_format_docs.py compares the two)."""
    return {
        "": set(_TOP_KEYS),
        "experiment": set(_EXPERIMENT_KEYS),
        "camera": set(_CAMERA_KEYS),
        "fit": set(_FIT_KEYS),
        "fit.free": set(_FREE_KEYS),
        "data": set(_DATA_KEYS),
        "runs": set(_RUN_KEYS),
        "candidates": set(_CANDIDATE_KEYS),
    }


class InputErrors(InputError):
    """Several loader problems at once (`errors`, each an `InputError`); the message lists
    them one per line, up to `MAX_ERRORS`."""

    def __init__(self, errors, total: int | None = None):
        self.errors = tuple(errors)
        total = len(self.errors) if total is None else total
        lines = [str(e) for e in self.errors[:MAX_ERRORS]]
        if total > len(lines):
            lines.append(f"... and {total - len(lines)} more")
        super().__init__(f"{total} problems (fix them all, then run again):\n" + "\n".join(lines))
        # where: the first problem's file (each line of the message names its own)
        self.file = next((e.file for e in self.errors if e.file is not None), None)


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
    # per output: (column, unit as written in the file) or None when the file lacks it
    output_columns: tuple = ()
    time_shift_s: float = 0.0  # file time of the run's t = 0 (time_origin)
    defaults: tuple = ()  # (path, SI value) settings filled by the device's run_settings rule


@dataclasses.dataclass(frozen=True)
class ExperimentSet:
    """A loaded experiment folder: everything `greybox fit` needs, in SI.

    - `device`: the resolved device (`spec`, where it came from, its module); `options`: the
      structural options from [model] with defaults filled in; `model`: the device built
      with those options, the [camera] settings and the fixed [experiment] settings.
    - `camera`: the [camera] values given, in SI ({"fps", "exposure_s", "m_per_px"}, each
      optional); `fixed`: {path: SI value} applied to every run.
    - `estimation`, `validation`: `Experiment`s by role; `runs`: `RunInfo` per run.
    - `free`: `FreeParameter`s to fit; `fit_options`: keyword arguments for `greybox._estimate.fit`
      (for a process-noise fit only those that apply to it: n_starts, seed, max_steps).
    - `noise`: the checked `[noise]` table (`NoiseTable`) of a process-noise fit, else None;
      `candidate`: the name of the ``[[candidates]]`` entry loaded, else None.
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
    physical_ranges: dict = dataclasses.field(default_factory=dict)  # path -> PhysicalRange
    # `[noise]` (a `NoiseTable`) for a process-noise fit; None: least squares
    noise: object = None
    candidate: str | None = None  # the ``[[candidates]]`` entry loaded, if one was

    @property
    def noise_model(self) -> str:
        return "none" if self.noise is None else "process"

    def run_info(self, name: str) -> RunInfo:
        return next(r for r in self.runs if r.name == name)

    @property
    def spec(self):
        return self.device.spec

    @property
    def device_name(self) -> str:
        return self.device.spec.name


def build_device(spec, options: dict):
    """`spec.model(options)`, bounded in time; a failure in the device's own code is the
    user's (`greybox._usercode.UserCodeError`, naming their file and line)."""
    from greybox._usercode import running_users_code

    with running_users_code(f"building device {spec.name!r} with options {options}"):
        return spec.model(options)


def trial_simulation(device, model, experiment, method: str) -> None:
    """Trace one simulation of `experiment` abstractly (`eqx.filter_eval_shape`: shapes only,
    nothing compiled or run), bounded in time: a device whose model code loops forever or
    raises when traced fails here, at load, naming its file and line, not after minutes of
    fitting (or after other candidates were fitted). Built-in devices are greybox's own,
    tested code and skip it."""
    if device.source == "builtin":
        return
    import equinox as eqx
    import jax

    from greybox._simulate.schedules import schedules_for
    from greybox._simulate.simulate import as_arrays
    from greybox._usercode import running_users_code

    padded = schedules_for(model, [experiment], on_device=False)
    row = {k: v[0] for k, v in padded.items()}
    model = as_arrays(model)
    # a trace sees structure and shapes, never values: one trial per structure is enough
    # (a batch of many folders of one device pays it once)
    key = (
        jax.tree.structure(model),
        tuple(np.shape(x) for x in jax.tree.leaves(model)),
        tuple((k, v.shape) for k, v in row.items()),
        method,
    )
    try:
        if key in _TRIED:
            return
    except TypeError:  # a static field that cannot be hashed: no reuse
        key = None
    where = device.location if device.source == "file" else None
    what = f"a trial simulation of device {device.spec.name!r} (tracing its model code)"
    with running_users_code(what, where):
        eqx.filter_eval_shape(_trial, model, row, method)
    if key is not None:
        if len(_TRIED) > 256:
            _TRIED.clear()
        _TRIED.add(key)


_TRIED: set = set()  # the structures `trial_simulation` has traced without a problem


def _trial(model, row: dict, method: str):
    """What a fit's simulation calls of the device's code. The adaptive path calls the
    vector field once, not a whole ODE solve (tracing diffrax costs seconds, and the
    device's code is the same at every step)."""
    import jax
    import jax.numpy as jnp

    from greybox._model.device import ODE_METHODS, AbstractSteppedDevice
    from greybox._simulate.simulate import observe_schedule

    if method not in ODE_METHODS or isinstance(model, AbstractSteppedDevice):
        return observe_schedule(model, row, method=method)
    x0 = jnp.asarray(model.initial_state(), dtype=float)
    dx = model.vector_field(row["t_start"], x0, row["levels"][0])
    return dx, jax.vmap(model.output)(x0[None])


def configure_model(spec, options: dict, camera: dict, fixed: dict):
    """`spec`'s model built with `options`, the given camera settings and fixed values applied.

    `camera` may hold "m_per_px" and "exposure_s" (SI); absent ones keep the device default.
    """
    from greybox._model.parameters import set_values

    model = with_camera(
        build_device(spec, options),
        exposure_s=camera.get("exposure_s"),
        m_per_px=camera.get("m_per_px"),
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
            if (
                isinstance(v, bool)
                or not isinstance(v, (int, float))
                or not abs(v) < 1e300
                or not math.isfinite(v)
            ):
                raise doc.error(
                    f"{repr(v)[:40]} must be a finite number (SI units)", *path, key[:60]
                )
            try:
                check_scalar_path(model, k)
            except (ValueError, AttributeError, IndexError, TypeError) as err:
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


def _free_parameters(
    doc: TomlDocument, entries, spec, options: dict, model, fixed: dict, where=("fit", "free")
) -> tuple:
    """[fit] free (or a candidate's free, at TOML path `where`): paths from the device's
    parameter table (a bare path takes the standard fit's settings, or the table's bounds), or
    tables that change what they give of the bare path's settings (`_table_entry`). Absent:
    the device's standard list."""
    list_where = where
    defaults = {p.path: p for p in spec.free_parameters(options)}
    if entries is None:
        return tuple(defaults.values())
    if not isinstance(entries, list) or not entries:
        raise doc.error(
            "must be a non-empty list of parameter paths (or tables); leave it "
            "out for the device's standard fit",
            *list_where,
        )
    table = {p.path: p for p in spec.parameter_table(options)}
    allowed = ", ".join(table)
    out, seen = [], set()
    for i, e in enumerate(entries):
        where = (*list_where, i)
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
            device_value = check_scalar_path(model, path)
        except ValueError as err:
            raise doc.error(str(err).split(": ", 1)[-1], *where) from None
        info = table[path]
        fp = defaults.get(path) or FreeParameter(
            path,
            unit=info.unit,
            lower=info.lower,
            upper=info.upper if info.lower is not None else None,
        )
        if isinstance(e, dict):
            fp = _table_entry(doc, e, fp, where)
        if fp.initial is None and not fp.per_experiment and spec.start_values is None:
            # the device's own value is the start (no hook moves it): a start on a bound has
            # no image under the fit's transform, so say so now, before any candidate fits
            try:
                fp.check_value(device_value)
            except ValueError as err:
                raise doc.error(
                    f"{str(err).split(': ', 1)[-1]} (the device's value; in the table form: "
                    f'{{ path = "{path}", initial = ... }})',
                    *where,
                ) from None
        if path in seen:
            raise doc.error(f"{path!r} is listed twice", *where)
        if path in fixed:
            raise doc.error(
                f"{path!r} is also fixed in [experiment] settings; fit it or fix it", *where
            )
        seen.add(path)
        out.append(fp)
    return tuple(out)


_PAIRS = (("lower", "upper"), ("prior_median", "prior_log_sd"))  # given together or not at all


def _table_entry(doc: TomlDocument, e: dict, bare: FreeParameter, where) -> FreeParameter:
    """A [fit] free table `e`: the bare path's parameter `bare` with what the table gives
    changed. Bounds and a prior are pairs: a table that gives either bound (or either prior
    key) sets both sides (lower only: no upper bound); one that gives neither keeps the bare
    path's. So `{ path = "rad", initial = 0.5 }` is the device's `rad`, bounds and all,
    started at 0.5 (unbounded, the heating-system plate's radiation ran to 483 against its
    declared upper bound of 50, 150 s a start)."""
    per_run = e.get("per_run", bare.per_experiment)
    if not isinstance(per_run, bool):
        raise doc.error(f"{per_run!r} must be true or false", *where, "per_run")
    start = doc.number(e, "initial", *where)
    scale = doc.number(e, "scale", *where, positive=True)
    kw = {k: doc.number(e, k, *where) for pair in _PAIRS for k in pair}
    for pair in _PAIRS:
        if all(kw[k] is None for k in pair):
            kw.update({k: getattr(bare, k) for k in pair})
    try:
        fp = dataclasses.replace(
            bare,
            unit=doc.string(e, "unit", *where, default=bare.unit),
            per_experiment=per_run,
            scale=bare.scale if scale is None else scale,
            initial=bare.initial if start is None else start,
            **kw,
        )
    except ValueError as err:
        raise doc.error(str(err).split(": ", 1)[-1], *where, "path") from None
    if start is not None:
        try:
            fp.check_value(start)
        except ValueError as err:
            kept = not any(k in e for k in _PAIRS[0])
            hint = " (the device's bounds, kept: give lower and upper to change them)" * kept
            raise doc.error(f"{str(err).split(': ', 1)[-1]}{hint}", *where, "initial") from None
    return fp


def _camera(doc: TomlDocument, data: dict) -> dict:
    """[camera] in SI. Each key is checked on its own; when some are wrong, `InputErrors`
    carries every problem and (its `partial` attribute) the usable rest, with a stand-in
    image scale when um_per_px is wrong or missing, so that the runs are still checked
    without repeating a [camera] problem for every pixel column."""
    errors: list = []
    cam = _attempt(errors, doc.table, data, "camera", required=False, fallback={})
    _attempt(errors, doc.check_keys, cam, _CAMERA_KEYS, "camera")
    fps = _attempt(errors, doc.number, cam, "fps", "camera", positive=True, unit="frames/s")
    exposure_ms = _attempt(
        errors, doc.number, cam, "exposure_ms", "camera", nonneg=True, unit="ms (0 = instantaneous)"
    )
    um_per_px = _attempt(
        errors, doc.number, cam, "um_per_px", "camera", positive=True, unit="um per pixel"
    )
    noise_um = _attempt(
        errors, doc.number, cam, "noise_um", "camera", positive=True, unit="um (1-sigma per frame)"
    )
    if errors:
        err = InputErrors(errors)
        err.partial = {
            "fps": fps,
            "exposure_s": None if exposure_ms is None else exposure_ms * 1e-3,
            # a wrong or misspelt um_per_px: a stand-in (nothing is fitted with it)
            "m_per_px": 1e-6 if um_per_px is None else um_per_px * 1e-6,
            "noise_m": None if noise_um is None else noise_um * 1e-6,
        }
        raise err
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
        "noise_m": None if noise_um is None else noise_um * 1e-6,
    }


def _read_noise(table: CsvTable, outputs, refs, camera: dict) -> np.ndarray | None:
    """Known per-frame noise (N, n_y) [SI] from the tracker's ``sigma_<unit>`` column (one
    output) or ``<output>_sigma_<unit>`` columns, for length outputs; None if absent.

    Every output with readings needs its column (a fit either knows the noise of every
    reading or estimates it); a column in px needs [camera] um_per_px."""
    cols = []
    for ch, ref in zip(outputs, refs):
        prefixes = [f"{ch.name}_sigma_"] + (["sigma_"] if len(outputs) == 1 else [])
        found = [c for c in table.header if any(c.startswith(p) for p in prefixes)]
        found = [c for c in found if c.rsplit("_", 1)[-1] in _NOISE_UNITS]
        if ch.si_unit != "m" or not found:
            cols.append(None)
            continue
        unit = found[0].rsplit("_", 1)[-1]
        scale = _NOISE_UNITS[unit] if unit != "px" else camera["m_per_px"]
        if scale is None:
            raise InputError(
                "a per-frame noise in pixels needs the image scale: add um_per_px to [camera]",
                file=table.file,
                line=table.header_line,
                field=found[0],
            )
        cols.append(table.numbers(found[0], allow_missing=True, what="noise sd") * scale)
    with_data = [j for j, r in enumerate(refs) if r is not None]
    if all(cols[j] is None for j in with_data):
        return None
    missing = [j for j in with_data if cols[j] is None]
    if missing:
        return _mixed_noise(table, outputs[missing[0]])
    n = table.n_rows
    return np.column_stack([c if c is not None else np.full(n, np.nan) for c in cols])


def _known_noise(doc: TomlDocument, spec, camera: dict, fit_options: dict, experiments) -> None:
    """Per-frame noise columns must be in every run or none; [camera] noise_um declares one
    noise level for every reading instead (set as the fit's known sigma)."""
    with_noise = [e.name for e in experiments if e.sigma is not None]
    if with_noise and len(with_noise) < len(experiments):
        missing = next(e.name for e in experiments if e.sigma is None)
        raise doc.error(
            f"runs {with_noise} have a per-frame noise column but {missing!r} has none; give it "
            "in every run or in none (the fit either knows the noise or estimates it)",
            "runs",
        )
    if camera.get("noise_m") is None:
        return
    if with_noise:
        raise doc.error(
            "the run files give a per-frame noise (sigma columns); declare noise_um or give "
            "the columns, not both",
            "camera",
            "noise_um",
        )
    if any(c.si_unit != "m" for c in spec.outputs):
        raise doc.error(
            f"is a camera position noise, but {spec.name}'s outputs are not positions",
            "camera",
            "noise_um",
        )
    spread = max(
        (float(np.nanmax(e.y) - np.nanmin(e.y)) for e in experiments if np.isfinite(e.y).any()),
        default=0.0,
    )
    if spread > 0 and camera["noise_m"] > NOISE_OVER_SPREAD * spread:
        raise doc.error(
            f"{camera['noise_m'] * 1e6:g} um is {camera['noise_m'] / spread:.3g} x the whole "
            f"range of the readings ({spread * 1e6:.4g} um): with that noise the data would say "
            "nothing. Give the tracker's per-frame noise (typically 0.01 to 1 px), in um",
            "camera",
            "noise_um",
        )
    fit_options["sigma"] = camera["noise_m"]


def _mixed_noise(table: CsvTable, channel):
    raise InputError(
        f"has a per-frame noise column for some outputs but not for {channel.name}; give "
        f"{channel.name}_sigma_<unit> too, or none (the fit then estimates the noise)",
        file=table.file,
        line=table.header_line,
        field=f"{channel.name}_sigma",
    )


def _read_outputs(
    doc: TomlDocument, table: CsvTable, outputs, camera: dict, y_choice, run: str, mapping: dict
):
    """(readings (N, n_y) in SI, ColumnRef or None per output).

    A multi-output device's run may lack some outputs (a single-sensor log): those columns
    are NaN (masked out of the fit); at least one output must have a valid reading. px
    columns need [camera] um_per_px."""
    from greybox.io._units import to_si

    single = len(outputs) == 1
    ys, refs = [], []
    for ch in outputs:
        ref = find_column(
            table,
            ch,
            required=single,
            mapped=mapping.get(ch.name),
            choose=y_choice if single else None,
            choose_hint=f' with y_column = "..." in run {run!r} of {doc.file}',
        )
        if ref is None:
            ys.append(np.full(table.n_rows, np.nan))
            refs.append(None)
            continue
        v = table.numbers(ref.column, allow_missing=True, what=f"{ch.name} reading in {ref.unit}")
        if ref.conv is None and camera["m_per_px"] is None:
            raise InputError(
                f"pixel readings need the image scale: add um_per_px to [camera] "
                f"in {doc.file} (or give {ch.name}_um)",
                file=table.file,
                line=table.header_line,
                field=ref.column,
            )
        if single and not np.isfinite(v).any():
            raise InputError(
                f"every reading is empty or NaN ({v.size} rows); a run needs at "
                "least one tracked frame (check the tracker output)",
                file=table.file,
                line=table.lines[0],
                field=ref.column,
            )
        ys.append(to_si(v, ref.conv, camera["m_per_px"]))
        refs.append(ref if np.isfinite(v).any() else None)
    y = np.column_stack(ys)
    if not np.isfinite(y).any():
        names = ", ".join(c.column_names()[0] for c in outputs)
        raise InputError(
            f"no output has a valid reading: give at least one of {names} (or map a column "
            "to an output in experiment.toml [columns]); a missing output is left out of the "
            "fit for this run",
            file=table.file,
            line=table.header_line,
            field=outputs[0].name,
        )
    return y, refs


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


def _logged_wave(t, v, end: float, name: str, delay: float, before: bool):
    """A logged input as a held waveform; `before`: the level logged at row k acted since row
    k-1 (``input_applied = "before_reading"``); `delay`: levels act `delay` s later (the
    first level is held before then)."""
    tt, vv = np.asarray(t, dtype=float), np.asarray(v, dtype=float)
    if before and tt.size > 1:
        tt, vv = tt[:-1], vv[1:]
    if delay > 0:
        tt = np.concatenate([tt[:1], tt + delay])
        vv = np.concatenate([vv[:1], vv])
        end = end + delay
    return from_samples(tt, vv, end_s=end, name=name)


def _read_inputs(
    doc: TomlDocument,
    table: CsvTable,
    entry: dict,
    t: np.ndarray,
    inputs,
    camera: dict,
    path: tuple,
    csv_name: str,
    rules: dict,
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
    constants = rules["constant_inputs"]
    logged = {}
    for ch in inputs:
        if ch.name in constants:
            continue
        ref = find_column(
            table,
            ch,
            required=kind == "logged" and len(inputs) == 1,
            mapped=rules["columns"].get(ch.name),
        )
        if ref is not None:
            what = f"logged {ch.description or ch.name} in {ref.unit}"
            logged[ch.name] = (ref, channel_numbers(table, ch, ref, what=what))
    lacking = [ch for ch in inputs if ch.name not in logged and ch.name not in constants]
    if (desc is None or kind == "logged") and lacking and (logged or kind == "logged"):
        names = ", ".join(ch.column_names()[0] for ch in lacking)
        raise InputError(
            f"missing input column(s) {names} "
            f"({', '.join(c.description or c.name for c in lacking)}); log them, map them "
            "in experiment.toml [columns], or declare an input that "
            f"stayed constant: constant_inputs = {{ {lacking[0].name} = 0 }} (SI units, "
            f"{lacking[0].si_unit}) in [data] or in the run",
            file=table.file,
            line=table.header_line,
            field=lacking[0].column_names()[0],
        )
    if desc is None and lacking:
        names = " and ".join(ch.column_names()[0] for ch in inputs)
        raise doc.error(
            f'no input waveform: describe it (waveform = {{ type = "pulse_train", '
            f"power_mW = ..., period_ms = ..., duty = 0.5, n_pulses = ... }}) or log "
            f'it in {csv_name} ({names}) with waveform = {{ type = "logged" }}',
            *path,
            "waveform",
        )
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    end = t[-1] + step
    if kind is None or kind == "logged":
        delay, before = rules["input_delay_s"], rules["input_applied"] == "before_reading"
        if delay >= end - t[0]:  # every input level would act after the last reading
            raise doc.error(
                f"{delay:g} s is not shorter than the record ({end - t[0]:g} s): no reading "
                "would see any input; give the delay in s (e.g. 0.05)",
                *path,
                "input_delay_s",
            )
        waves = []
        for ch in inputs:
            if ch.name in constants:
                waves.append(from_samples(t[:1], [constants[ch.name]], end_s=end + delay))
            else:
                ref, v = logged[ch.name]
                waves.append(_logged_wave(t, v, end, ref.column, delay, before))
        parts = [logged[c.name][0].column for c in inputs if c.name in logged]
        parts += [
            f"{c.name} = {constants[c.name]:g} {c.si_unit}" for c in inputs if c.name in constants
        ]
        text = f"logged in {', '.join(parts)} ({t.size} samples, each held until the next)"
        if before:
            text += "; each level applied from the previous reading"
        if delay:
            text += f"; applied {delay:g} s late"
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
    ref, values = logged[ch.name]
    slack = max(
        1.0 / camera["fps"] if camera["fps"] else 0.0,
        camera["exposure_s"] or 0.0,
        step,
    )
    where = f"{doc.file}:{doc.where.line(*path, 'waveform')}"
    check_log_against_description(table, ref, values, t, wave, ch, slack, where)
    return wave, text, "described (log checked)"


NOISE_OVER_SPREAD = 1.0  # readings whose whole range is below one noise sd carry no signal
NEAR_CONSTANT = 1e-9  # relative spread of an output below which it is rounding, not signal


def _check_run_consistency(doc, table, path, t, y, refs, valid, wave, t_start) -> None:
    """Frames against the waveform's extent and t_start_s; outputs that never vary."""
    if t[-1] < 0:
        raise InputError(
            f"every frame ({t[0]:g} s to {t[-1]:g} s) is before the waveform starts at 0 s; "
            "t_s counts from the start of the waveform",
            file=table.file,
            line=table.lines[0],
            field="t_s",
        )
    if t_start > t[-1]:
        raise doc.error(
            f"{t_start:g} s is after the last frame ({t[-1]:g} s in {table.file}); "
            "t_start_s is when the device starts from rest, within the recording",
            *path,
            "t_start_s",
        )
    end = float(wave.end_s)
    step = float(np.median(np.diff(t))) if t.size > 1 else 0.0
    slack = max(3 * step, 0.1 * max(end, 0.0), 1e-9)
    if t[-1] > end + slack or t[0] > end:
        raise InputError(
            f"frames run from {t[0]:g} s to {t[-1]:g} s but the run's waveform ends at "
            f"{end:g} s (see {doc.file}:{doc.where.line(*path, 'waveform')}); describe the "
            "whole recording (add tail_ms / end_s for the time after the last pulse, check "
            "n_pulses and period_ms) or cut the CSV to the described part",
            file=table.file,
            line=table.lines[-1],
            field="t_s",
        )
    for j, ref in enumerate(refs):
        if ref is None:
            continue
        col = ref.column
        v = y[:, j][np.isfinite(y[:, j])]
        spread = float(np.ptp(v)) if v.size >= 2 else None
        # a spread within the rounding of the readings themselves is no signal either
        if spread is not None and spread <= NEAR_CONSTANT * float(np.max(np.abs(v))):
            what = "is" if spread == 0.0 else f"stays within {spread:.3g} of"
            raise InputError(
                f"every valid reading {what} {v[0]:g} ({v.size} frames): the output never "
                f"varies beyond {NEAR_CONSTANT:g} of its size (rounding), so nothing in it can "
                "be fitted (check the tracker output, the column and the laser)",
                file=table.file,
                line=table.lines[0],
                field=col,
            )


def _check_ranges(doc: TomlDocument, ranges: dict, settings: dict, *path) -> None:
    """Settings against their physical ranges ({path: PhysicalRange}); every one outside."""
    bad = [doc.error(msg, *path, key) for key, msg in out_of_range_settings(settings, ranges)]
    if len(bad) == 1:
        raise bad[0]
    if bad:
        raise InputErrors(bad)


def _physical_ranges(doc: TomlDocument, data: dict, spec, options: dict) -> dict:
    """{path: PhysicalRange}: the device's, with [physical_ranges] overrides (every problem
    in that table reported together)."""
    table = spec.parameter_table(options)
    given = data.get("physical_ranges")
    overrides, problems = parse_physical_ranges({} if given is None else given, table)
    bad = [doc.error(msg, "physical_ranges", *((key,) if key else ())) for key, msg in problems]
    if len(bad) == 1:
        raise bad[0]
    if bad:
        raise InputErrors(bad)
    return physical_ranges(table, overrides)


def fit_memory_estimate(fs) -> float:
    """Estimated peak resident bytes of fitting `fs` (`greybox._estimate.memory`: base + one
    solve of the runs padded to the longest; every start and the noise re-fit reuse it, and
    the starts a CPU runs side by side add at most
    `greybox._estimate.starts.SIDE_BY_SIDE_BYTES`)."""
    from greybox._estimate import memory as _memory

    runs = list(fs.estimation) + list(fs.validation)
    try:
        n_states = int(fs.model.n_states)
    except Exception:  # a device that only knows its size once built for a run
        n_states = 8
    working = _memory.solve_bytes(
        runs=len(runs),
        frames=max(e.n_frames for e in runs),
        states=n_states,
        outputs=len(fs.spec.outputs),
        inputs=len(fs.spec.inputs),
        raw=sum(len(fs.estimation) if p.per_experiment else 1 for p in fs.free),
    )
    return _memory.peak_bytes(working)


def max_problem_bytes() -> float:
    """The memory a fit may need: GREYBOX_MAX_PROBLEM_GB, else `MAX_PROBLEM_BYTES`."""
    import os

    env = os.environ.get("GREYBOX_MAX_PROBLEM_GB")
    try:
        value = float(env) * 1e9 if env else MAX_PROBLEM_BYTES
    except ValueError:
        return MAX_PROBLEM_BYTES
    return value if math.isfinite(value) and value > 0 else MAX_PROBLEM_BYTES


def check_problem_size(fs, max_bytes: float | None = None) -> None:
    """Estimate a fit's peak memory before anything is compiled (`fit_memory_estimate`, the
    model `greybox._estimate.memory` shares with compare, fit-many and design); refuse one
    too large."""
    if max_bytes is None:
        max_bytes = max_problem_bytes()
    need = fit_memory_estimate(fs)
    if need > max_bytes:
        runs = list(fs.estimation) + list(fs.validation)
        longest = max(runs, key=lambda e: e.n_frames)
        n_raw = sum(len(fs.estimation) if p.per_experiment else 1 for p in fs.free)
        raise InputError(
            f"the fit would need about {need / 1e9:.1f} GB ({len(runs)} runs padded to the "
            f"longest, {longest.n_frames} frames in run {longest.name!r}, "
            f"{n_raw} fitted values); the limit is {max_bytes / 1e9:.1f} GB. Decimate the "
            "long runs (keep every k-th frame), split them into shorter runs, or fit fewer "
            "runs or per-run parameters (GREYBOX_MAX_PROBLEM_GB raises the limit)",
            file=str(Path(fs.directory) / TOML_NAME),
            field="runs",
        )


def _column_mapping(doc: TomlDocument, table, spec, *path) -> dict:
    """{"time" | channel name: (column, unit or None, where)} from a ``columns`` table."""
    if not isinstance(table, dict):
        raise doc.error(
            'must be a table of signal = column, e.g. { time = "Time", T1 = { column = '
            '"T1", unit = "degC" } }, or (with header = false) a list of column names',
            *path,
        )
    allowed = ["time", *(c.name for c in spec.inputs), *(c.name for c in spec.outputs)]
    out = {}
    for key, value in table.items():
        where = (*path, key)
        if key not in allowed:
            raise doc.error(
                f"{key!r} is not a signal of {spec.name}; map one of {', '.join(allowed)}",
                *where,
            )
        if isinstance(value, str) and value.strip():
            col, unit = value, None
        elif isinstance(value, dict):
            doc.check_keys(value, {"column", "unit"}, *where)
            col = doc.string(value, "column", *where, required=True)
            unit = doc.string(value, "unit", *where)
        else:
            raise doc.error(
                f"{repr(value)[:40]}: give the file's column name, or "
                '{ column = "...", unit = "..." }',
                *where,
            )
        for other, (taken, _, _) in out.items():
            if taken.strip() == col.strip():
                raise doc.error(
                    f"column {excerpt(col)} is already the {other!r} signal; two signals "
                    "cannot be read from one column",
                    *where,
                )
        out[key] = (col, unit, f"{doc.file}:{doc.where.line(*where)}")
    return out


def _data_rules(doc: TomlDocument, table: dict, spec, base: dict | None, *path) -> dict:
    """The data-reading rules of [data] (`base` None) or a run (over `base`)."""
    rules = (
        dict(base)
        if base is not None
        else {
            "header": True,
            "names": None,
            "columns": {},
            "time_origin": None,
            "input_delay_s": 0.0,
            "input_applied": "at_reading",
            "constant_inputs": {},
            "delimiter": None,
        }
    )
    if "header" in table:
        if not isinstance(table["header"], bool):
            raise doc.error(f"{table['header']!r} must be true or false", *path, "header")
        rules["header"] = table["header"]
    cols = table.get("columns")
    if isinstance(cols, list):
        if not cols or not all(isinstance(c, str) and c.strip() for c in cols):
            raise doc.error(
                "the columns of a header-less file: a list of quoted names in file order, "
                'e.g. ["t_s", "T1_degC", "T2_degC", "H1_pct", "H2_pct"]',
                *path,
                "columns",
            )
        if len(set(cols)) != len(cols):
            raise doc.error("a column name appears twice", *path, "columns")
        rules["names"] = list(cols)
        rules["columns"] = {}  # a run's own columns replace [columns]
    elif cols is not None:
        rules["columns"] = _column_mapping(doc, cols, spec, *path, "columns")
    if rules["header"] and rules["names"] is not None and "columns" in table:
        raise doc.error(
            "a list of column names is for a header-less file: add header = false (or "
            'map columns with a table: columns = { T1 = "..." })',
            *path,
            "columns",
        )
    if not rules["header"] and rules["names"] is None and base is not None:
        raise doc.error(
            'a header-less file needs its column names: columns = ["t_s", ...] in file order',
            *path,
            "header",
        )
    if "time_origin" in table:
        v = table["time_origin"]
        if isinstance(v, str) and v in TIME_ORIGINS:
            rules["time_origin"] = v
        elif isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            rules["time_origin"] = float(v)
        else:
            raise doc.error(
                f'{repr(v)[:40]}: use "first_row" (t = 0 at the first row), "file" '
                "(the file's clock as is) or the file time [s] that is t = 0",
                *path,
                "time_origin",
            )
    if "input_delay_s" in table:
        rules["input_delay_s"] = doc.number(table, "input_delay_s", *path, nonneg=True, unit="s")
    if "input_applied" in table:
        rules["input_applied"] = doc.string(table, "input_applied", *path, choices=INPUT_APPLIED)
    if "constant_inputs" in table:
        ci = table["constant_inputs"]
        names = {c.name: c for c in spec.inputs}
        if not isinstance(ci, dict):
            raise doc.error(
                "must be a table { input = level } (SI units), e.g. { H2 = 0 }",
                *path,
                "constant_inputs",
            )
        out = dict(rules["constant_inputs"])
        for k in ci:
            if k not in names:
                raise doc.error(
                    f"{k!r} is not an input of {spec.name} ({', '.join(names)})",
                    *path,
                    "constant_inputs",
                    k,
                )
            v = doc.number(ci, k, *path, "constant_inputs")
            problem = names[k].check_range(np.array([v]))
            if problem:
                raise doc.error(
                    f"{problem}, outside the channel's range", *path, "constant_inputs", k
                )
            out[k] = v
        rules["constant_inputs"] = out
    return rules


def _quoted_path(rel: str, limit: int = 200) -> str:
    """A file name for a message: whole when it is printable and not absurdly long."""
    return repr(rel) if len(rel) <= limit else excerpt(rel, limit)


def _time_origin(table: CsvTable, t: np.ndarray, tref, rule, where: str) -> float:
    """File time [s] of the run's t = 0; refuses a clock far from 0 without a declared rule."""
    if rule == "first_row":
        return float(t[0])
    if isinstance(rule, float):
        return rule
    span = float(t[-1] - t[0])
    if rule is None and t[0] > 1.0 and t[0] > 0.1 * span:
        raise InputError(
            f"the clock starts at {t[0]:g} s, far from 0 for a {span:g} s run: the model "
            "would sit at rest from t = 0 with the inputs off before the first row. Declare "
            f'time_origin = "first_row" (t = 0 at the first row) in [data] or in the run '
            f'({where}), or time_origin = "file" to keep the clock as it is',
            file=table.file,
            line=table.lines[0],
            field=tref.column,
        )
    return 0.0


def _load_run(
    doc: TomlDocument,
    i: int,
    entry: dict,
    directory: Path,
    spec,
    model,
    camera: dict,
    names: set,
    data_rules: dict,
    options: dict,
    fixed: dict,
    free_paths: set,
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
    try:
        csv_path = (directory / rel).resolve()
        csv_path.is_file()
    except (OSError, ValueError) as err:  # a name too long, a NUL byte, a link loop
        raise doc.error(
            f"{repr(rel)[:60]} is not a usable file name ({type(err).__name__}); name the "
            "run's CSV relative to the experiment folder",
            *path,
            "file",
        ) from None
    if not csv_path.is_relative_to(directory.resolve()):
        raise doc.error(
            f"{_quoted_path(rel)} lies outside the experiment folder ({directory.resolve()}); "
            "a run's CSV must be inside the folder that holds experiment.toml (or a subfolder "
            "of it): copy the file into the folder and name it relative to it (links that "
            "leave the folder are refused too)",
            *path,
            "file",
        )
    if not csv_path.is_file():
        raise doc.error(
            f"{repr(rel)[:60]} does not exist; put the run's CSV there or fix the "
            "file name (relative to the experiment folder)",
            *path,
            "file",
        )
    t_start = doc.number(entry, "t_start_s", *path, default=0.0)
    settings = _settings(doc, entry.get("settings", {}), model, *path, "settings")
    y_choice = doc.string(entry, "y_column", *path)
    rules = _data_rules(doc, entry, spec, data_rules, *path)

    table = read_csv(
        directory / rel,  # as the user named it (messages), checked above to lie inside
        names=None if rules["header"] else rules["names"],
        delimiter=rules["delimiter"],
    )
    t, tref = time_column(table, rules["columns"].get("time"))
    check_increasing(table, t, tref.column)
    shift = _time_origin(
        table, t, tref, rules["time_origin"], f"{doc.file}:{doc.where.line(*path)}"
    )
    t = t - shift
    y, refs = _read_outputs(doc, table, spec.outputs, camera, y_choice, name, rules["columns"])
    valid = np.any(np.isfinite(y), axis=1)
    _check_frame_rate(doc, table, t, valid, camera["fps"])
    wave, text, source = _read_inputs(
        doc, table, entry, t, tuple(spec.inputs), camera, path, csv_path.name, rules
    )
    _check_run_consistency(doc, table, path, t, y, refs, valid, wave, t_start)
    noise = _read_noise(table, spec.outputs, refs, camera)
    if noise is not None:  # a frame without a noise figure is left out, like a dropped frame
        y = np.where(np.isfinite(noise) & (noise > 0), y, np.nan)
    try:
        exp = Experiment(
            name,
            t,
            y if y.shape[1] > 1 else y[:, 0],
            wave,
            t_start_s=t_start,
            role=role,
            settings=settings,
            sigma=noise,
        )
    except ValueError as err:
        raise InputError(str(err), file=table.file) from None
    defaults = {}
    if spec.run_settings is not None:
        try:
            proposed = dict(spec.run_settings(model, exp, options) or {})
        except ValueError as err:
            raise doc.error(f"{spec.name}: {err}", *path) from None
        defaults = {
            k: float(v)
            for k, v in proposed.items()
            if k not in settings and k not in fixed and k not in free_paths
        }
        if defaults:
            exp = dataclasses.replace(exp, settings={**defaults, **settings})
    info = RunInfo(
        name,
        role,
        str(csv_path),
        ",".join(r.column for r in refs if r is not None),
        t.size,
        int(np.any(np.isfinite(y), axis=1).sum()),  # a frame with any valid reading counts
        text,
        source,
        output_columns=tuple(None if r is None else (r.column, r.unit) for r in refs),
        time_shift_s=shift,
        defaults=tuple(defaults.items()),
    )
    return exp, info


def _candidate(doc: TomlDocument, data: dict, index: int) -> dict:
    """``[[candidates]]`` entry `index`, its keys checked (each part is checked where it is
    used, at the candidate's own TOML path)."""
    entries = data.get("candidates")
    if not isinstance(entries, list) or not entries:
        raise doc.error(
            "no [[candidates]] tables; add one per structure to compare "
            '(name = "...", model = { ... }, optional free = [...], settings = { ... }, '
            "fit = { ... }, noise = { ... })",
            "candidates",
        )
    if not 0 <= index < len(entries):
        raise doc.error(f"there are {len(entries)} candidates, not {index + 1}", "candidates")
    entry = entries[index]
    if not isinstance(entry, dict):
        raise doc.error("each candidate is a [[candidates]] table", "candidates", index)
    doc.check_keys(entry, _CANDIDATE_KEYS, "candidates", index)
    doc.string(entry, "name", "candidates", index, required=True)
    doc.table(entry, "model", "candidates", index, required=False)
    for key in ("settings", "fit"):
        doc.table(entry, key, "candidates", index, required=False)
    if "fit" in entry and "free" in entry["fit"]:
        raise doc.error(
            "give the candidate's free list as its own key (free = [...]), not inside fit",
            "candidates",
            index,
            "fit",
            "free",
        )
    return entry


MAX_CANDIDATES = 32


def check_candidates(directory) -> list[str]:
    """Before the first fit of `greybox compare`: every candidate loads and fits in memory
    (one bad candidate must not surface after the others ran). Returns the names."""
    names = candidate_names(directory)
    for i in range(len(names)):
        check_problem_size(load_experiment_set(directory, candidate=i))
    return names


def candidate_names(directory) -> list[str]:
    """Names of the ``[[candidates]]`` structures of an experiment folder (loader-checked)."""
    return list(candidate_nests(directory))


def candidate_nests(directory) -> dict:
    """{name: names of the candidates it declares nested in it (``nests = [...]``)} of every
    ``[[candidates]]`` entry, in file order (names unique, `nests` naming other candidates)."""
    doc = TomlDocument(Path(directory) / TOML_NAME)
    entries = doc.data.get("candidates")
    if not isinstance(entries, list) or not entries:
        _candidate(doc, doc.data, 0)  # raises the located "no candidates" error
    if len(entries) > MAX_CANDIDATES:  # each candidate is a whole fit
        raise doc.error(
            f"{len(entries)} candidates; compare at most {MAX_CANDIDATES} structures at once",
            "candidates",
        )
    names = []
    for i in range(len(entries)):
        _candidate(doc, doc.data, i)  # checks the entry, name included
        names.append(entries[i]["name"])
    if len(set(names)) != len(names):
        raise doc.error(f"candidate names repeat ({names}); name each once", "candidates")
    out = {}
    for i, name in enumerate(names):
        nests = entries[i].get("nests", [])
        where = ("candidates", i, "nests")
        if not isinstance(nests, list) or not all(isinstance(n, str) for n in nests):
            raise doc.error("give a list of candidate names, e.g. [\"one node\"]", *where)
        for n in nests:
            if n == name or n not in names:
                raise doc.error(
                    f"{n!r} is not another candidate; the candidates are: "
                    + ", ".join(repr(m) for m in names if m != name),
                    *where,
                )
        out[name] = tuple(nests)
    return out


_NO_CAMERA = ("fps", "exposure_s", "m_per_px", "noise_m")


def _attempt(errors: list, fn, *args, fallback=None, **kwargs):
    """`fn(*args, **kwargs)`, or `fallback` with its problem(s) appended to `errors`."""
    try:
        return fn(*args, **kwargs)
    except InputErrors as err:
        errors.extend(err.errors)
    except InputError as err:
        errors.append(err)
    return fallback


def _raise_collected(errors: list) -> None:
    """Raise the collected problems: one as itself, several as `InputErrors` (capped)."""
    if len(errors) == 1:
        raise errors[0]
    if errors:
        raise InputErrors(errors)


def _device(doc: TomlDocument, exp: dict, directory: Path):
    device_ref = doc.string(exp, "device", "experiment", required=True)
    try:
        return resolve(device_ref, base_dir=directory)
    except (DeviceNotFound, DeviceSpecError) as err:
        raise doc.error(str(err), "experiment", "device") from None


def describe_hint(device) -> str:
    """A `greybox describe` command that finds `device` (a `ResolvedDevice`) from any folder:
    a file device by its absolute path, others by name."""
    if device.source == "file":
        return f"greybox describe {device.location}:{device.ref.partition(':')[2] or 'SPEC'}"
    return f"greybox describe {device.ref}"


def _options(doc: TomlDocument, device, model_table: dict) -> dict:
    try:
        return device.spec.resolve_options(model_table)
    except ValueError as err:
        key = str(err).split(":", 1)[0]
        raise doc.error(
            f"{str(err).split(': ', 1)[-1]} (`{describe_hint(device)}` lists the options)",
            "model",
            key,
        ) from None


def _base_model(doc: TomlDocument, spec, options: dict, camera: dict):
    try:
        return configure_model(spec, options, camera, {})
    except InputError:  # the device's own code failed: its file and line, not the toml's
        raise
    except ValueError as err:
        raise doc.error(f"cannot build the model ({err})", "model") from None


_FIT_DEFAULTS = {"loss": "huber", "n_starts": None, "seed": 0, "max_steps": 200}


def _fit_table(doc: TomlDocument, fitopt: dict, model, *where) -> dict:
    """The settings a [fit] table (or a candidate's `fit`, at `where`) gives, checked; only
    those given (the defaults are filled in after a candidate's are merged over [fit])."""
    from greybox._estimate.fit import LOSSES

    doc.check_keys(fitopt, _FIT_KEYS - ({"free"} if where != ("fit",) else set()), *where)
    out = {}
    if "method" in fitopt:
        method = doc.string(fitopt, "method", *where)
        try:
            out["method"] = check_method(model, method)
        except ValueError as err:
            raise doc.error(str(err).split(": ", 1)[-1], *where, "method") from None
    if "noise_model" in fitopt:
        out["noise_model"] = doc.string(fitopt, "noise_model", *where, choices=NOISE_MODELS)
    if "loss" in fitopt:
        out["loss"] = doc.string(fitopt, "loss", *where, choices=LOSSES)
    # n_starts absent: the fit's own rule (several starts when more than two shared values
    # are free)
    for key, minimum in (("n_starts", 1), ("seed", 0), ("max_steps", 1), ("solver_max_steps", 16)):
        if key in fitopt:
            out[key] = doc.integer(fitopt, key, *where, minimum=minimum)
    for key, cap, fix in (
        ("n_starts", MAX_STARTS, "a few starts (3-20) are enough; more only cost time"),
        ("max_steps", MAX_FIT_STEPS, "the optimiser's step budget; 200-2000 is usual"),
        ("solver_max_steps", MAX_SOLVER_STEPS, "the ODE solver's step budget per run"),
    ):
        if (out.get(key) or 0) > cap:
            raise doc.error(f"{out[key]} is more than {cap}; {fix}", *where, key)
    return out


def _fit_settings(doc: TomlDocument, data: dict, model, entry, index) -> tuple:
    """(fit_options, noise_model, noise table, its TOML path, the [fit] settings refused for
    a process-noise fit as `InputError`s) of the folder, or of candidate
    `index` (`entry`): its `fit` over [fit], its `noise` instead of [noise] (a candidate with
    its own `noise` is a process-noise fit unless its `fit` says otherwise)."""
    top = doc.table(data, "fit", required=False)
    given = _fit_table(doc, top, model, "fit")
    where_of = dict.fromkeys(given, ("fit",))
    noise_table, noise_where = data.get("noise"), ("noise",)
    if entry is not None:
        cand_where = ("candidates", index, "fit")
        own = _fit_table(doc, entry.get("fit") or {}, model, *cand_where)
        given.update(own)
        where_of.update(dict.fromkeys(own, cand_where))
        if "noise" in entry:
            noise_table, noise_where = entry["noise"], ("candidates", index, "noise")
            given.setdefault("noise_model", "process")
    noise_model = given.pop("noise_model", "none")
    if noise_model == "none" and noise_table is not None:
        raise doc.error('needs noise_model = "process" (or remove the noise table)', *noise_where)
    refused = []  # reported with the rest of the folder's problems (the noise table too)
    if noise_model == "process":
        for key, why in REFUSED_WITH_PROCESS.items():
            if key in given:
                refused.append(
                    doc.error(
                        f'does not apply with noise_model = "process": {why}', *where_of[key], key
                    )
                )
        # max_steps absent: the likelihood back end's own budget (damped Newton steps)
        fit_options = {k: given.get(k, _FIT_DEFAULTS[k]) for k in ("n_starts", "seed")}
        fit_options["max_steps"] = given.get("max_steps")
    else:
        fit_options = {**_FIT_DEFAULTS, **given}
        fit_options["method"] = check_method(model, given.get("method"))
    return fit_options, noise_model, (noise_table or {}), noise_where, refused


def _all_data_rules(doc: TomlDocument, data: dict, spec) -> dict:
    """[data] and [columns]: how every run's file is read (a run may override them)."""
    data_table = doc.table(data, "data", required=False)
    doc.check_keys(data_table, _DATA_KEYS, "data")
    data_rules = _data_rules(doc, data_table, spec, None, "data")
    if "columns" in data and "columns" in data_table:
        raise doc.error(
            "give the column mapping once: [columns] or [data] columns", "data", "columns"
        )
    if "columns" in data:
        data_rules["columns"] = _column_mapping(doc, data["columns"], spec, "columns")
    csv_table = doc.table(data, "csv", required=False)
    doc.check_keys(csv_table, {"delimiter"}, "csv")
    if "delimiter" in csv_table:
        spelled = doc.string(csv_table, "delimiter", "csv", choices=tuple(_DELIMITER_SPELLINGS))
        data_rules["delimiter"] = _DELIMITER_SPELLINGS[spelled]
    if not data_rules["header"] and data_rules["names"] is None:
        raise doc.error(
            'a header-less file needs its column names: columns = ["t_s", ...] in file order',
            "data",
            "header",
        )
    return data_rules


def load_experiment_set(directory, *, candidate: int | None = None) -> ExperimentSet:
    """Load and check an experiment folder (``experiment.toml`` + run CSVs).

    With `candidate` (an index into ``[[candidates]]``), that candidate's ``model`` options
    are applied over [model], its ``settings`` over [experiment] settings, its ``fit`` over
    [fit]; its ``free`` list and ``noise`` table (if given) replace [fit] free and [noise].
    Raises `InputError` (``file:line: field: problem and fix``) for one problem and
    `InputErrors` listing every problem (TOML and CSV, up to `MAX_ERRORS`) for several.
    """
    directory = Path(directory)
    if not directory.is_dir():
        raise InputError(
            f"{directory} is not a folder; give the experiment folder that holds {TOML_NAME}",
            file=str(directory),
            field="EXPERIMENT_DIR",
        )
    doc = TomlDocument(directory / TOML_NAME)  # an unreadable file stops here, alone
    data = doc.data
    # Every problem is collected: those of the TOML file (each section checked on its own,
    # a section with a problem replaced by its defaults) and those of every run's CSV, and
    # reported together. Only a problem that leaves nothing to check the runs against (no
    # device, a model that cannot be built, a broken [data]/[columns] mapping, no runs)
    # stops before the CSVs are read.
    errors: list = []
    _attempt(errors, doc.check_keys, data, _TOP_KEYS)
    exp = _attempt(errors, doc.table, data, "experiment", fallback={})
    _attempt(errors, doc.check_keys, exp, _EXPERIMENT_KEYS, "experiment")
    device = _attempt(errors, _device, doc, exp, directory)
    if device is None:
        _raise_collected(errors)
    spec = device.spec
    model_table = _attempt(errors, doc.table, data, "model", required=False, fallback={})
    chosen = None
    if candidate is not None:
        chosen = _attempt(errors, _candidate, doc, data, candidate)
        if chosen is not None:
            model_table = {**model_table, **(chosen.get("model") or {})}
    options = _attempt(errors, _options, doc, device, model_table)
    if options is None:  # check the rest against the device's default structure
        options = spec.resolve_options({})
    description = _attempt(errors, doc.string, exp, "description", "experiment", default="")
    try:
        camera = _camera(doc, data)
    except InputErrors as err:  # every problem of [camera]; the runs checked with the rest
        errors.extend(err.errors)
        camera = getattr(err, "partial", dict.fromkeys(_NO_CAMERA))
    except InputError as err:
        errors.append(err)
        camera = dict.fromkeys(_NO_CAMERA)
    base = _attempt(errors, _base_model, doc, spec, options, camera)
    if base is None:
        _raise_collected(errors)
    fixed = _attempt(
        errors, _settings, doc, exp.get("settings", {}), base, "experiment", "settings", fallback={}
    )
    ranges = _attempt(
        errors,
        _physical_ranges,
        doc,
        data,
        spec,
        options,
        fallback=physical_ranges(spec.parameter_table(options)),
    )
    _attempt(errors, _check_ranges, doc, ranges, fixed, "experiment", "settings")
    if chosen is not None and isinstance(chosen.get("settings"), dict):  # its known values
        where = ("candidates", candidate, "settings")
        own = _attempt(errors, _settings, doc, chosen["settings"], base, *where, fallback={})
        _attempt(errors, _check_ranges, doc, ranges, own, *where)
        fixed = {**fixed, **own}
    model = configure_model(spec, options, camera, fixed)
    settings = _attempt(errors, _fit_settings, doc, data, model, chosen, candidate)
    fit_options, noise_model, noise_table, noise_where, refused = settings or (
        {},
        "none",
        {},
        (),
        [],
    )
    errors.extend(refused)
    fitopt = data.get("fit") if isinstance(data.get("fit"), dict) else {}
    free_entries, free_where = fitopt.get("free"), ("fit", "free")
    if chosen is not None and "free" in chosen:
        free_entries, free_where = chosen["free"], ("candidates", candidate, "free")
    free = _attempt(
        errors, _free_parameters, doc, free_entries, spec, options, model, fixed, free_where
    )
    noise = None
    if noise_model == "process":
        noise = _attempt(errors, parse_noise, doc, noise_table, model, spec, *noise_where)

    runs = data.get("runs")
    data_rules = _attempt(errors, _all_data_rules, doc, data, spec)
    if not isinstance(runs, list) or not runs:
        errors.append(
            doc.error(
                "no runs; add one [[runs]] table per CSV (name, file, role, waveform)", "runs"
            )
        )
    elif len(runs) > MAX_RUNS:
        errors.append(
            doc.error(
                f"{len(runs)} runs; at most {MAX_RUNS} per experiment folder (split the "
                "folder, or merge short runs)",
                "runs",
            )
        )
    if data_rules is None or not isinstance(runs, list) or not runs or len(runs) > MAX_RUNS:
        _raise_collected(errors)  # no runs to check, or no mapping to read them with
    free_paths = {p.path for p in free or ()}
    experiments, infos, names = [], [], set()
    for i, entry in enumerate(runs):
        try:
            e, info = _load_run(
                doc,
                i,
                entry,
                directory,
                spec,
                model,
                camera,
                names,
                data_rules,
                options,
                fixed,
                free_paths,
            )
            _check_ranges(doc, ranges, dict(e.settings), "runs", i, "settings")
        except InputError as err:  # every run is checked; the problems are listed together
            errors.extend(err.errors if isinstance(err, InputErrors) else [err])
            if isinstance(entry, dict) and isinstance(entry.get("name"), str):
                names.add(entry["name"])
            continue
        names.add(e.name)
        experiments.append(e)
        infos.append(info)
    _raise_collected(errors)
    estimation = tuple(e for e in experiments if e.role == "estimation")
    validation = tuple(e for e in experiments if e.role == "validation")
    # a frame counts when any output has a valid reading (a one-sensor log of a two-sensor
    # board is a run: the missing output is masked out of the fit)
    if not estimation or sum(int(e.mask.any(axis=1).sum()) for e in estimation) == 0:
        raise doc.error(
            "the estimation set has zero frames: no run has role = "
            '"estimation" (with tracked frames); mark at least one run for '
            "estimation",
            "runs",
            0,
            "role",
        )
    if noise is None:  # the likelihood fit estimates the measurement noise itself
        _known_noise(doc, spec, camera, fit_options, experiments)
    else:
        _check_instantaneous(doc, model, noise_where)
        _check_k_step(doc, noise, experiments, noise_where)
        if camera.get("noise_m") is not None:
            errors.append(
                doc.error(
                    'does not apply with noise_model = "process" (the likelihood fit '
                    "estimates the measurement sd); hold it in the noise table instead: "
                    'fixed = { "measurement.<output>" = sd in m }',
                    "camera",
                    "noise_um",
                )
            )
            _raise_collected(errors)
    # a process-noise fit has no `method` of its own: trace the device's default path
    method = fit_options.get("method") or default_method(model)
    trial_simulation(device, model, estimation[0], method)
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
        physical_ranges=ranges,
        noise=noise,
        candidate=None if chosen is None else chosen["name"],
    )


def _check_k_step(doc: TomlDocument, noise, experiments, where) -> None:
    """The k-step prediction needs k frames of history: a horizon as long as the longest
    run predicts nothing."""
    longest = max(e.n_frames for e in experiments)
    if noise.k_step >= longest:
        raise doc.error(
            f"{noise.k_step} frames is not shorter than the longest run ({longest} frames); "
            f"give a horizon below {longest} (the default is 10)",
            *where,
            "k_step",
        )


def _check_instantaneous(doc: TomlDocument, model, where) -> None:
    """The Kalman filter reads each output at an instant (no exposure average)."""
    offsets, _ = model.readout.quadrature()
    if np.size(offsets) != 1 or float(np.ravel(offsets)[0]) != 0.0:
        raise doc.error(
            "the Kalman filter needs instantaneous readings: set [camera] exposure_ms = 0",
            *where,
        )
