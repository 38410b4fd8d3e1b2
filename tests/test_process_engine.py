"""The process-noise fit, library and command line, against an independent reference.

Data: `tests/rc3_reference.py` (numpy/scipy only): a three-state stochastic RC building model
(indoor air and envelope measured, heater node not), three inputs (ambient temperature, heater
power, solar gain), process noise on every state, measurement noise, 1,500 irregular frames
with dropped readings, drawn by the exact discretisation of the SDE. The reference maximum
log-likelihood is the numpy Kalman filter's, maximised by scipy from several starts (the
truth, a start up to a factor 2 from it, and greybox's estimate).

`greybox fit` on an experiment folder of those data (`tests/rc_folder.py`: the device file
beside it, `noise_model = "process"`), every physical and noise parameter started a factor
3-10 away from the truth, must reach the reference maximum within 0.1, with every parameter
within 3 standard errors of the truth and the status "converged". The library's
`greybox.fit` on the same loaded folder (the composition the command runs) gives the same
estimate to 1e-8 and is checked at the level of its `FitResult`; it reuses the command's
compiled likelihood, so the second fit costs only its solve.

Measured (seed 0): greybox log L 3256.8245989 (command and library), the scipy reference
maximum 3256.8245986 (trust-region Newton: about 9 s for the truth and the factor-2 start on
a loaded 2-core machine, where L-BFGS-B from the same starts took 1-2 minutes).
"""

import dataclasses
import json

import numpy as np
import pytest
import scipy.linalg as sla

import greybox
from greybox.blocks._camera import SensorReadout
from greybox.cli import main
from tests import rc3_reference as ref
from tests.rc_building_device import NOMINAL, RCBuilding
from tests.rc_folder import write_folder

PHYS = ("Ci", "Ce", "Ch", "Rie", "Rea", "Rih", "Aw")
NOISE = {"q_i": "process.air", "q_e": "process.envelope", "q_h": "process.heater"}
MEAS = {"sd_Ti": "measurement.Ti", "sd_Te": "measurement.Te"}
# start values: every parameter a factor 3-10 from the truth
FACTORS = {
    "Ci": 4.0,
    "Ce": 0.25,
    "Ch": 3.0,
    "Rie": 0.3,
    "Rea": 5.0,
    "Rih": 0.2,
    "Aw": 0.3,
    "q_i": 10.0,
    "q_e": 0.1,
    "q_h": 8.0,
    "sd_Ti": 4.0,
    "sd_Te": 0.25,
}


# the command's folder: these noise starts; its physical starts are the device file's nominal
# values (tests/rc_building_device.NOMINAL), a factor 3-4 from the truth
NOISE_FACTORS = {k: FACTORS[k] for k in (*NOISE, *MEAS)}


def RC3(**values):  # noqa: N802 (the reference's TiTeTh model, air and envelope read)
    """The reference's TiTeTh model as a user writes it (tests/rc_building_device.py)."""
    return RCBuilding(**values, readout=SensorReadout(), nodes=3, outputs_read=2)


STRUCTURE = greybox.NoiseStructure(
    process_groups=(("air", (0,)), ("envelope", (1,)), ("heater", (2,)))
)


def _experiment(data):
    u = greybox.PiecewiseConstant(
        data["u_times_s"], data["u_levels"], float(data["t_s"][-1]) + 600.0
    )
    return greybox.Experiment("rc3", data["t_s"], data["y"], u)


def _free():
    units = {"Ci": "J/K", "Ce": "J/K", "Ch": "J/K", "Rie": "K/W", "Rea": "K/W", "Rih": "K/W"}
    free = [greybox.FreeParameter(k, units.get(k, "m^2"), lower=0.0) for k in PHYS]
    free += [greybox.FreeParameter(v, "K^2/s", lower=0.0) for v in NOISE.values()]
    free += [greybox.FreeParameter(v, "K", lower=0.0) for v in MEAS.values()]
    return free


