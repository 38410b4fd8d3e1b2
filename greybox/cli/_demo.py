"""`greybox demo`: fit the embedded data set and compare the recovered values with the truth."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

HELP = """\
Fit the embedded default experiment set (experiments/chevron_laser: a laser-heated
chevron actuator filmed at 30 fps, six estimation runs at 5-30 mW with 200-1000 ms
periods and three validation runs; synthetic data whose true parameters are known) and
print the recovered values next to the true ones with their 95 % intervals and
identifiability verdicts.

It runs exactly what `greybox fit experiments/chevron_laser` runs and writes the same
result folder (params.json, report.md, figures/) to --out. Units: absorptance is
dimensionless, the thermal time constant is shown in ms, camera offsets in um, laser power
in mW; params.json holds SI values. Fit % are free-run simulation.
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser(
        "demo",
        help="fit the embedded chevron data set and show recovered vs true values",
        description=HELP,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument(
        "--out", metavar="DIR", default="results/demo", help="result folder (default results/demo)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="replace --out even if it is a non-empty folder greybox did not write",
    )
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=run)
    return p


def embedded_dir() -> Path:
    """The embedded data set: `experiments/` in a source checkout or editable install, else the
    copy packed into the wheel (`greybox/_embedded`, see pyproject.toml)."""
    checkout = Path(__file__).resolve().parents[2] / "experiments" / "chevron_laser"
    if checkout.is_dir():
        return checkout
    return Path(__file__).resolve().parents[1] / "_embedded" / "chevron_laser"


def truth_rows(outcome, truth: dict) -> tuple[list[str], bool]:
    """Recovered-vs-true lines, and whether every identifiable physical parameter's true
    value lies inside its reported 95 % interval."""
    from greybox.report._markdown import display_unit, estimate_texts, fmt

    lines = [
        f"{'parameter':<20} {'true':>9} {'recovered':>10}  {'95 % interval':<20} "
        f"{'inside':<6} verdict"
    ]
    ok = True
    r = outcome.result
    for path, t in truth["parameters"].items():
        try:
            p = r.estimate(path)
        except KeyError:
            continue
        f, _ = display_unit(p.unit, p.value)
        value, ci, unit = estimate_texts(p)
        inside = bool(p.ci95[0] <= t["value"] <= p.ci95[1])
        if p.verdict in ("identifiable", "weakly identified"):  # both carry an interval
            ok &= inside
        label = f"{path} [{unit}]" if unit != "1" else path
        lines.append(
            f"{label:<20} {fmt(t['value'] * f, 5):>9} {value:>10}  "
            f"{ci:<20} {'yes' if inside else 'NO':<6} {p.verdict}"
        )
    offsets = truth.get("camera_offset_m", {})
    errors = [
        ((p.value - offsets[p.experiment]), p.se)
        for p in r.parameters
        if p.path == "camera.offset_m" and p.experiment in offsets
    ]
    if errors:
        worst = max(errors, key=lambda e: abs(e[0] / e[1]))
        lines.append(
            f"camera offsets, one per run ({len(errors)}): largest error "
            f"{abs(worst[0]) * 1e9:.1f} nm = {abs(worst[0] / worst[1]):.1f} standard "
            "errors (nuisance values, ~200 um each)"
        )
    return lines, ok


def run(args) -> int:
    from greybox.cli._common import Progress
    from greybox.cli._ticker import Ticker
    from greybox.io._jax_setup import configure

    configure()  # float64, compiled programs kept on disk
    with Ticker(Progress(args.quiet)) as say:  # a line at least every 5 s, in every phase
        return _run(args, say)


def _run(args, say) -> int:
    from greybox._model.errors import InputError
    from greybox.cli._common import fit_experiment_dir, fit_lines

    data = embedded_dir()
    if not (data / "experiment.toml").is_file():
        raise InputError(
            "the embedded data set is not installed with this copy of greybox; "
            "run the demo from a source checkout (pip install -e .)",
            file=str(data),
            field="demo data",
        )
    out = Path(args.out)
    outcome = fit_experiment_dir(data, out, say, force=args.force)
    truth = json.loads((data / "truth.json").read_text())
    rows, ok = truth_rows(outcome, truth)
    print(f"greybox demo: {outcome.fitset.description}")
    print()
    print("\n".join(rows))
    print()
    print("\n".join(fit_lines(outcome)))
    print(
        ("recovered: each true physical parameter lies inside its reported 95 % interval")
        if ok
        else "WARNING: a true physical parameter lies outside its 95 % interval"
    )
    print(f"report: {out / 'report.md'}; figures: {out / 'figures'}/ (done in {say.elapsed:.1f} s)")
    return 0 if ok and outcome.result.valid else 1
