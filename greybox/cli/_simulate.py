"""`greybox simulate`: fitted params.json + a new input waveform -> CSV and figure, 95 % band."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from greybox.cli._trust import add_trust_device_option

HELP = """\
Simulate new input waveforms with a fitted model (the params.json written by
`greybox fit`; the data are not needed) and write the response of every output with a
95 % band from the parameter covariance (delta method), for any device.

--waveform SPEC (repeat it: one per input of a multi-input device) is one of
  pulse:power_mW=25,period_ms=300,duty=0.5,n=10[,delay_ms=200][,tail_ms=500]
      a square pulse train for a single-input device: level named after the input and its
      unit (laser_mW, power_W, H1_pct), period/delay/tail in ms (or _s), duty = on-fraction
      in (0, 1], n = pulses;
  NAME=pulse:...   NAME=const:LEVEL
      per input channel of a multi-input device, e.g. for tclab
      --waveform H1=pulse:H1_pct=50,period_s=600,duty=0.5,n=3 --waveform H2=const:0
      (const: a level in the channel's SI unit, or const:H2_pct=0); every input needs one;
  PATH.csv
      a logged trace: a time column (t_s) and one column per input (laser_mW; H1_pct and
      H2_pct), each level held until the next sample.

Output (in --out, written atomically):
  simulation.csv   t_s [s]; per output <name>_<unit>, <name>_lo95_<unit>, <name>_hi95_<unit>;
                   per input <name>_<unit> (e.g. y_um, ..., laser_mW; T1_K, ..., H1_pct)
                   (from the model's initial state: per-run camera offsets belong to the
                   recorded runs and are not part of a new waveform)
  simulation.png   each output with its band, the inputs beneath (--figure-format for svg/pdf)
  simulation.json  what the band is (confidence band or prediction interval), the
                   waveform, the columns, the params file used and its fit's verdict
                   (`fit_verdict`: valid, structure rejected, ...; anything but valid is
                   also said in a line)
--out must be absent, empty or an earlier greybox result (it holds a .greybox-result
marker); any other folder is refused before any work unless --force. A response or band
that is not finite (an overflowing waveform, a damaged params.json) is refused, not
written. Exit status: 0 done; 2 bad input (one line); 3 a bug (traceback; please report
it); 130 interrupted; 143 terminated.
--duration-s S simulates from 0 to S seconds (by default to the waveform's end; a constant
input has no end of its own: give --duration-s). --initial-state PATH=VALUE (repeatable;
SI units) sets a parameter that fixes the device's state at t = 0, e.g.
initial_T1_K=300 for tclab; `greybox describe DEVICE` lists them.
Units: every column is in the unit of the fit's files (params.json) or the channel's own
declared unit (a power declared in W is written in W).
By default the band is a 95 % confidence band of the model response (parameter
uncertainty only); --noise adds the fitted measurement noise sigma, giving a 95 %
prediction interval for new readings.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a new input waveform with fitted params.json (95 %% band)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--params",
        required=True,
        metavar="PARAMS_JSON",
        help="params.json written by `greybox fit`",
    )
    p.add_argument(
        "--waveform",
        required=True,
        action="append",
        metavar="SPEC",
        help="pulse:power_mW=..,period_ms=..,duty=..,n=.., NAME=pulse:.../NAME=const:LEVEL "
        "per input, or a CSV with t_s and every input column",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default="results/simulation",
        help="output folder (default results/simulation)",
    )
    p.add_argument(
        "--dt-ms",
        type=float,
        default=None,
        metavar="MS",
        help="output time step in ms (default 1, or the waveform's length / 5000 when longer)",
    )
    p.add_argument(
        "--duration-s",
        type=float,
        default=None,
        metavar="S",
        help="simulate from 0 to S seconds (default: the waveform's end)",
    )
    p.add_argument(
        "--initial-state",
        action="append",
        default=[],
        metavar="PATH=VALUE",
        help="a parameter that sets the state at t = 0, in SI (e.g. initial_T1_K=300); "
        "repeatable",
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out even if it is a non-empty folder greybox did not write",
    )
    from greybox.cli._figures import add_figure_format

    add_figure_format(p)
    add_trust_device_option(p)
    p.add_argument(
        "--noise",
        action="store_true",
        help="include measurement noise: prediction interval for camera readings",
    )
    p.set_defaults(func=run)
    return p


