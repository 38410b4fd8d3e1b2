"""`greybox fit` on the synthetic micro-robot folder (experiments/microrobot): the identifiable
parameters come back within 3 standard errors of truth.json, the friction capacity and the
leg stiffness are reported as prior-dominated (pose data fix only their ratio W), and the
result folder is complete."""

import json
from pathlib import Path

import pytest

from greybox.cli import main

FOLDER = Path(__file__).resolve().parents[1] / "experiments" / "microrobot"
IDENTIFIABLE = ("absorptance_left", "thermal.frame_capacitance_J_per_K", "locomotion.turn_gain")
PRIOR_DOMINATED = ("locomotion.foot_forward_N", "locomotion.stiffness_N_per_m")


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    out = tmp_path_factory.mktemp("microrobot") / "result"
    assert main(["fit", str(FOLDER), "--out", str(out), "--quiet", "--no-figures"]) == 0
    return out, json.loads((out / "params.json").read_text())


def test_fit_recovers_truth_and_reports_verdicts(fitted):
    out, doc = fitted
    truth = json.loads((FOLDER / "truth.json").read_text())["parameters"]
    shared = {p["path"]: p for p in doc["parameters"] if p["experiment"] is None}
    for path in IDENTIFIABLE:
        p = shared[path]
        assert p["verdict"] == "identifiable", p
        assert abs(p["value"] - truth[path]["value"]) < 3 * p["se"], p
    for path in PRIOR_DOMINATED:
        assert shared[path]["verdict"] == "prior-dominated", shared[path]
        assert shared[path]["prior"] is not None
    assert doc["convergence"]["converged"]
    assert doc["fit_percent"]["horizon"] == "simulation"
    assert min(min(v) for v in doc["fit_percent_robust"]["validation"].values()) > 75.0
    assert (out / "report.md").is_file()


def test_fit_started_above_the_walk_lands_in_the_dead_zone_and_says_so():
    # starting at the nominal gain and turning gain over-predicts the walk by more than the
    # walk itself, so standing still fits better: Levenberg-Marquardt descends into the play
    # dead zone (S_pp < W, every motion gradient zero). That must not read as a success.
    import dataclasses

    from greybox._estimate.fit import fit
    from greybox.io import load_experiment_set

    fs = load_experiment_set(FOLDER)
    nominal = {"absorptance_left": 0.448, "locomotion.turn_gain": 1.0}
    free = [
        dataclasses.replace(p, initial=nominal[p.path]) if p.path in nominal else p for p in fs.free
    ]
    # one start only: the automatic multi-start (4 starts here) is what rescues such a start
    result = fit(fs.model, fs.estimation, free, **{**fs.fit_options, "n_starts": 1})
    verdicts = {p.name: p.verdict for p in result.parameters}
    assert result.estimate("absorptance_left").value < 0.2  # no motion left
    assert verdicts["absorptance_left"] in ("not identifiable", "at bound")
    assert verdicts["locomotion.turn_gain"] in ("not identifiable", "at bound")
    assert not result.valid