def _start_model(data, x0):
    t = data["truth"]
    dev = RC3(
        **{k: t[k] * FACTORS[k] for k in PHYS},
        Ti0=float(x0[0]),
        Te0=float(x0[1]),
        Th0=float(x0[2]),
    )
    values = {v: t[k] * FACTORS[k] for k, v in {**NOISE, **MEAS}.items()}
    return greybox.stochastic.stochastic_device(dev, STRUCTURE, outputs=("Ti", "Te"), values=values)


def _estimate(result) -> dict:
    """{reference name: estimate}"""
    paths = {**{k: k for k in PHYS}, **NOISE, **MEAS}
    return {k: result.estimate(p).value for k, p in paths.items()}


def _estimate_paths(result) -> dict:
    """{greybox path: estimate}"""
    paths = {**{k: k for k in PHYS}, **NOISE, **MEAS}
    return {p: result.estimate(p).value for p in paths.values()}


@pytest.fixture(scope="module")
def data():
    return ref.simulate(seed=0)


def _noise_table(data) -> str:
    """The three-state noise table with start values a factor 3-10 from the truth."""
    start = ", ".join(
        f'"{path}" = {data["truth"][k] * NOISE_FACTORS[k]!r}'
        for k, path in {**NOISE, **MEAS}.items()
    )
    return (
        "[noise]\nprocess = { air = [0], envelope = [1], heater = [2] }\n"
        f"initial = {{ {start} }}\n"
    )


@pytest.fixture(scope="module")
def folder(tmp_path_factory, data):
    root = tmp_path_factory.mktemp("rc3")
    return write_folder(
        root, data, noise=_noise_table(data), validation=ref.simulate(seed=1, n=100)
    )


@pytest.fixture(scope="module")
def cli_fit(folder):
    """`greybox fit` on the folder: (exit status, folder, result folder, params.json)."""
    out = folder.parent / "result"
    code = main(["fit", str(folder), "--out", str(out), "--quiet"])
    return code, folder, out, json.loads((out / "params.json").read_text())


@pytest.fixture(scope="module")
def fitted(folder, cli_fit):
    """The library's `FitResult` for the same folder: `greybox.fit` on the loaded experiment
    set, composed as the command composes it (after the command: the compiled likelihood is
    reused)."""
    from greybox.cli._common import fit_loaded
    from greybox.io import load_experiment_set

    result, _ = fit_loaded(load_experiment_set(folder), lambda message: None)
    return result


def test_starts_are_a_factor_3_to_10_from_the_truth(data):
    truth = data["truth"]
    for k in PHYS:
        r = NOMINAL[k] / truth[k]
        assert 3.0 <= max(r, 1 / r) <= 10.0, (k, r)
    for k, f in NOISE_FACTORS.items():
        assert 3.0 <= max(f, 1 / f) <= 10.0, (k, f)


def test_library_and_command_give_the_same_fit(cli_fit, fitted):
    code, _, _, doc = cli_fit
    assert code == 0
    assert doc["log_likelihood"] == pytest.approx(fitted.log_likelihood, abs=1e-8)
    by_path = {p["path"]: p["value"] for p in doc["parameters"]}
    for path, value in _estimate_paths(fitted).items():
        assert by_path[path] == pytest.approx(value, rel=1e-8), path


@pytest.fixture(scope="module")
def reference(data, fitted):
    return ref.reference_max(data, n_starts=2, extra_starts=[_estimate(fitted)])


def test_reaches_the_reference_maximum(data, cli_fit, fitted, reference):
    ll_ref, _ = reference
    _, _, _, doc = cli_fit
    assert doc["log_likelihood"] >= ll_ref - 0.1  # the command's fit reaches it
    assert doc["convergence"]["status"] == "converged"
    # greybox's own value and the numpy filter at greybox's estimate agree ...
    ll_at_estimate = ref.loglik(_estimate(fitted), data)
    assert fitted.log_likelihood == pytest.approx(ll_at_estimate, abs=1e-6)
    # ... and no reference start found a higher maximum
    assert fitted.log_likelihood >= ll_ref - 0.1
    assert fitted.status == "converged", fitted.message
    assert fitted.valid