def _fmt(v: float) -> str:
    return f"{v:.6g}" if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")


def _file_unit(channel, unit):
    """(unit, (scale, offset)) of the fit's files for an output (params.json "file_units"),
    or None to use the display unit (pixels, or an older params.json without it)."""
    from greybox.io._units import channel_conversion

    if not isinstance(unit, str):
        return None
    try:
        conv = channel_conversion(channel, unit)
    except ValueError:
        return None
    return None if conv is None else (unit, conv)


def _column_unit(unit: str) -> str:
    return {"%": "pct"}.get(unit, unit)


def read_waveform(specs, inputs):
    """(waveform, description, specs) from --waveform: channel specs or one CSV."""
    from greybox._model.errors import InputError
    from greybox.io._waveform_spec import parse_channel_specs, waveform_from_csv

    specs = list(specs)
    csvs = [x for x in specs if x.lower().endswith(".csv") and "=" not in x]
    if not csvs:
        return (*parse_channel_specs(specs, inputs), specs)
    if len(specs) > 1:
        raise InputError("a CSV waveform holds every input; give it alone", field="--waveform")
    if not Path(csvs[0]).is_file():
        raise InputError(
            "no such file; give pulse:... (NAME=pulse:... per input) or the path of a "
            f"CSV with t_s,{','.join(c.column_names()[0] for c in inputs)} columns",
            file=csvs[0],
            field="--waveform",
        )
    return (*waveform_from_csv(csvs[0], inputs), specs)


def sample_times(
    wave, dt_ms, *, n_default: int, n_max: int, duration_s: float | None = None
) -> np.ndarray:
    """Output times [s] from 0 to the waveform's end (or `duration_s`): every `dt_ms`, by
    default 1 ms or the length / `n_default` when longer; more than `n_max` samples is
    refused."""
    from greybox._model.errors import InputError

    end = float(wave.end_s) if duration_s is None else float(duration_s)
    dt = dt_ms * 1e-3 if dt_ms is not None else max(1e-3, end / n_default)
    n = int(math.floor(end / dt + 1e-9)) + 1
    if n > n_max:
        raise InputError(f"{n} output samples; raise --dt-ms", field="--dt-ms")
    return np.arange(n) * dt


def simulation_columns(outputs, inputs, file_units, t, arrays, wave):
    """(header, columns, descriptions, peaks) of simulation.csv: time, then per output the
    response and its band (`arrays` = (y, lo, hi), SI) in the fit's file unit, then each
    input in its display unit."""
    from greybox.report._markdown import channel_unit

    y, lo, hi = arrays
    header, cols, described = ["t_s"], [t], {"t_s": "time [s]"}
    peaks = {}
    for j, ch in enumerate(outputs):
        conv = _file_unit(ch, file_units.get(ch.name))
        if conv is None:
            f, u = channel_unit(ch)
            conv = (u, (1.0 / f, 0.0))
        u, (scale, offset) = conv
        u = _column_unit(u)
        names = [f"{ch.name}_{u}", f"{ch.name}_lo95_{u}", f"{ch.name}_hi95_{u}"]
        header += names
        cols += [(a[:, j] - offset) / scale for a in (y, lo, hi)]
        described[names[0]] = f"{ch.description or ch.name} [{u}]"
        described[names[1]] = f"lower end of the band [{u}]"
        described[names[2]] = f"upper end of the band [{u}]"
        peaks[ch.name] = {"y": float(np.max(cols[-3])), "unit": u}
    levels = np.asarray(wave(t)).reshape(t.size, -1)
    for k, ch in enumerate(inputs):
        f, u = channel_unit(ch)
        u = _column_unit(u)
        header.append(f"{ch.name}_{u}")
        cols.append(levels[:, k] * f)
        described[header[-1]] = f"{ch.description or ch.name} [{u}]"
    return header, cols, described, peaks


