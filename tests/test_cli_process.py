"""`greybox compare`, `fit --candidate`, `fit-many` and the `[noise]` table on process-noise
experiment folders, checked against the numpy/scipy reference of tests/rc3_reference.py (a
three-state stochastic RC building model: exact discretisation of the SDE, irregular frames,
dropped readings). `greybox fit`, its result folder, `load_params` and `simulate` on such a
folder are tested in tests/test_process_engine.py (one 1,500-frame fit serves both the library
and the command line there).

- `greybox compare` with one-, two- and three-state candidates (the air temperature read
  alone, each candidate with its own noise table) prefers the three-state structure; its
  likelihood-ratio p-values are chi-square tail areas of the candidates' log-likelihoods.
- A folder whose third candidate is invalid exits 2 at once, fitting nothing, with every
  problem listed; `greybox fit --candidate` reproduces that candidate's row of compare.json.

Records are short (300 frames) so the fits stay within a few minutes on two cores.
"""

import csv
import io
import json
import time

import pytest
from scipy.stats import chi2

from greybox.cli import main
from tests import rc3_reference as ref
from tests.rc_folder import CANDIDATES, write_candidates_folder, write_folder

N_FRAMES = 300

@pytest.fixture(scope="module")
def data():
    return ref.simulate(seed=0, n=N_FRAMES)


# ------------------------------------------------------------------------------------------
# compare


@pytest.fixture(scope="module")
def compared(tmp_path_factory, data):
    root = tmp_path_factory.mktemp("rc3cands")
    folder = write_candidates_folder(root, data)
    out = root / "compare"
    code = main(["compare", str(folder), "--out", str(out), "--quiet"])
    return code, folder, out, json.loads((out / "compare.json").read_text())


@pytest.mark.slow
def test_compare_prefers_three_states_and_lr_tests_match_chi_square(compared):
    code, _, out, doc = compared
    assert code == 0
    assert doc["preferred"] == "three states"
    cands = {c["name"]: c for c in doc["candidates"]}
    # k: the fitted values of each structure (physics + process intensities + sensor sd)
    assert {n: c["k"] for n, c in cands.items()} == {
        "one state": 3 + 1 + 1,
        "two states": 5 + 2 + 1,
        "three states": 7 + 3 + 1,
    }
    tests = {(t["larger"], t["nested"]): t for t in doc["likelihood_ratio_tests"]}
    assert set(tests) == {("two states", "one state"), ("three states", "two states")}
    for (big, small), t in tests.items():
        stat = 2 * (cands[big]["loglik"] - cands[small]["loglik"])
        dof = cands[big]["k"] - cands[small]["k"]
        assert t["statistic"] == pytest.approx(stat, rel=1e-12)
        assert t["dof"] == dof
        assert t["p_value"] == pytest.approx(chi2.sf(stat, dof), rel=1e-9, abs=1e-300)
    for c in doc["candidates"]:  # every candidate lists its estimates with intervals
        assert {e["path"] for e in c["estimates"]} >= {"Ci", "process.air", "measurement.Ti"}
        assert all(len(e["ci95"]) == 2 and e["verdict"] for e in c["estimates"])
    md = (out / "compare.md").read_text()
    assert "Likelihood-ratio tests" in md and "### three states" in md
    # candidates that differ in their [noise] say how in the table and in compare.json
    assert cands["two states"]["noise"] == (
        "process noise on air (states [0]), envelope (states [1]); disturbances: none"
    )
    row = next(line for line in md.splitlines() if line.startswith("| two states |"))
    assert f"noise: {cands['two states']['noise']}" in row
    # each candidate's headline verdict; the preferred one is valid and plausible
    assert cands["three states"]["headline"]["verdict"] == "valid"
    assert all(c["headline"]["text"] in md for c in cands.values())


@pytest.mark.slow
def test_fit_candidate_reproduces_its_compare_row(compared, tmp_path):
    _, folder, _, doc = compared
    out = tmp_path / "one"
    argv = ["fit", str(folder), "--candidate", "one state", "--out", str(out), "--quiet"]
    assert main([*argv, "--no-figures"]) == 0
    params = json.loads((out / "params.json").read_text())
    row = next(c for c in doc["candidates"] if c["name"] == "one state")
    assert params["experiment"]["candidate"] == "one state"
    assert params["log_likelihood"] == pytest.approx(row["loglik"], rel=1e-9)
    assert params["aic"] == pytest.approx(row["aic"], rel=1e-9)
    values = {p["path"]: p["value"] for p in params["parameters"]}
    for e in row["estimates"]:
        assert values[e["path"]] == pytest.approx(e["value"], rel=1e-7), e["path"]


def test_invalid_third_candidate_exits_2_before_any_fit(tmp_path, data, capsys):
    third = CANDIDATES.index('name = "three states"')
    bad = CANDIDATES[:third] + (
        CANDIDATES[third:]
        .replace('path = "Rih"', 'path = "Xyz"')
        .replace("heater = [2] }", "heater = [7] }")
        .replace('nests = ["two states"]', 'nests = ["two states"]\nfit = { loss = "l2" }')
    )
    folder = write_candidates_folder(tmp_path, data, bad)
    out = tmp_path / "out"
    t0 = time.perf_counter()
    assert main(["compare", str(folder), "--out", str(out), "--quiet"]) == 2
    assert time.perf_counter() - t0 < 10
    assert not out.exists()
    err = capsys.readouterr().err
    assert "candidates[2].free[5].path: 'Xyz' is not a parameter" in err, err
    assert "candidates[2].fit.loss: does not apply" in err
    assert "candidates[2].noise.process.heater: state(s) [7] do not exist" in err