def test_every_parameter_within_three_standard_errors(data, fitted):
    truth = data["truth"]
    paths = {**{k: k for k in PHYS}, **NOISE, **MEAS}
    for k, path in paths.items():
        est = fitted.estimate(path)
        p = next(q for q in fitted.free if q.path == path)
        j = [q.path for q in fitted.free].index(path)
        sd_raw = float(np.sqrt(fitted.covariance_raw[j, j]))
        z = (fitted.raw[j] - float(p.to_raw(truth[k]))) / sd_raw
        assert abs(z) < 3.0, (path, est.value, truth[k], z)


def test_result_carries_every_horizon(data, fitted):
    run = fitted.predictions["rc3"]
    assert set(run) == {"simulation", "one-step", "k-step"}
    # the loaded run's rows: every frame and every input change (readings NaN there)
    y = np.asarray(fitted.experiments[0].y)
    read = data["y"][np.isfinite(data["y"]).any(axis=1)]
    np.testing.assert_allclose(y[np.isfinite(y).any(axis=1)], read, atol=1e-8)  # CSV: 9 decimals
    ok = np.isfinite(y)

    def rmse(z):
        return float(np.sqrt(np.mean((y - z)[ok] ** 2)))

    # one-step < k-step < simulation error: the horizons are what they say
    assert rmse(run["one-step"]) < rmse(run["k-step"]) < rmse(run["simulation"])
    assert fitted.n_observations == int(ok.sum()) - int(ok[0].sum())
    assert fitted.aic == pytest.approx(-2 * fitted.log_likelihood + 2 * fitted.raw.size)
    assert len(fitted.multistart_costs) == 1


def test_initial_state_from_first_reading_keeps_measurement_noise():
    """The initial state read off the first reading (the unmeasured heater node: the air
    reading, with a 3 K prior sd): the measurement sd stays near the truth instead of
    collapsing, and the fit converges. 600 frames of the reference model show it (the sds
    came back within 4 % of the truth on seeds 0-2; within 6 % on 1,500 frames, which took
    twice as long)."""
    data = ref.simulate(seed=0, n=600)
    y0 = data["y"][0]
    model = _start_model(data, (y0[0], y0[1], y0[0]))
    noise = greybox.ProcessNoise(STRUCTURE, initial_state=greybox.InitialState(sd=(0, 0, 3.0)))
    res = greybox.fit(model, [_experiment(data)], _free(), noise=noise, n_starts=1)
    for k, path in MEAS.items():
        v = res.estimate(path).value
        assert 0.5 * data["truth"][k] < v < 2.0 * data["truth"][k], (path, v)
    assert res.status == "converged", res.message


def test_at_bound_judged_in_log_space():
    p = greybox.FreeParameter("R", lower=1.0, upper=1e4)
    assert p.bound_hit(float(p.to_raw(5.3)), 0.0) is None
    assert p.bound_hit(float(p.to_raw(1.0001)), 0.0) == "lower"
    lag = greybox.FreeParameter("tau", lower=1e-4, upper=1.0)
    assert lag.bound_hit(float(lag.to_raw(1.06e-3)), 0.0) is None
    assert lag.bound_hit(float(lag.to_raw(0.99995)), 0.0) == "upper"


