"""`greybox compare`: fit every candidate structure of an experiment folder and rank them."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

HELP = """\
Fit each candidate model structure listed in EXPERIMENT_DIR/experiment.toml to the same
estimation runs, validate each on the validation runs, and write one table: parameters with
their intervals and verdicts, AIC, BIC, estimation and validation fit % per output
(free-run simulation), the residual verdict, convergence and bound verdicts, and a
likelihood-ratio test for every nested pair. The preferred structure is named by a rule
stated in the report: the lowest information criterion (--rule aic, default, or bic) on the
estimation data among the candidates whose fit is valid; validation fit % is shown beside it
and never used to choose.

Each candidate carries a whole structure; what it leaves out comes from the top-level
tables ([model], [experiment] settings, [fit], [fit] free, [noise]):

  [[candidates]]
  name = "one node"
  model = { thermal_nodes = 1 }               # structural options over [model]
  settings = { "thermal.lag_s" = 0.002 }      # known values over [experiment] settings
  fit = { n_starts = 4 }                      # [fit] settings over [fit]
  free = ["absorptance", "thermal.tau_s"]     # replaces [fit] free (bounds, priors: tables)

  [[candidates]]
  name = "two nodes"
  model = { thermal_nodes = 2 }
  nests = ["one node"]                        # contains "one node": likelihood-ratio test
  noise = { process = "all" }                 # its own [noise]: a process-noise fit

Every candidate is loaded and checked before the first fit: problems in any of them are
listed together (exit 2, nothing fitted). Candidates must share one noise model (their
log-likelihoods must score the same data model). `greybox fit --candidate NAME` fits one
candidate exactly as compare does.

Output (--out, written atomically like `greybox fit`): compare.md, compare.json.
The preferred candidate is the one with the lowest criterion among those whose fit is valid
and physically plausible; compare.md opens with why no candidate is, or with what it means
when the residual test rejects every one, and each candidate in compare.json carries its
headline verdict (as params.json of `greybox fit`). Across runs: each per-run parameter
(fitted on every estimation run, re-fitted on each validation run) is tested for equality
between the runs (Wald test with its joint covariance) and flagged run-specific when its
estimates differ (p < 0.01): chosen on one run, it does not hold on the others (a compare.md
section; per_run_agreement in compare.json).
Exit status: 0 done; 1 no valid, physically plausible candidate (with --strict also a
preferred candidate whose structure the residual test rejects); 2 bad input; 3 a bug.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "compare",
        help="fit the candidate structures of an experiment folder and rank them (AIC/BIC)",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("experiment_dir", metavar="EXPERIMENT_DIR")
    p.add_argument("--out", metavar="DIR", help="result folder (default results/<name>-compare)")
    p.add_argument("--rule", choices=("aic", "bic"), default="aic", help="selection rule")
    p.add_argument("--force", action="store_true", help="replace a non-result --out folder")
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.add_argument(
        "--strict",
        action="store_true",
        help="exit 1 also when the residual test rejects the preferred candidate's structure "
        "(the result is written either way)",
    )
    p.set_defaults(func=run)
    return p


def _pct(values) -> str:
    return " / ".join("n/a" if v is None or v != v else f"{v:.1f}" for v in values)


def load_candidates(experiment_dir) -> list:
    """Every candidate of the folder loaded and checked (`ExperimentSet`s, in file order),
    before anything is fitted: the problems of all candidates are raised together."""
    from greybox._model.errors import InputError
    from greybox.io._experiment_set import (
        InputErrors,
        candidate_nests,
        check_problem_size,
        load_experiment_set,
    )

    nests = candidate_nests(experiment_dir)
    loaded, errors = [], []
    for i in range(len(nests)):
        try:
            fs = load_experiment_set(experiment_dir, candidate=i)
            check_problem_size(fs)
            loaded.append(fs)
        except InputErrors as err:
            errors.extend(err.errors)
        except InputError as err:
            errors.append(err)
    seen = []  # repeated problems (a shared run file) are listed once
    for e in errors:
        if str(e) not in map(str, seen):
            seen.append(e)
    if not seen:
        kinds = {fs.noise_model for fs in loaded}
        if len(kinds) > 1:
            by = ", ".join(f"{fs.candidate!r}: {fs.noise_model}" for fs in loaded)
            seen.append(
                InputError(
                    "candidates mix noise models (" + by + "); their log-likelihoods score "
                    "different data models and cannot be compared: give every candidate the "
                    'same noise_model (a noise table, or [fit] noise_model = "process")',
                    file=str(Path(experiment_dir) / "experiment.toml"),
                    field="candidates",
                )
            )
    if len(seen) == 1:
        raise seen[0]
    if seen:
        raise InputErrors(seen)
    return loaded