# ------------------------------------------------------------------------------------------
# [noise] and [fit] checked in io, before any fit (fast: nothing is compiled)


def _folder_with(tmp_path, data, extra="", noise=None, fit_extra=""):
    from tests.rc_folder import THREE_STATE_NOISE

    folder = write_folder(tmp_path, data, noise=noise or THREE_STATE_NOISE, extra=extra)
    toml = folder / "experiment.toml"
    toml.write_text(toml.read_text().replace("n_starts = 1\n", f"n_starts = 1\n{fit_extra}"))
    return folder


@pytest.mark.parametrize(
    ("fit_extra", "noise_extra", "field"),
    [
        ('loss = "l2"\n', "", "fit.loss: does not apply"),
        ('method = "zoh"\n', "", "fit.method: does not apply"),
        ("", "initial_state = { sd = [0.1, 0.2] }\n", "noise.initial_state.sd: give one sd"),
        ("", 'initial_state = "estimated"\n', "noise.initial_state: 'estimated'"),
        ("", 'fixed = { "measurement.T9" = 0.1 }\n', "noise.fixed.measurement.T9: not a noise"),
        ("", "k_step = 20000\n", "noise.k_step: 20000 is above the largest allowed, 10000"),
        ("", "k_step = 5000\n", "noise.k_step: 5000 frames is not shorter than the longest run"),
    ],
)
def test_noise_and_fit_settings_are_checked_by_name(
    tmp_path, data, capsys, fit_extra, noise_extra, field
):
    from tests.rc_folder import THREE_STATE_NOISE

    folder = _folder_with(
        tmp_path, data, noise=THREE_STATE_NOISE + noise_extra, fit_extra=fit_extra
    )
    out = tmp_path / "out"
    assert main(["fit", str(folder), "--out", str(out), "--quiet"]) == 2
    assert field in capsys.readouterr().err
    assert not out.exists()


def test_noise_table_maps_once_to_the_engine_objects(tmp_path, data):
    import greybox
    from greybox.io import load_experiment_set
    from greybox.io._noise_table import noise_model
    from tests.rc_folder import THREE_STATE_NOISE

    noise = THREE_STATE_NOISE + 'initial_state = "diffuse"\nfilter = "kalman"\n'
    noise += 'fixed = { "measurement.Te" = 0.08 }\nk_step = 5\n'
    fs = load_experiment_set(_folder_with(tmp_path, data, noise=noise, fit_extra="seed = 3\n"))
    assert fs.fit_options == {"n_starts": 1, "seed": 3, "max_steps": None}
    model, config, free = noise_model(fs.noise, fs.model, fs.spec)
    assert config.initial_state == greybox.InitialState(diffuse=True)
    assert config.filter == greybox.KalmanFilter() and config.k_step == 5
    assert [p.path for p in free] == [
        "process.air",
        "process.envelope",
        "process.heater",
        "measurement.Ti",
    ]
    from greybox._model.parameters import get_value

    assert float(get_value(model, "measurement.Te")) == 0.08


@pytest.mark.slow
def test_fit_many_fits_process_noise_devices(tmp_path):
    """Two devices (records of two seeds), each a one-node process-noise folder of the air
    temperature: fit-many writes each device's params.json (a process-noise file) and the
    batch table; each device's log-likelihood is the one `greybox fit` gives that folder."""
    one_node = '[model]\nnodes = 1\n\n[noise]\nprocess = { air = [0] }\n'
    folders = []
    for seed in (0, 2):
        d = ref.simulate(seed=seed, n=150)
        folders.append(
            write_folder(
                tmp_path / f"s{seed}", d, spec="SPEC_AIR", outputs=("Ti",), noise=one_node,
                name=f"house{seed}",
            )
        )
    out = tmp_path / "batch"
    assert main(["fit-many", *map(str, folders), "--out", str(out), "--quiet"]) in (0, 1)
    rows = (out / "batch.csv").read_text().splitlines()
    assert rows[0].startswith("device,status") and len(rows) == 3
    single = tmp_path / "single"
    assert main(["fit", str(folders[1]), "--out", str(single), "--quiet", "--no-figures"]) in (0, 1)
    one = json.loads((single / "params.json").read_text())
    batch = json.loads((out / "devices" / "house2" / "params.json").read_text())
    assert batch["noise_model"]["kind"] == "process noise"
    assert batch["log_likelihood"] == pytest.approx(one["log_likelihood"], rel=1e-9)
    # batch.md and batch.csv say what was minimised and give each device's headline verdict,
    # the one its report.md opens with
    md = (out / "batch.md").read_text()
    assert "maximum likelihood of the one-step prediction errors" in md
    assert "free-run simulation error" not in md
    row = next(r for r in csv.DictReader(io.StringIO((out / "batch.csv").read_text())))
    assert row["objective"] == "-log L (one-step prediction errors)"
    device = json.loads((out / "devices" / row["device"] / "params.json").read_text())
    assert row["verdict"] == device["headline"]["verdict"]
    assert f"| {row['device']} | {row['status']} | {row['verdict']} |" in md