@pytest.mark.parametrize("minimum", [0.5, -0.5])
def test_a_vanished_intensity_is_restarted_only_where_zero_is_no_minimum(minimum):
    """`likelihood.revive` on a closed-form cost in one intensity q >= 0 (start 1):
    -log L = (q - minimum)^2 + 7. A solve that ended with q vanished (1e-9) at a minimum of 0.5
    sits where the cost still falls as q rises (dc/dq = -1 at zero, hidden in log coordinates
    by the factor q): it is restarted from q = 1 and ends at 0.5, 0.25 lower. At -0.5 zero is
    the bound-constrained minimum (dc/dq = +1): nothing is solved again."""
    from greybox._estimate import likelihood as lik

    p = greybox.FreeParameter("process.q", lower=0.0)
    raw0 = np.array([float(p.to_raw(1.0))])

    def cost(q):
        return (q - minimum) ** 2 + 7.0

    def totals(_item, raws):
        return np.array([cost(float(p.to_value(r[0]))) for r in raws])

    solved = []

    def solve(items):  # the solve from each start ends at the interior minimum (or zero)
        solved.extend(float(p.to_value(r[0])) for _, r in items)
        q = max(minimum, 1e-12)
        return [{"raw": np.array([float(p.to_raw(q))]), "cost": cost(q), "steps": 5}] * len(items)

    vanished = {"raw": np.array([float(p.to_raw(1e-9))]), "cost": cost(1e-9), "steps": 40}
    said = []
    out = lik.revive([vanished], [[p]], [raw0], solve, totals, said.append, ["start 1/1"])[0]
    if minimum > 0:
        assert solved == pytest.approx([1.0])  # restarted from its start value
        assert float(p.to_value(out["raw"][0])) == pytest.approx(0.5)
        assert vanished["cost"] - out["cost"] == pytest.approx(0.25, rel=1e-6)
        assert out["steps"] == 45 and "process.q had vanished" in said[0]
    else:
        assert solved == [] and said == []
        assert out["cost"] == vanished["cost"] and out["steps"] == 40


def test_process_noise_not_needed_leaves_fit_valid(data):
    """Data without envelope process noise: that intensity goes to zero, "not needed", and the
    fit is still valid."""
    truth = dict(data["truth"], q_e=0.0)
    d0 = ref.simulate(seed=1, n=600, truth=truth)
    t = d0["truth"]
    dev = RC3(**{k: t[k] for k in PHYS}, Ti0=ref.X0[0], Te0=ref.X0[1], Th0=ref.X0[2])
    values = {"process.air": t["q_i"], "process.envelope": 1e-7, "process.heater": t["q_h"]}
    values |= {v: t[k] for k, v in MEAS.items()}
    model = greybox.stochastic.stochastic_device(
        dev, STRUCTURE, outputs=("Ti", "Te"), values=values
    )
    free = [greybox.FreeParameter(v, "K^2/s", lower=0.0) for v in NOISE.values()]
    free += [greybox.FreeParameter(v, "K", lower=0.0) for v in MEAS.values()]
    free += [greybox.FreeParameter("Rea", "K/W", lower=0.0)]
    noise = dataclasses.replace(greybox.ProcessNoise(STRUCTURE), start_noise=False)
    res = greybox.fit(model, [_experiment(d0)], free, noise=noise, n_starts=1)
    assert res.estimate("process.envelope").verdict == "not needed", res.estimate(
        "process.envelope"
    )
    assert res.valid, res.message


def test_validate_scores_new_runs_at_the_estimate(data, fitted):
    """`greybox.validate` on a new record: its innovations' log-likelihood at the fitted
    parameters equals the numpy filter's, and every horizon is reported. Its residual test
    is the fit's, on the one-step innovations: white on a record of the true structure
    (numpy-simulated), where the free-run simulation residuals are not (the process noise
    makes the record wander from the deterministic response)."""
    from greybox._estimate.residuals import analyse

    new = ref.simulate(seed=5, n=300)
    e = _experiment(new)
    val = greybox.validate(fitted, [e])
    (run,) = val.runs
    assert run.role == "validation"
    assert run.log_likelihood == pytest.approx(ref.loglik(_estimate(fitted), new), abs=1e-6)
    assert [h for h, _, _ in run.horizons] == [
        "simulation",
        "one-step prediction",
        "10-step prediction",
    ]
    assert val.fit_percent["rc3"].shape == (2,)
    assert val.residuals.all_white and np.all(val.residuals.p_value > 0.01), val.residuals.verdict
    innovations = analyse([(e.name, e.t_s, e.y - run.y_one_step, e.mask, e.frame_inputs())])
    assert np.allclose(val.residuals.q, innovations.q)
    wander = analyse([(e.name, e.t_s, e.y - run.y_simulation, e.mask, e.frame_inputs())])
    assert not wander.all_white and np.nanmax(wander.p_value) < 0.01 / 2, wander.verdict


# ------------------------------------------------------------------------------------------
# the command's result folder


