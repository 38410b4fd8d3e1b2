"""What several commands share: progress lines, the fit of a loaded experiment folder (any
noise model), the terminal summary of a fit, and how loader problems are printed.

Commands import this module; it imports no command module (no cli -> cli circle).
"""

from __future__ import annotations

import contextlib
import dataclasses
import sys
import time
from pathlib import Path


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


def print_input_errors(command: str, where, err) -> None:
    """Every loader problem of an `InputErrors`, one per line (up to 20, then a count)."""
    print(f"greybox {command}: error: {len(err.errors)} problems in {where}:", file=sys.stderr)
    for e in err.errors[:20]:
        print(f"greybox {command}: error: {' '.join(str(e).split())}", file=sys.stderr)
    if len(err.errors) > 20:
        print(f"greybox {command}: error: ... and {len(err.errors) - 20} more", file=sys.stderr)


def fit_loaded(fs, say, *, start=None, validate_runs: bool = True):
    """(FitResult, ValidationResult or None) of a loaded folder (`ExperimentSet`), whatever
    its noise model: one call of `greybox.fit`, then (`validate_runs`) the validation runs.
    `start`: a function free -> free (a warm start)."""
    from greybox._estimate.fit import fit
    from greybox._model.errors import InputError
    from greybox._model.freeparams import StartOutsideBounds

    free = list(fs.free)
    options = dict(fs.fit_options)
    if fs.noise is not None:
        from greybox.io._noise_table import noise_model

        model, noise, noise_free = noise_model(fs.noise, fs.model, fs.spec)
        free += noise_free
        options["noise"] = noise
    else:
        model = fs.model
    if start is not None:
        free = start(free)
    try:
        result = fit(model, fs.estimation, free, progress=say, **options)
    except StartOutsideBounds as err:  # a start the device or a hook gave, not the file
        where = "[fit] free" if fs.candidate is None else f"candidate {fs.candidate!r}: free"
        raise InputError(
            f"{err} (in the table form: {{ path = ..., initial = ... }}); nothing was fitted",
            file=str(fs.directory / "experiment.toml"),
            field=where,
        ) from err
    validation = validate_with_progress(fs, result, say) if validate_runs else None
    return result, validation


def validate_with_progress(fs, result, say):
    """`validate_loaded` on the folder's validation runs, said first; None where it has
    none."""
    if not fs.validation:
        return None
    per_run = sorted({p.path for p in fs.free if p.per_experiment})
    say(
        f"validating on {len(fs.validation)} runs (physics fixed"
        + (f"; per-run {', '.join(per_run)} re-fitted)" if per_run else ")")
    )
    return validate_loaded(fs, result)


def validate_loaded(fs, result):
    """`greybox.validate` of a folder's fit on its validation runs, with the fit's solver
    settings; a validation run whose simulation fails is the user's device and settings, not
    a greybox bug: an `InputError` at [fit] method."""
    from greybox._estimate.fit import validate
    from greybox._model.errors import InputError
    from greybox._simulate.simulate import SolverFailed

    solver = {k: v for k, v in fs.fit_options.items() if k.startswith("solver_")}
    try:
        return validate(result, fs.validation, **solver)
    except SolverFailed as err:
        raise InputError(
            f"{str(err).removeprefix('validate: ')} (the fit itself finished: "
            f"{result.status}); nothing was written",
            file=str(fs.directory / "experiment.toml"),
            field="[fit] method",
        ) from err


@dataclasses.dataclass(frozen=True)
class FitOutcome:
    fitset: object
    result: object
    validation: object
    out: Path
    document: dict
    metrics: dict | None = None  # io._results.metrics_table: per run, horizon and output


def default_out(experiment_dir) -> Path:
    return Path("results") / Path(experiment_dir).resolve().name