def compare_experiment_dir(experiment_dir, say, *, rule: str = "aic"):
    """(scores, preferred, likelihood-ratio tests, verdicts) for every candidate of the
    folder (see the module help). Every candidate is checked before the first fit; the
    preferred one is never an invalid or physically implausible fit (`preferred_plausible`)."""
    from greybox._estimate.compare import likelihood_ratios, nested_pairs, score
    from greybox._estimate.verdict import candidate_verdict, preferred_plausible
    from greybox.cli._common import fit_loaded
    from greybox.io._experiment_set import candidate_nests

    nests = candidate_nests(experiment_dir)
    loaded = load_candidates(experiment_dir)
    names = [fs.candidate for fs in loaded]

    def run_candidate(i, start=None):
        fs = loaded[i]
        warm = None if start is None else (lambda free: _warm_started(free, start))
        result, validation = fit_loaded(fs, say, start=warm)
        s = score(names[i], fs.options, result, validation, nests=nests[names[i]])
        v = candidate_verdict(names[i], result, fs.physical_ranges)
        say(
            f"candidate {names[i]!r}: AIC {s.aic:.6g}, BIC {s.bic:.6g}, {s.status}, "
            f"{v.headline.verdict}"
        )
        return s, result, v

    scores, results, verdicts = [], [], []
    for i, name in enumerate(names):
        say(f"candidate {i + 1}/{len(names)} {name!r}: {loaded[i].options}")
        s, result, v = run_candidate(i)
        scores.append(s)
        results.append(result)
        verdicts.append(v)
    # a structure that fits worse than one nested in it may have stopped at a local optimum:
    # re-start it once from the nested estimate (which it contains) and say what happened
    for big, small in nested_pairs(scores):
        if not scores[big].loglik < scores[small].loglik:
            continue  # already repaired through another nested candidate
        say(
            f"candidate {names[big]!r} fits worse than {names[small]!r}, which is nested in "
            f"it (log L {scores[big].loglik:.6g} < {scores[small].loglik:.6g}); re-starting "
            "it from that estimate"
        )
        s, result, v = run_candidate(big, start=results[small])
        if s.loglik > scores[big].loglik:
            note = (
                f"Re-started from the estimate of the nested candidate {names[small]!r}: the "
                f"first fit stopped at a local optimum (log L {scores[big].loglik:.6g})."
            )
            scores[big] = dataclasses.replace(s, note=note)
            results[big] = result
            verdicts[big] = v
        else:
            note = (
                f"Fits worse than the nested candidate {names[small]!r} by the criterion's "
                "likelihood, and a re-start from its estimate did not improve that: the fit "
                "minimises least squares weighted by each output's noise scale from the "
                "residuals, the criterion uses each output's ML noise variance, and the two "
                "can rank the outputs' errors differently."
            )
            scores[big] = dataclasses.replace(scores[big], note=note)
    best = preferred_plausible(scores, verdicts, rule)
    return scores, best, likelihood_ratios(scores), verdicts


def _warm_started(free, result):
    """`free` with each shared parameter that `result` also fitted starting at its estimate
    (strictly inside the bounds; a value on a bound keeps the usual start)."""
    fitted = {p.path: p.value for p in result.parameters if p.experiment is None}
    out = []
    for p in free:
        v = fitted.get(p.path)
        inside = v is not None and (p.lower is None or v > p.lower)
        inside = inside and (p.upper is None or v < p.upper)
        out.append(
            dataclasses.replace(p, initial=float(v)) if inside and not p.per_experiment else p
        )
    return out