@pytest.mark.slow
def test_process_noise_fit_recovers_the_truth(cli_fit, data):
    code, _, out, doc = cli_fit
    assert code == 0
    assert doc["schema"] == "greybox.params/3"
    assert doc["noise_model"]["kind"] == "process noise"
    assert doc["convergence"]["status"] == "converged"
    by_path = {p["path"]: p for p in doc["parameters"]}
    truth = data["truth"]
    for path in PHYS:
        p = by_path[path]
        assert abs(p["value"] - truth[path]) < 3 * p["se"], (path, p["value"], p["se"])
    for name, path in {**NOISE, **MEAS}.items():
        p = by_path[path]
        if p["verdict"] == "identifiable":
            assert abs(p["value"] - truth[name]) < 3 * p["se"], (path, p["value"], p["se"])
    # the likelihood the CLI reports is the independent numpy Kalman filter's at the estimate
    estimate = {k: by_path[k]["value"] for k in PHYS}
    estimate.update({name: by_path[path]["value"] for name, path in {**NOISE, **MEAS}.items()})
    assert doc["log_likelihood"] == pytest.approx(ref.loglik(estimate, data), abs=1e-6)


@pytest.mark.slow
def test_process_noise_result_folder(cli_fit):
    _, _, out, doc = cli_fit
    metrics = (out / "metrics.csv").read_text().splitlines()
    assert metrics[0] == "run,role,output,horizon,unit,n,fit_percent,rmse,mae,sae"
    horizons = {line.split(",")[3] for line in metrics[1:]}
    assert horizons == {"simulation", "one-step prediction", "10-step prediction"}
    header = (out / "predictions" / "rc3.csv").read_text().splitlines()[0].split(",")
    for col in ("Ti_K", "Ti_sim_K", "Ti_onestep_K", "Ti_10step_K", "Ti_innovation_K"):
        assert col in header
    # the innovations in the CSV are measured - one-step prediction (10 significant digits)
    table = np.genfromtxt(out / "predictions" / "rc3.csv", delimiter=",", names=True)
    ok = np.isfinite(table["Ti_K"])
    np.testing.assert_allclose(
        table["Ti_innovation_K"][ok], (table["Ti_K"] - table["Ti_onestep_K"])[ok], atol=2e-7
    )
    report = (out / "report.md").read_text()
    assert "prediction-error form" in report and "one-step prediction" in report
    # the headline verdict (residual test on the innovations) opens report.md, as params.json
    head = doc["headline"]
    assert head["verdict"] == "valid", head  # the true structure, white innovations
    assert report.splitlines()[2] == f"**{head['text']}**"
    assert doc["runs"]["rc3"]["whiteness"]["Ti"]["test"] == "Ljung-Box"
    # one residual test throughout: the one the headline used, on the innovations of the
    # estimation and the validation runs, in report.md and params.json alike
    for key, runs in (("residuals", "estimation"), ("residuals_validation", "validation")):
        tested = doc[key]
        assert tested["tested"].startswith("innovations") and tested["white"], tested
        assert f"**Innovations ({runs} runs): {tested['verdict']}.**" in report
    assert "20 lags" not in report
    assert (out / "figures" / "innovations_Ti.png").is_file()
    # the validation run: filtered at the estimate, scored at every horizon
    assert {tuple(line.split(",")[:2]) for line in metrics[1:]} == {
        ("rc3", "estimation"),
        ("val", "validation"),
    }
    val = json.loads((out / "validation_runs.json").read_text())["runs"]["val"]
    assert set(val["fit_percent"]) == horizons and val["whiteness"]["Te"]["test"] == "Ljung-Box"
    assert np.isfinite(val["log_likelihood"]) and val["refitted"] == {}


def _numpy_response(p: dict, x0, t, levels):
    """The deterministic response (air, envelope) of the reference model with inputs held
    constant on each step (exact ZOH discretisation, scipy's expm)."""
    A, B, *_ = ref.matrices({**ref.TRUTH, **p})
    x, out = np.asarray(x0, float), [np.asarray(x0, float)[:2]]
    for k in range(t.size - 1):
        h = t[k + 1] - t[k]
        m = np.zeros((6, 6))
        m[:3, :3], m[:3, 3:] = A * h, B * h
        e = sla.expm(m)
        x = e[:3, :3] @ x + e[:3, 3:] @ levels[k]
        out.append(x[:2])
    return np.array(out)