def fit_experiment_dir(
    experiment_dir,
    out,
    say,
    *,
    force: bool = False,
    candidate: str | None = None,
    figure_format: str | None = "png",
) -> FitOutcome:
    """Load, fit, validate and write the result folder atomically (the work of `greybox fit`,
    for every noise model). `candidate`: the name of a ``[[candidates]]`` entry to fit;
    `figure_format`: png, svg or pdf, None for no figures.

    `out` is checked first (absent, empty or an earlier result, writable; `force` replaces
    any other folder), then the problem size, before anything is compiled."""
    from greybox.io._atomic import check_output_dir
    from greybox.io._drawing import drawing_process
    from greybox.io._experiment_set import check_problem_size, load_experiment_set

    out = check_output_dir(out, force=force, inputs=[experiment_dir])
    say(f"loading {experiment_dir}")
    index = None if candidate is None else candidate_index(experiment_dir, candidate)
    fs = load_experiment_set(experiment_dir, candidate=index)
    check_problem_size(fs)
    # a drawing process's start overlaps the fit; it shares the drawing (none: no figures)
    with drawing_process() if figure_format else contextlib.nullcontext():
        return _fit_and_write(fs, out, say, force, candidate, figure_format)


def _fit_and_write(fs, out, say, force, candidate, figure_format) -> FitOutcome:
    from greybox.io._drawing import drawing_ahead
    from greybox.io._results import estimation_figure_jobs, write_fit_result

    n_est = sum(e.n_frames for e in fs.estimation)
    n_val = sum(e.n_frames for e in fs.validation)
    how = "least squares" if fs.noise is None else "maximum likelihood (process noise)"
    say(
        f"{fs.device_name}{'' if candidate is None else f' (candidate {candidate!r})'}: "
        f"{len(fs.estimation)} estimation runs ({n_est} frames), {len(fs.validation)} "
        f"validation runs ({n_val} frames); {how} over "
        f"{', '.join(p.path + (' (per run)' if p.per_experiment else '') for p in fs.free)}"
        + ("" if fs.noise is None else " and the noise parameters")
    )
    say("fitting (the first solve includes compiling the model, a few seconds)")
    result, _ = fit_loaded(fs, say, validate_runs=False)
    # the drawing process draws the estimation's figures while the validation runs
    early = []
    if figure_format and fs.validation:
        early = estimation_figure_jobs(fs, result, figure_format)
    with drawing_ahead(early) as ahead:
        validation = validate_with_progress(fs, result, say)
        say(f"writing {out}")
        written = write_fit_result(
            out, fs, result, validation, force=force, fmt=figure_format, ahead=ahead
        )
    return FitOutcome(fs, result, validation, Path(out), written.document, written.metrics)


def candidate_index(experiment_dir, name: str) -> int:
    """The index of the ``[[candidates]]`` entry called `name` (a located error if none)."""
    from greybox._model.errors import InputError
    from greybox.io._experiment_set import candidate_names

    names = candidate_names(experiment_dir)
    if name not in names:
        raise InputError(
            f"{name!r} is not a candidate of {experiment_dir}; the candidates are: "
            + ", ".join(repr(n) for n in names),
            file=str(Path(experiment_dir) / "experiment.toml"),
            field="--candidate",
        )
    return names.index(name)


def parameter_lines(result) -> list[str]:
    """Terminal table of the shared parameters: value, 95 % interval, verdict."""
    from greybox.report._markdown import estimate_texts

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
    """Terminal lines: fit % per run (and horizon), noise, outliers, convergence."""
    from greybox.report._markdown import display_unit, fmt

    r, v = outcome.result, outcome.validation
    if outcome.fitset.noise is not None:
        return _process_lines(outcome)
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
    source = "estimated" if r.sigma_source == "estimated" else r.sigma_source
    lines.append(
        f"noise sigma {', '.join(fmt(float(s) * f, 3) for s in r.sigma)} {unit} "
        f"({source}), "
        f"{sum(r.n_outliers.values())} outliers flagged, "
        f"{r.status if r.valid else r.status.upper() + ': ' + r.message}"
    )
    lines.append(f"residuals (estimation): {r.residuals.verdict}")
    return lines


def _process_lines(outcome: FitOutcome) -> list[str]:
    from greybox.io._results import metric_rows

    r = outcome.result
    lines = []
    for run, role, out, horizon, _, _, fp, *_ in metric_rows(outcome.metrics):
        lines.append(f"{run} ({role}) {out} {horizon} fit % {'n/a' if fp is None else f'{fp:.2f}'}")
    lines.append(
        f"log L {r.log_likelihood:.8g} ({r.n_observations} readings), AIC {r.aic:.8g}, "
        f"BIC {r.bic:.8g}; {r.status if r.valid else r.status.upper() + ': ' + r.message}"
    )
    lines.append(f"innovations (estimation runs): {r.residuals.verdict}")
    return lines
