"""`greybox fit`: experiment folder -> params.json, report.md and figures (written atomically)."""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import time
from pathlib import Path

HELP = """\
Fit the physical parameters of a device model to an experiment folder and write the
result: params.json (every fitted value in SI with its unit, standard error, 95 %
interval and identifiability verdict), report.md (tables, simulation fit % per run for the
estimation and validation runs, the identifiability verdict) and figures/*.png (measured vs
model per run with the laser waveform beneath, residuals, parameter correlation).

EXPERIMENT_DIR holds experiment.toml and one CSV per run (format: experiments/README.md):
  [camera]   fps [frames/s], exposure_ms [ms], um_per_px [um per pixel]
  run CSVs   t_s [s], y_um [um] or y_px [pixels, converted with um_per_px], optional
             laser_mW [mW] when the laser is logged rather than described
  waveform   per run: { type = "pulse_train", power_mW [mW], period_ms [ms], duty [0-1],
             n_pulses, delay_ms [ms], tail_ms [ms] } or { type = "logged" }

Units in the output: params.json holds SI values (m, s, W, K/W) with each unit named;
report.md and the figures show um, ms and mW. Every fit % is free-run simulation (the
model driven by the laser alone), never one-step prediction.

The result folder is written atomically: it appears complete or not at all (an error, a
bad input or Ctrl-C leaves no partial result, and an earlier result stays as it was).
Exit status: 0 done; 1 written but the fit did not converge (see report.md); 2 bad input
(one line naming the file, line and field); 130 interrupted.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "fit",
        help="fit physical parameters to an experiment folder (TOML + CSV runs)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "experiment_dir",
        metavar="EXPERIMENT_DIR",
        help="folder with experiment.toml and the run CSVs",
    )
    p.add_argument(
        "--out",
        metavar="DIR",
        help="result folder (default results/<experiment folder name>); replaced "
        "as a whole when the new result is complete",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)
    return p


class Progress:
    """Progress lines with elapsed seconds, on stderr (stdout stays for results)."""

    def __init__(self, quiet: bool = False):
        self.t0 = time.perf_counter()
        self.quiet = quiet

    def __call__(self, message: str) -> None:
        if not self.quiet:
            print(
                f"[{time.perf_counter() - self.t0:6.1f} s] {message}", file=sys.stderr, flush=True
            )

    @property
    def elapsed(self) -> float:
        return time.perf_counter() - self.t0


@dataclasses.dataclass(frozen=True)
class FitOutcome:
    fitset: object
    result: object
    validation: object
    out: Path
    document: dict


def default_out(experiment_dir) -> Path:
    return Path("results") / Path(experiment_dir).resolve().name


def fit_experiment_dir(experiment_dir, out, say) -> FitOutcome:
    """Load, fit, validate and write the result folder atomically (the work of `greybox fit`)."""
    from greybox._fit import fit, validate
    from greybox.io._atomic import atomic_output_dir
    from greybox.io._experiment_set import load_experiment_set
    from greybox.io._params_file import params_document, write_params

    say(f"loading {experiment_dir}")
    fs = load_experiment_set(experiment_dir)
    n_est = sum(e.n_frames for e in fs.estimation)
    n_val = sum(e.n_frames for e in fs.validation)
    say(
        f"{fs.device_name}: {len(fs.estimation)} estimation runs ({n_est} frames), "
        f"{len(fs.validation)} validation runs ({n_val} frames); fitting "
        f"{', '.join(p.path + (' (per run)' if p.per_experiment else '') for p in fs.free)}"
    )
    say("fitting (the first solve includes compiling the model, a few seconds)")
    result = fit(fs.model, fs.estimation, fs.free, progress=say, **fs.fit_options)
    validation = None
    if fs.validation:
        per_run = sorted({p.path for p in fs.free if p.per_experiment})
        say(
            f"validating on {len(fs.validation)} runs (physics fixed"
            + (f"; per-run {', '.join(per_run)} re-fitted)" if per_run else ")")
        )
        validation = validate(result, fs.validation)
    document = params_document(fs, result, validation)
    say(f"writing {out}")
    with atomic_output_dir(out) as tmp:
        usual_permissions(tmp)
        figures = write_figures(tmp, fs, result, validation)
        write_params(tmp / "params.json", document)
        (tmp / "report.md").write_text(render_report(fs, result, validation, figures))
    return FitOutcome(fs, result, validation, Path(out), document)


def usual_permissions(folder: Path) -> None:
    """Give a result folder the permissions of a folder made by mkdir (the temporary folder
    behind an atomic write is private)."""
    mask = os.umask(0)
    os.umask(mask)
    folder.chmod(0o777 & ~mask)


def render_report(fs, result, validation, figures) -> str:
    from greybox._report import fit_report

    notes = {p.path: p.identifiability for p in fs.spec.parameter_table(fs.options)}
    source = " ".join(filter(None, [fs.description, f"Data: `{fs.directory}`."]))
    return fit_report(
        result,
        validation,
        title=fs.name,
        device_name=fs.device_name,
        runs=fs.runs,
        parameter_notes=notes,
        figures=figures,
        source=source,
        output_unit=fs.spec.outputs[0].si_unit,
    )


def write_figures(folder: Path, fs, result, validation) -> list[str]:
    """Per-run fit figures, residuals and correlation under `folder`/figures; relative paths."""
    from greybox import _plots as plots

    outputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.outputs)
    inputs = tuple((c.description or c.name, c.si_unit) for c in fs.spec.inputs)
    (folder / "figures").mkdir()
    runs = [
        (e, "estimation", result.predict(i), result.fit_percent[e.name])
        for i, e in enumerate(result.experiments)
    ]
    if validation is not None:
        runs += [
            (e, "validation", z, validation.fit_percent[e.name])
            for e, z in zip(validation.experiments, validation.predictions)
        ]  # figure titles: fit % on every valid frame (the headline number)
    names = []
    for e, role, z, pct in runs:
        name = f"figures/fit_{e.name}.png"
        plots.run_figure(
            folder / name,
            name=e.name,
            role=role,
            t_s=e.t_s,
            y=e.y,
            y_model=z,
            inputs=e.inputs,
            sigma=result.sigma,
            fit_percent=pct,
            outputs=outputs,
            input_labels=inputs,
        )
        names.append(name)
    # one residuals figure per output channel (units and noise differ between channels)
    for j, (channel, out) in enumerate(zip(fs.spec.outputs, outputs)):
        name = (
            "figures/residuals.png"
            if len(outputs) == 1
            else f"figures/residuals_{channel.name}.png"
        )
        plots.residuals_figure(
            folder / name,
            [(e.name, role, e.t_s, e.y[:, j], z[:, j]) for e, role, z, _ in runs],
            sigma=float(result.sigma[j]),
            output=out,
        )
        names.append(name)
    plots.correlation_figure(
        folder / "figures/correlation.png", [p.name for p in result.parameters], result.correlation
    )
    return names + ["figures/correlation.png"]


def parameter_lines(result) -> list[str]:
    """Terminal table of the shared parameters: value, 95 % interval, verdict."""
    from greybox._report import estimate_texts

    lines = ["parameter                  value        95 % interval               verdict"]
    for p in result.parameters:
        if p.experiment is not None:
            continue
        value, ci, unit = estimate_texts(p)
        lines.append(
            f"{p.name:<26} {value:>8} {unit if unit != '1' else '':<3} {ci:<27} {p.verdict}"
        )
    return lines


def fit_lines(outcome: FitOutcome) -> list[str]:
    """Terminal lines: simulation fit % per run, sigma, outliers, convergence."""
    from greybox._report import display_unit, fmt

    r, v = outcome.result, outcome.validation
    f, unit = display_unit(outcome.fitset.spec.outputs[0].si_unit)

    def scores(res) -> str:
        out = []
        for k, x in res.fit_percent.items():
            n = res.n_outliers[k]
            extra = f" ({fmt(res.fit_percent_robust[k], 3)} without {n} flagged)" if n else ""
            out.append(f"{k} {fmt(x, 3)}{extra}")
        return ", ".join(out)

    lines = ["simulation fit % (estimation): " + scores(r)]
    if v is not None:
        lines.append("simulation fit % (validation): " + scores(v))
    lines.append(
        f"noise sigma {', '.join(fmt(float(s) * f, 3) for s in r.sigma)} {unit} "
        "(estimated), "
        f"{sum(r.n_outliers.values())} outliers flagged, "
        f"{'converged' if r.converged else 'NOT CONVERGED: ' + r.message}"
    )
    return lines


def run(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    say = Progress(args.quiet)
    out = Path(args.out) if args.out else default_out(args.experiment_dir)
    outcome = fit_experiment_dir(args.experiment_dir, out, say)
    print("\n".join(parameter_lines(outcome.result) + fit_lines(outcome)))
    print(f"wrote {out}/ (params.json, report.md, figures/) in {say.elapsed:.1f} s")
    if not outcome.result.converged:
        print(
            f"greybox fit: warning: the fit did not converge ({outcome.result.message}); "
            "the result is written but its numbers are not trustworthy",
            file=sys.stderr,
        )
        return 1
    return 0