def write_simulation(
    out, force, header, cols, meta, band, wave, device, text, outputs, inputs, fmt="png"
):
    """simulation.csv, simulation.json and simulation.<fmt>, written atomically to `out`."""
    from greybox.io._atomic import atomic_output_dir
    from greybox.io._drawing import drawing_beside
    from greybox.io._results import usual_permissions

    figure = (
        f"simulation.{fmt}",
        "band_figure",
        (band, wave),
        dict(
            title=f"{device}: {text}"[:200],
            output_labels=tuple((c.description or c.name, c.si_unit) for c in outputs),
            input_labels=tuple((c.description or c.name, c.si_unit) for c in inputs),
            output_channels=outputs,
            input_channels=inputs,
            file_units=meta.get("file_units") or {},
        ),
    )
    table = np.column_stack(cols)
    with atomic_output_dir(out, kind="simulate", force=force) as tmp:
        usual_permissions(tmp)
        with drawing_beside(tmp, [figure]):  # in the drawing process, where `run` has one
            rows = [",".join(header)]
            for k in range(table.shape[0]):
                rows.append(",".join([f"{table[k, 0]:.6f}"] + [_fmt(v) for v in table[k, 1:]]))
            (tmp / "simulation.csv").write_text("\n".join(rows) + "\n")
            (tmp / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")


def run(args) -> int:
    from greybox.cli._ticker import Ticker, to_stderr

    with Ticker(to_stderr) as tick:  # speaks only after 5 s of silence (compile, writing)
        return _run(args, tick)


def _run(args, tick) -> int:
    from greybox.io._jax_setup import configure

    configure()  # float64, compiled programs kept on disk
    from greybox._model.errors import InputError
    from greybox.io._atomic import check_output_dir
    from greybox.io._drawing import drawing_process

    if args.dt_ms is not None and not (math.isfinite(args.dt_ms) and args.dt_ms > 0):
        raise InputError(f"must be a positive number of ms, got {args.dt_ms}", field="--dt-ms")
    check_output_dir(args.out, force=args.force, inputs=[args.params])
    if args.duration_s is not None and not (math.isfinite(args.duration_s) and args.duration_s > 0):
        raise InputError(
            f"must be a positive number of seconds, got {args.duration_s}", field="--duration-s"
        )

    # a drawing process's start (matplotlib) overlaps the simulation; it draws the figure
    with drawing_process():
        return _simulate_and_write(args, tick)


def _simulate_and_write(args, tick) -> int:
    from greybox._model.errors import InputError
    from greybox._usercode import trusted_devices
    from greybox.io._params_file import load_params

    with trusted_devices(args.params, args.trust_device):
        # least squares or process noise (params/2 and /3)
        fitted = with_initial_state(load_params(args.params), args.initial_state)
    inputs, outputs = tuple(fitted.spec.inputs), tuple(fitted.spec.outputs)
    wave, text, specs = read_waveform(args.waveform, inputs)
    process = fitted.noise is not None
    t = sample_times(
        wave,
        args.dt_ms,
        n_default=2000 if process else 5000,
        n_max=200_000 if process else 2_000_000,
        duration_s=args.duration_s,
    )
    n = t.size
    tick.phase_is("computing the response and its band (compiling the model first)")
    if process:
        band = process_band(fitted, wave, t, bool(args.noise))
    else:
        band = fitted.posterior.band(wave, t, noise=args.noise)
    y, lo, hi = (np.asarray(a).reshape(n, -1) for a in (band.y, band.lower, band.upper))
    for name, arr in (("response", y), ("band", lo), ("band", hi)):
        if not np.all(np.isfinite(arr)):
            k = int(np.flatnonzero(~np.all(np.isfinite(arr), axis=1))[0])
            raise InputError(
                f"the simulated {name} is not finite from t = {t[k]:g} s (a waveform or "
                "parameter value the model cannot take: lower the power, or check the "
                "values and covariance in params.json); nothing was written",
                file=str(args.params),
                field="--waveform",
            )
    file_units = (fitted.document or {}).get("file_units") or {}
    header, cols, described, peaks = simulation_columns(
        outputs, inputs, file_units, t, (y, lo, hi), wave
    )
    first = peaks[outputs[0].name]
    headline = (fitted.document or {}).get("headline") or {}  # the fit's verdict, if recorded
    meta = {
        "params": str(args.params),
        "fit_verdict": headline.get("verdict"),
        "device": fitted.device_name,
        "waveform": {"spec": specs if len(specs) > 1 else specs[0], "description": text},
        "noise_model": fitted.noise_model,
        "band": {
            "kind": band.kind,
            "level": band.level,
            "includes_noise": band.includes_noise,
            "includes_process_noise": process,
            "n_paths": _n_paths() if process else None,
            "sigma_m": [float(s) for s in fitted.sigma] if args.noise else None,
        },
        "columns": described,
        "peak": first,
        "peaks": peaks,
        "initial_state": dict(_initial_values(args.initial_state)),
        "file_units": file_units,
    }
    tick.phase_is(f"writing {args.out}")
    write_simulation(
        args.out,
        args.force,
        header,
        cols,
        meta,
        band,
        wave,
        fitted.device_name,
        text,
        outputs,
        inputs,
        args.figure_format,
    )
    width = float(np.nanmax(cols[3] - cols[2]))
    print(
        f"simulated {text}: {n} samples, peak {first['y']:.4g} {first['unit']}, widest band "
        f"{width:.3g} {first['unit']}"
    )
    print(f"band: {band.kind}")
    if headline.get("verdict") not in (None, "valid"):
        print(
            f"note: the fit in {args.params} is '{headline['verdict']}' (its headline): the "
            "band covers the uncertainty of its values within its structure, not what the "
            "structure misses"
        )
    if args.duration_s is None and np.size(getattr(wave, "times_s", (0, 0))) == 1:
        print(
            f"note: every input is constant, so the waveform has no length of its own: "
            f"simulated {t[-1]:g} s; give --duration-s for longer"
        )
    print(
        f"wrote {Path(args.out)}/ (simulation.csv, simulation.{args.figure_format}, "
        "simulation.json)"
    )
    return 0


def _initial_values(specs) -> list:
    """[(path, SI value)] from --initial-state PATH=VALUE."""
    from greybox._model.errors import InputError

    out = []
    for spec in specs:
        path, sep, value = spec.partition("=")
        try:
            v = float(value)
        except ValueError:
            v = math.nan
        if not sep or not path.strip() or not math.isfinite(v):
            raise InputError(
                f"{spec!r}: give PATH=VALUE with a finite number in SI units, e.g. "
                "initial_T1_K=300",
                field="--initial-state",
            )
        out.append((path.strip(), v))
    return out


def with_initial_state(fitted, specs):
    """`fitted` with its model's initial-state parameters set from --initial-state."""
    import dataclasses

    from greybox._model.errors import InputError
    from greybox._model.parameters import set_values

    values = _initial_values(specs)
    if not values:
        return fitted
    table = fitted.spec.parameter_table(fitted.options)
    allowed = [p.path for p in table if "initial" in p.path]
    fitted_paths = {p.path for p in fitted.free if not p.per_experiment}
    for path, _ in values:
        if path not in allowed:
            raise InputError(
                f"{path!r} is not an initial-state parameter of {fitted.device_name}; "
                + (f"use one of {', '.join(allowed)}" if allowed else "it has none"),
                field="--initial-state",
            )
        if path in fitted_paths:
            raise InputError(
                f"{path!r} was fitted (params.json holds its estimate and uncertainty); a new "
                "initial state needs a fit that did not estimate it",
                field="--initial-state",
            )
    model = set_values(fitted.model, [p for p, _ in values], [v for _, v in values])
    return dataclasses.replace(fitted, model=model)


def _n_paths() -> int:
    from greybox._estimate.prediction import N_PATHS

    return N_PATHS


def process_band(fitted, wave, t, measurement_noise: bool):
    """The 95 % band of sample paths of a process-noise fit (`Posterior.band`'s)."""
    return fitted.posterior.band(wave, t, noise=measurement_noise)
