"""`greybox fit`: experiment folder -> params.json, report.md and figures (written atomically)."""

from __future__ import annotations

import argparse
import sys
import textwrap
from pathlib import Path

from greybox._estimate.verdict import exit_status_help
from greybox.cli._common import (  # re-exported: the API of `greybox fit` used by tests
    FitOutcome as FitOutcome,
)
from greybox.cli._common import Progress, default_out, fit_lines, parameter_lines
from greybox.cli._common import fit_experiment_dir as fit_experiment_dir
from greybox.cli._figures import add_figure_format

HELP = """\
Fit the physical parameters of a device model to an experiment folder and write the
result: params.json (every fitted value in SI with its unit, standard error, 95 %
interval and identifiability verdict), report.md (tables, simulation fit % per run for the
estimation and validation runs, the identifiability verdict), figures/*.png (or .svg/.pdf
with --figure-format, none with --no-figures; measured vs model per run with the laser
waveform beneath, residuals, parameter correlation),
predictions/<run>.csv (per run: time, then per output measured, simulated, 95 % band and
residual, in the unit of the run's file), metrics.csv (per run and output: simulation fit %,
RMSE, MAE, SAE in the file's unit) and validation_runs.json (per validation run: its
settings and the per-run values re-fitted on it).

EXPERIMENT_DIR holds experiment.toml and one CSV per run (format: experiments/README.md):
  [camera]   fps [frames/s], exposure_ms [ms], um_per_px [um per pixel]
  run CSVs   t_s [s], y_um [um] or y_px [pixels, converted with um_per_px], optional
             laser_mW [mW] when the laser is logged rather than described; any unit
             pint knows (T1_degC, t_ms), or the logger's own names mapped in [columns]
             (header-less files: [data] header = false, columns = [...])
  waveform   per run: { type = "pulse_train", power_mW [mW], period_ms [ms], duty [0-1],
             n_pulses, delay_ms [ms], tail_ms [ms] } or { type = "logged" }

Units in the output: params.json holds SI values (m, s, W, K/W) with each unit named;
report.md and the figures show um, ms and mW. Every fit % is free-run simulation (the
model driven by the laser alone), never one-step prediction. With [fit] noise_model =
"process" and a [noise] table (experiments/README.md) the fit is maximum likelihood through
a Kalman filter instead (the same command, result folder and params.json schema), and
predictions/, metrics.csv and the report give fit % in simulation, one-step and k-step
prediction, each labelled. --candidate NAME fits one [[candidates]] entry of the folder
(its model options, settings, [fit] settings, free list and noise table) as `greybox
compare` fits it.

The result folder is written atomically: it appears complete or not at all (an error, a
bad input, Ctrl-C or SIGTERM leaves no partial result, and an earlier result stays as it
was). --out must be absent, empty or an earlier greybox result (it holds a
.greybox-result marker); any other folder is refused before any work unless --force.
"""
HELP += textwrap.fill(exit_status_help(), width=92) + "\n"


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
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out even if it is a non-empty folder greybox did not write",
    )
    p.add_argument(
        "--candidate",
        metavar="NAME",
        help="fit the [[candidates]] entry called NAME (as `greybox compare` fits it)",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument(
        "--strict",
        action="store_true",
        help="exit 1 also when the residual test rejects the structure or a fitted value is "
        "physically implausible (the result is written either way)",
    )
    add_figure_format(p, optional=True)
    p.set_defaults(func=run)
    return p


def run(args) -> int:
    from greybox.cli._common import print_input_errors
    from greybox.cli._ticker import Ticker

    out = Path(args.out) if args.out else default_out(args.experiment_dir)
    # a line at least every 5 s, in every phase: the imports (JAX alone takes 2 s, several
    # on a loaded machine) included
    with Ticker(Progress(args.quiet)) as say:
        say.phase_is("starting (importing JAX and the fitting code)")
        from greybox.io._jax_setup import configure

        configure()  # float64, compiled programs kept on disk
        from greybox.io._experiment_set import InputErrors

        try:
            outcome = fit_experiment_dir(
                args.experiment_dir,
                out,
                say,
                force=args.force,
                candidate=args.candidate,
                figure_format=args.figure_format,
            )
        except InputErrors as err:  # every loader problem, one per line
            print_input_errors("fit", args.experiment_dir, err)
            return 2
    print("\n".join(parameter_lines(outcome.result) + fit_lines(outcome)))
    figures = "" if args.figure_format is None else "figures/, "
    print(
        f"wrote {out}/ (params.json, report.md, {figures}predictions/, metrics.csv, "
        f"validation_runs.json) in {say.elapsed:.1f} s"
    )
    from greybox._estimate.verdict import (
        fit_headline,  # one verdict: status, bounds, physics, residuals
    )

    head = fit_headline(outcome.result, outcome.fitset.physical_ranges, strict=args.strict)
    print("\n".join([head.text, *[f"  {d}" for d in head.details], head.intervals]))
    if not outcome.result.valid:
        print(
            f"greybox fit: warning: {outcome.result.status}: the estimate is not valid "
            f"({outcome.result.message}); the result is written but its numbers are not "
            "trustworthy",
            file=sys.stderr,
        )
        return 1
    return head.exit_status
