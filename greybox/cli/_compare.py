"""`greybox compare`: fit every candidate structure of an experiment folder and rank them."""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

HELP = """\
Fit each candidate model structure listed in EXPERIMENT_DIR/experiment.toml to the same
estimation runs, validate each on the validation runs, and write one table: parameters,
AIC, BIC, estimation and validation fit % per output (free-run simulation), the residual
verdict, convergence and bound verdicts. The preferred structure is named by a rule stated
in the report: the lowest information criterion (--rule aic, default, or bic) on the
estimation data among the candidates whose fit is valid; validation fit % is shown beside it
and never used to choose.

Candidates in experiment.toml (each a [model] option set and, optionally, a free list; the
top-level [model] and [fit] free are the defaults a candidate starts from):

  [[candidates]]
  name = "one node"
  model = { thermal_nodes = 1 }

  [[candidates]]
  name = "two nodes + lag"
  model = { thermal_nodes = 2, elongation_lag = true }
  free = ["absorptance", "thermal.resistance_K_per_W[0]", "thermal.lag_s"]

Output (--out, written atomically like `greybox fit`): compare.md, compare.json.
Exit status: 0 done; 1 no candidate gave a valid fit; 2 bad input; 3 a bug.
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
    p.set_defaults(func=run)
    return p


def _pct(values) -> str:
    return " / ".join("n/a" if v is None or v != v else f"{v:.1f}" for v in values)


def compare_experiment_dir(experiment_dir, say, *, rule: str = "aic"):
    """(scores, preferred) for every candidate of the folder (see the module help)."""
    from greybox._compare import nested_pairs, preferred, score
    from greybox._fit import fit, validate
    from greybox.io._experiment_set import candidate_names, load_experiment_set

    names = candidate_names(experiment_dir)

    def run_candidate(i, start=None):
        fs = load_experiment_set(experiment_dir, candidate=i)
        free = fs.free if start is None else _warm_started(fs.free, start)
        result = fit(fs.model, fs.estimation, free, progress=say, **fs.fit_options)
        solver = {k: v for k, v in fs.fit_options.items() if k.startswith("solver_")}
        validation = validate(result, fs.validation, **solver) if fs.validation else None
        s = score(names[i], fs.options, result, validation)
        say(f"candidate {names[i]!r}: AIC {s.aic:.6g}, BIC {s.bic:.6g}, {s.status}")
        return s, result

    scores, results = [], []
    for i, name in enumerate(names):
        fs = load_experiment_set(experiment_dir, candidate=i)
        say(f"candidate {i + 1}/{len(names)} {name!r}: {fs.options}")
        s, result = run_candidate(i)
        scores.append(s)
        results.append(result)
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
        s, result = run_candidate(big, start=results[small])
        if s.loglik > scores[big].loglik:
            note = (
                f"Re-started from the estimate of the nested candidate {names[small]!r}: the "
                f"first fit stopped at a local optimum (log L {scores[big].loglik:.6g})."
            )
            scores[big] = dataclasses.replace(s, note=note)
            results[big] = result
        else:
            note = (
                f"Fits worse than the nested candidate {names[small]!r} by the criterion's "
                "likelihood, and a re-start from its estimate did not improve that: the fit "
                "minimises least squares weighted by each output's noise scale from the "
                "residuals, the criterion uses each output's ML noise variance, and the two "
                "can rank the outputs' errors differently."
            )
            scores[big] = dataclasses.replace(scores[big], note=note)
    return scores, preferred(scores, rule)


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


def report_lines(experiment_dir, scores, best, rule: str) -> list[str]:
    lines = [f"# Structure comparison: {Path(experiment_dir).resolve().name}", ""]
    if best is None:
        lines += ["**No candidate gave a valid fit**; none is preferred (see each status).", ""]
    else:
        lines += [
            f"**Preferred: {best.name}** (lowest {rule.upper()} on the estimation runs among "
            "the valid fits; validation fit % is shown and was not used to choose).",
            "",
        ]
    lines += [
        "Information criteria from the Gaussian log-likelihood of the free-run simulation "
        "residuals (noise variance per output at its maximum-likelihood value); k counts every "
        "fitted value and one noise variance per output. Fit % is simulation, per output.",
        "",
        "| candidate | options (those that differ) | k | AIC | BIC | "
        "estimation fit % (mean per output) | validation fit % | residuals | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    differ = [k for k in scores[0].options if len({repr(s.options[k]) for s in scores}) > 1]
    for s in scores:
        est = _mean_fit(s.fit_estimation)
        val = _mean_fit(s.fit_validation)
        opts = ", ".join(f"{k}={s.options[k]}" for k in differ) or "as [model]"
        lines.append(
            f"| {s.name} | {opts} | {s.n_params} | {s.aic:.6g} | {s.bic:.6g} | {_pct(est)} | "
            f"{_pct(val) if s.fit_validation else '-'} | {s.residual_verdict} | {s.status} |"
        )
    nested = [s for s in scores if s.note]
    if nested:
        lines += ["", "Nested structures (each must fit at least as well as one nested in it):", ""]
        lines += [f"- {s.name}: {s.note}" for s in nested]
    lines += ["", "Free parameters per candidate:", ""]
    lines += [f"- {s.name}: {', '.join(s.free)}" for s in scores]
    return lines + [""]


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


def run(args) -> int:
    import jax

    jax.config.update("jax_enable_x64", True)
    from greybox.cli._common import Progress
    from greybox.io._results import usual_permissions
    from greybox.io._atomic import atomic_output_dir, check_output_dir

    say = Progress(args.quiet)
    out = Path(args.out or Path("results") / f"{Path(args.experiment_dir).resolve().name}-compare")
    out = check_output_dir(out, force=args.force, inputs=[args.experiment_dir])
    scores, best = compare_experiment_dir(args.experiment_dir, say, rule=args.rule)
    lines = report_lines(args.experiment_dir, scores, best, args.rule)
    doc = {
        "rule": args.rule,
        "preferred": None if best is None else best.name,
        "horizon": "simulation",
        "candidates": [
            {
                "name": s.name,
                "options": s.options,
                "free": list(s.free),
                "k": s.n_params,
                "n": s.n_data,
                "loglik": _num(s.loglik),
                "aic": _num(s.aic),
                "bic": _num(s.bic),
                "fit_percent_estimation": _per_run(s.fit_estimation),
                "fit_percent_validation": _per_run(s.fit_validation),
                "residuals": s.residual_verdict,
                "status": s.status,
                "valid": s.valid,
                "message": s.message,
                "note": s.note,
            }
            for s in scores
        ],
    }
    with atomic_output_dir(out, kind="compare", force=args.force) as tmp:
        usual_permissions(tmp)
        (tmp / "compare.md").write_text("\n".join(lines))
        (tmp / "compare.json").write_text(json.dumps(doc, indent=2, allow_nan=False) + "\n")
    print("\n".join(lines[:4]))
    print(f"wrote {out}/ (compare.md, compare.json) in {say.elapsed:.1f} s")
    return 0 if best is not None else 1
