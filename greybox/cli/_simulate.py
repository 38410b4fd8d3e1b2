"""`greybox simulate`: fitted params.json + a new laser waveform -> CSV and PNG with a 95 % band."""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

HELP = """\
Simulate a new laser waveform with a fitted model (the params.json written by
`greybox fit`; the data are not needed) and write the response with a 95 % band from the
parameter covariance (delta method).

--waveform SPEC is either
  pulse:power_mW=25,period_ms=300,duty=0.5,n=10[,delay_ms=200][,tail_ms=500]
      a square pulse train: power in mW (or power_W in W), period/delay/tail in ms
      (or period_s, delay_s, tail_s in s), duty = on-fraction in (0, 1], n = pulses;
  PATH.csv
      a logged trace with columns t_s [s] and laser_mW [mW] (or laser_W [W]), each level
      held until the next sample.

Output (in --out, written atomically):
  simulation.csv   t_s [s], y_um [um], y_lo95_um, y_hi95_um [um], laser_mW [mW]
                   (displacement from rest: per-run camera offsets belong to the recorded
                   runs and are not part of a new waveform)
  simulation.png   response with its band, laser waveform beneath
  simulation.json  what the band is (confidence band or prediction interval), the
                   waveform, the params file used
By default the band is a 95 % confidence band of the model response (parameter
uncertainty only); --noise adds the fitted measurement noise sigma, giving a 95 %
prediction interval for new camera readings.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "simulate",
        help="simulate a new laser waveform with fitted params.json (95 %% band)",
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
        metavar="SPEC",
        help="pulse:power_mW=..,period_ms=..,duty=..,n=.. or a CSV with t_s,laser_mW",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        default="results/simulation",
        help="output folder (default results/simulation)",
    )
    p.add_argument(
        "--dt-ms", type=float, default=1.0, metavar="MS", help="output time step in ms (default 1)"
    )
    p.add_argument(
        "--noise",
        action="store_true",
        help="include measurement noise: prediction interval for camera readings",
    )
    p.set_defaults(func=run)
    return p


def _fmt(v: float) -> str:
    return f"{v:.6g}" if math.isfinite(v) else ("inf" if v > 0 else "-inf" if v < 0 else "nan")


def run(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from greybox import _plots as plots
    from greybox._errors import InputError
    from greybox.io._atomic import atomic_output_dir
    from greybox.io._waveform_spec import parse_waveform_spec, waveform_from_csv
    from greybox.io._params_file import load_params
    from greybox._prediction import prediction_band
    from greybox._report import display_unit

    if not (math.isfinite(args.dt_ms) and args.dt_ms > 0):
        raise InputError(f"must be a positive number of ms, got {args.dt_ms}", field="--dt-ms")
    fitted = load_params(args.params)
    in_ch, out_ch = fitted.spec.inputs[0], fitted.spec.outputs[0]
    spec = args.waveform
    if spec.startswith("pulse:") or not spec.lower().endswith(".csv"):
        wave, text = parse_waveform_spec(spec, in_ch)
    elif not Path(spec).is_file():
        raise InputError(
            "no such file; give pulse:power_mW=..,period_ms=..,duty=..,n=.. or "
            f"the path of a CSV with t_s,{in_ch.column_names()[0]} columns",
            file=spec,
            field="--waveform",
        )
    else:
        wave, text = waveform_from_csv(spec, in_ch)
    dt = args.dt_ms * 1e-3
    n = int(math.floor((wave.end_s - 0.0) / dt + 1e-9)) + 1
    if n > 2_000_000:
        raise InputError(f"{n} output samples; raise --dt-ms", field="--dt-ms")
    t = np.arange(n) * dt
    sigma = fitted.sigma if args.noise else None
    band = prediction_band(
        fitted.model,
        fitted.free,
        fitted.raw,
        fitted.covariance_raw,
        wave,
        t,
        sigma=sigma,
        null_directions=fitted.null_directions,
        method=fitted.method,
    )
    fy, uy = display_unit(out_ch.si_unit)
    fu, uu = display_unit(in_ch.si_unit)
    y_name = f"{out_ch.name}"
    header = [
        "t_s",
        f"{y_name}_{uy}",
        f"{y_name}_lo95_{uy}",
        f"{y_name}_hi95_{uy}",
        f"{in_ch.name}_{uu}",
    ]
    level = np.asarray(wave(t)).reshape(n, -1)[:, 0] * fu
    meta = {
        "params": str(args.params),
        "device": fitted.device_name,
        "waveform": {"spec": spec, "description": text},
        "band": {
            "kind": band.kind,
            "level": band.level,
            "includes_noise": band.includes_noise,
            "sigma_m": [float(s) for s in fitted.sigma] if args.noise else None,
        },
        "columns": {
            header[0]: "time [s]",
            header[1]: f"{out_ch.description} from rest [{uy}]",
            header[2]: f"lower end of the band [{uy}]",
            header[3]: f"upper end of the band [{uy}]",
            header[4]: f"{in_ch.description} [{uu}]",
        },
        "peak": {"y": float(np.max(band.y[:, 0]) * fy), "unit": uy},
    }
    with atomic_output_dir(args.out) as tmp:
        from greybox.cli._fit import usual_permissions

        usual_permissions(tmp)
        rows = [",".join(header)]
        for k in range(n):
            rows.append(
                ",".join(
                    [
                        f"{t[k]:.6f}",
                        _fmt(band.y[k, 0] * fy),
                        _fmt(band.lower[k, 0] * fy),
                        _fmt(band.upper[k, 0] * fy),
                        f"{level[k]:.6g}",
                    ]
                )
            )
        (tmp / "simulation.csv").write_text("\n".join(rows) + "\n")
        (tmp / "simulation.json").write_text(json.dumps(meta, indent=2) + "\n")
        plots.band_figure(
            tmp / "simulation.png",
            band,
            wave,
            title=f"{fitted.device_name}: {text}",
            output_label=(out_ch.description, out_ch.si_unit),
            input_label=(in_ch.description, in_ch.si_unit),
        )
    width = float(np.nanmax(band.upper[:, 0] - band.lower[:, 0]) * fy)
    print(
        f"simulated {text}: {n} samples, peak {meta['peak']['y']:.4g} {uy}, widest band "
        f"{width:.3g} {uy}"
    )
    print(f"band: {band.kind}")
    print(f"wrote {Path(args.out)}/ (simulation.csv, simulation.png, simulation.json)")
    return 0