def report_lines(experiment_dir, scores, best, rule: str, tests=(), verdicts=()) -> list[str]:
    from greybox._estimate.verdict import all_rejected_lines, no_valid_candidate_lines

    lines = [f"# Structure comparison: {Path(experiment_dir).resolve().name}", ""]
    warning = no_valid_candidate_lines(verdicts) or all_rejected_lines(verdicts, rule)
    if warning:
        lines += [*warning, ""]
    if best is None:
        if not warning:
            lines += [
                "**No candidate gave a valid fit**; none is preferred (see each status).",
                "",
            ]
    else:
        head = {v.name: v.headline for v in verdicts}.get(best.name)
        lines += [
            f"**Preferred: {best.name}** (lowest {rule.upper()} on the estimation runs among "
            "the valid, physically plausible fits; validation fit % is shown and was not "
            "used to choose)." + ("" if head is None else f" Its verdict: {head.text}."),
            "",
        ]
    if scores and scores[0].noise_model == "process noise":
        lines += [
            "Information criteria from each candidate's maximum log-likelihood (process noise "
            "and measurement noise, continuous-discrete Kalman filter, prediction-error form) "
            "over the same readings; k counts every fitted value, noise parameters included. "
            "Fit % is simulation, per output.",
            "",
        ]
    else:
        lines += [
            "Information criteria from the Gaussian log-likelihood of the free-run simulation "
            "residuals (noise variance per output at its maximum-likelihood value); k counts "
            "every fitted value and one noise variance per output. Fit % is simulation, per "
            "output.",
            "",
        ]
    lines += [
        "| candidate | options (those that differ) | k | log L | AIC | BIC | "
        "estimation fit % (mean per output) | validation fit % | residuals | status |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    differ = [k for k in scores[0].options if len({repr(s.options[k]) for s in scores}) > 1]
    noise_differs = len({s.noise for s in scores}) > 1  # candidates with their own [noise]
    for s in scores:
        est = _mean_fit(s.fit_estimation)
        val = _mean_fit(s.fit_validation)
        opts = [f"{k}={s.options[k]}" for k in differ]
        opts += [f"noise: {s.noise or 'none'}"] if noise_differs else []
        opts = ", ".join(opts) or "as [model]"
        lines.append(
            f"| {s.name} | {opts} | {s.n_params} | {s.loglik:.8g} | {s.aic:.8g} | {s.bic:.8g} | "
            f"{_pct(est)} | {_pct(val) if s.fit_validation else '-'} | {s.residual_verdict} | "
            f"{s.status} |"
        )
    if tests:
        lines += [
            "",
            "## Likelihood-ratio tests (nested pairs)",
            "",
            "D = 2 (log L of the larger - log L of the nested), against chi-square with the "
            "difference in k as degrees of freedom (Wilks); p < 0.05: the larger structure "
            "explains the data better than the nested one can. (A nested variance at its "
            "zero boundary makes the chi-square p-value conservative.)",
            "",
            "| larger | nested | nested by | D | dof | p |",
            "|---|---|---|---|---|---|",
        ]
        for t in tests:
            p = "n/a" if t.p_value != t.p_value else f"{t.p_value:.3g}"
            by = "declared (nests)" if t.declared else "options and free set"
            lines.append(
                f"| {t.big} | {t.small} | {by} | {t.statistic:.6g} | {t.dof} | {p} |"
            )
    lines += _run_agreement_lines(scores)
    nested = [s for s in scores if s.note]
    if nested:
        lines += ["", "Nested structures (each must fit at least as well as one nested in it):", ""]
        lines += [f"- {s.name}: {s.note}" for s in nested]
    lines += ["", "## Estimates per candidate", ""]
    heads = {v.name: [*v.headline.lines, ""] for v in verdicts}
    for s in scores:
        lines += [
            f"### {s.name}",
            "",
            f"Status **{s.status}**{'' if s.valid else ' (not valid)'}: {s.message}",
            "",
            *heads.get(s.name, []),
            "| parameter | run | value | unit | std. error | 95 % interval | verdict |",
            "|---|---|---|---|---|---|---|",
        ]
        for e in s.estimates:
            ci = e["ci95"]
            interval = "n/a" if None in ci else f"[{ci[0]:.5g}, {ci[1]:.5g}]"
            lines.append(
                f"| `{e['path']}` | {e['run'] or '-'} | {_g(e['value'])} | {e['unit']} | "
                f"{_g(e['se'])} | {interval} | {e['verdict']} |"
            )
        lines.append("")
    return lines + [""]


def _run_agreement_lines(scores) -> list[str]:
    """compare.md's section on per-run parameters: does each hold across the runs?"""
    from greybox._estimate.compare import RUN_ALPHA, run_agreement_text

    rows = [(s.name, a) for s in scores for a in s.run_agreement]
    if not rows:
        return []
    lines = [
        "",
        "## Per-run parameters across runs",
        "",
        "Each per-run parameter's estimates on the estimation runs (and its values re-fitted "
        "on the validation runs), tested for equality (Wald test with their joint covariance, "
        "chi-square with runs - 1 dof); p < "
        f"{RUN_ALPHA:g}: **run-specific**, a property of each run, not of the device.",
        "",
        "| candidate | parameter | runs: value | weighted mean | unit | across runs |",
        "|---|---|---|---|---|---|",
    ]
    for name, a in rows:
        val = set(a["validation_runs"])
        per = ", ".join(
            f"{r}{' (validation)' if r in val else ''}: {v:.5g}"
            for r, v in zip(a["runs"], a["values"])
        )
        lines.append(
            f"| {name} | `{a['path']}` | {per} | {a['mean']:.5g} | {a['unit']} | "
            f"{run_agreement_text(a)} |"
        )
    return lines


def _g(x) -> str:
    return "n/a" if x is None else f"{x:.5g}"


def _num(x):
    import math

    return float(x) if math.isfinite(x) else None


def _per_run(per_run: dict) -> dict:
    """{run: [fit % per output]} with NaN as None (JSON)."""
    return {k: _mean_fit({k: v}) for k, v in per_run.items()}


def _mean_fit(per_run: dict):
    import numpy as np

    if not per_run:
        return []
    arr = np.array([np.atleast_1d(v) for v in per_run.values()], dtype=float)
    return [float(np.nanmean(col)) if np.isfinite(col).any() else None for col in arr.T]


def candidate_record(s, verdict=None) -> dict:
    """One candidate's row of compare.json (what `greybox fit --candidate` reproduces), with
    its headline verdict (`greybox._estimate.verdict.candidate_verdict`)."""
    return {
        "name": s.name,
        "options": s.options,
        "free": list(s.free),
        "noise_model": s.noise_model,
        "noise": s.noise or None,
        "nests": list(s.nests),
        "k": s.n_params,
        "n": s.n_data,
        "loglik": _num(s.loglik),
        "aic": _num(s.aic),
        "bic": _num(s.bic),
        "estimates": list(s.estimates),
        "per_run_agreement": [
            {k: _num(v) if isinstance(v, float) else v for k, v in a.items()}
            for a in s.run_agreement
        ],
        "fit_percent_estimation": _per_run(s.fit_estimation),
        "fit_percent_validation": _per_run(s.fit_validation),
        "residuals": s.residual_verdict,
        "status": s.status,
        "valid": s.valid,
        "message": s.message,
        "note": s.note,
        **({} if verdict is None else {"headline": verdict.headline.as_json()}),
    }


def run(args) -> int:
    from greybox.io._jax_setup import configure

    configure()  # float64, compiled programs kept on disk
    from greybox.cli._common import Progress, print_input_errors
    from greybox.cli._ticker import Ticker
    from greybox.io._atomic import atomic_output_dir, check_output_dir
    from greybox.io._experiment_set import InputErrors
    from greybox.io._results import usual_permissions

    out = Path(args.out or Path("results") / f"{Path(args.experiment_dir).resolve().name}-compare")
    out = check_output_dir(out, force=args.force, inputs=[args.experiment_dir])
    try:
        with Ticker(Progress(args.quiet)) as say:  # a line at least every 5 s, in every phase
            scores, best, tests, verdicts = compare_experiment_dir(
                args.experiment_dir, say, rule=args.rule
            )
    except InputErrors as err:  # every candidate's problems, one per line; nothing fitted
        print_input_errors("compare", args.experiment_dir, err)
        return 2
    lines = report_lines(args.experiment_dir, scores, best, args.rule, tests, verdicts)
    doc = {
        "rule": args.rule,
        "preferred": None if best is None else best.name,
        "horizon": "simulation",
        "noise_model": scores[0].noise_model,
        "candidates": [candidate_record(s, v) for s, v in zip(scores, verdicts)],
        "likelihood_ratio_tests": [
            {
                "larger": t.big,
                "nested": t.small,
                "declared": t.declared,
                "statistic": _num(t.statistic),
                "dof": t.dof,
                "p_value": _num(t.p_value),
            }
            for t in tests
        ],
    }
    with atomic_output_dir(out, kind="compare", force=args.force) as tmp:
        usual_permissions(tmp)
        (tmp / "compare.md").write_text("\n".join(lines))
        (tmp / "compare.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    print("\n".join(lines[:4]))
    print(f"wrote {out}/ (compare.md, compare.json) in {say.elapsed:.1f} s")
    if best is None:
        return 1
    from greybox._estimate.verdict import VALID

    head = {v.name: v.headline for v in verdicts}[best.name]
    return 1 if args.strict and head.verdict != VALID else 0