@pytest.mark.slow
def test_process_params_load_and_drive_simulate(cli_fit, data, tmp_path):
    from greybox.io import load_params

    _, _, out, doc = cli_fit
    device_file = str(doc["device"]["location"])  # a user's file beside the folder: trusted
    loaded = load_params(out / "params.json", trust_device=(device_file,))
    assert loaded.noise_model == "process noise"
    from greybox._model.parameters import get_value

    for path, value in doc["noise_model"]["values"].items():
        assert float(get_value(loaded.model, path)) == pytest.approx(value, rel=1e-12)
    sim = tmp_path / "sim"
    args = ["simulate", "--params", str(out / "params.json"), "--out", str(sim)]
    args += ["--trust-device", device_file, "--dt-ms", "600000"]
    args += ["--waveform", "Ta=const:280", "--waveform", "Ps=const:0"]
    args += ["--waveform", "Ph=pulse:Ph_W=1500,period_s=86400,duty=0.5,n=2"]
    assert main(args) == 0
    meta = json.loads((sim / "simulation.json").read_text())
    assert meta["noise_model"] == "process noise"
    assert "process noise" in meta["band"]["kind"]
    table = np.genfromtxt(sim / "simulation.csv", delimiter=",", names=True)
    t = table["t_s"]
    levels = np.column_stack(
        [np.full(t.size, 280.0), np.where((t % 86400) < 43200, 1500.0, 0.0), np.zeros(t.size)]
    )
    by_path = {p["path"]: p["value"] for p in doc["parameters"]}
    y = _numpy_response({k: by_path[k] for k in PHYS}, data["x0"], t, levels)
    # simulation.csv holds 6 significant digits: 1e-3 K at 293 K
    np.testing.assert_allclose(table["Ti_K"], y[:, 0], atol=5.1e-4)
    np.testing.assert_allclose(table["Te_K"], y[:, 1], atol=5.1e-4)
    width = table["Ti_hi95_K"] - table["Ti_lo95_K"]
    assert width[0] < 1e-6  # the initial state is known
    assert width[-1] > 0.1  # process noise and the parameters' spread widen it




def test_a_start_that_needed_newton_iterations_ends_on_a_central_hessian():
    """-log L = sum(exp(x) - (2, 3) x) + (x1 - x2)^2 / 2 (a closed form: Hessian diag(exp(x))
    + [[1, -1], [-1, 1]]; third derivatives exp(x), so a forward difference of step 1e-4 is
    off by ~1e-4 relative, a central one by ~1e-9). Three BFGS steps from (2, -1) stop short
    of the minimum, so Newton takes over: its Hessians in between are forward differences,
    and the one returned for the covariance must be central, at the end point, and the end
    point the minimum (its gradient nought to the tolerance)."""
    import equinox as eqx
    import jax.numpy as jnp

    from greybox._estimate import likelihood as lik

    class Closed(eqx.Module):
        def data_nll(self, r):
            return jnp.sum(jnp.exp(r) - jnp.array([2.0, 3.0]) * r) + 0.5 * (r[0] - r[1]) ** 2

        def prior_nll(self, r):
            return 0.0 * r[0]

    out = lik._newton(Closed(), jnp.array([2.0, -1.0]), jnp.asarray(3))
    raw = np.asarray(out["raw"])
    assert bool(out["converged"]) and int(out["steps"]) > 3  # Newton iterations were needed
    gradient = np.exp(raw) - [2.0, 3.0] + np.array([1.0, -1.0]) * (raw[0] - raw[1])
    hessian = np.diag(np.exp(raw)) + np.array([[1.0, -1.0], [-1.0, 1.0]])
    assert np.max(np.abs(gradient)) < 1e-5
    np.testing.assert_allclose(np.asarray(out["hessian"]), hessian, rtol=1e-7, atol=1e-9)
