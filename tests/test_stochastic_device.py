"""Stochastic grey-box fits of a greybox device (process noise, random-walk disturbances, EKF).

Truth is independent of greybox's filter and discretisation:

- data: the linear two-heater TCLab (the built-in `tclab` device without radiation) with
  process noise on the heater nodes and one random-walk ambient offset shared by both sensors,
  simulated by a numpy/scipy exact discretisation written here (the network matrices from the
  physics, `scipy.linalg.expm` of Van Loan's block matrix per step), at irregular frame times
  with dropped frames;
- the deterministic fit: free-run least squares of the same network by `scipy.optimize`
  over the same numpy matrices (batched `scipy.linalg.expm` per step), not greybox;
- the zero-noise EKF likelihood of the nonlinear (radiation) TCLab against the Gaussian
  likelihood of `greybox.simulate`'s residuals (diffrax at tight tolerances, a different
  integrator from the filter's local linearisation);
- the EKF on a linear device against the exact linear Kalman filter;
- the Kalman likelihood on a regular grid against dynamax's `lgssm_filter` (a maintained JAX
  filtering library) given the same discretised matrices.

One compiled fit is shared: the library fit is built exactly as `greybox fit` builds it from
the experiment folder (same model options, free list, units and starts), so the command's fit
of the same record reuses its compiled likelihood and filter.

Measured on the synthetic record (600 frames at irregular 0.6-1.4 s, 4 dropped frames and one
dropped reading, seed 3): stochastic fit z-scores (raw coordinates) U 0.11, Us 1.06, alpha1
0.14, alpha2 0.55, tau -0.09, q_heaters -0.55, sd_T1 -0.76, sd_T2 0.09, q_walk -1.34;
innovations Ljung-Box p 0.75 / 0.87; fit % per output ordered one-step > 10-step >
simulation. Deterministic least squares on the same data: residuals not white (Ljung-Box p = 0
on both outputs, lag-1 autocorrelation 0.86 / 0.80; estimates 0.95-1.13 x the truth). EKF
with zero process noise vs the simulation-residual likelihood: relative difference 2.4e-8 (the
default 4 local linearisations per step for a nonlinear device); EKF vs exact Kalman filter on
the linear device: ~1e-15; greybox vs dynamax on a regular grid: 7.5e-10 relative.
Coverage of the fit's 95 % intervals over 120 replicates: `benchmarks/kalman.py
--coverage-device 120`.
"""

import json

import numpy as np
import pytest
import scipy.linalg as sla
import scipy.optimize as so
from threadpoolctl import threadpool_limits

import greybox

SPEC = greybox.get_device("tclab")
OPTIONS = {"radiation": False, "shared_sensor_lag": True}
AMBIENT = 296.15
TRUTH = {
    "U_W_per_m2K": 6.0,
    "Us_W_per_m2K": 20.0,
    "alpha1_W_per_pct": 0.011,
    "alpha2_W_per_pct": 0.0075,
    "tau1_s": 25.0,
}
NOISE = {
    "process.heaters": 2e-3,
    "output_walk.shared": 4e-4,
    "measurement.T1": 0.08,
    "measurement.T2": 0.1,
}
# the units `greybox fit` gives these paths (thermal states and sensors in K)
UNITS = {
    "process.heaters": "K^2/s",
    "measurement.T1": "K",
    "measurement.T2": "K",
    "output_walk.shared": "K^2/s",
}
STRUCTURE = greybox.NoiseStructure(
    process_groups=(("heaters", (0, 1)),), disturbances=("ambient_random_walk_shared",)
)
X0 = np.array([1.0, 0.5, 1.0, 0.5])  # initial rises over ambient (the run's settings below)


def tclab_matrices(p):
    """Linear TCLab (rises over ambient: heater 1, heater 2, sensor 1, sensor 2), by hand."""
    c = 0.004 * 500.0
    ua, us = p["U_W_per_m2K"] * 10e-4, p["Us_W_per_m2K"] * 2e-4
    tau = p["tau1_s"]
    a = np.array(
        [
            [-(ua + us) / c, us / c, 0, 0],
            [us / c, -(ua + us) / c, 0, 0],
            [1 / tau, 0, -1 / tau, 0],
            [0, 1 / tau, 0, -1 / tau],
        ]
    )
    b = np.array([[p["alpha1_W_per_pct"] / c, 0], [0, p["alpha2_W_per_pct"] / c], [0, 0], [0, 0]])
    return a, b


def steps_of(e):
    """(step ends, step lengths, input level on each step) of a record: frames + switches."""
    sw = np.asarray(e.inputs.times_s)
    grid = np.unique(np.concatenate([[0.0], e.t_s, sw[sw > 0]]))
    levels = np.asarray(e.inputs(grid[:-1])).reshape(grid.size - 1, -1)
    return grid[1:], np.diff(grid), levels


def simulate_truth(seed=3, n=600):
    """Exact discretisation of the SDE (heater process noise + shared ambient random walk)."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.6, 1.4, n))
    t -= t[0]
    sw = t[::60]  # the heaters switch at frames (so a logged input column is exact)
    levels = rng.choice([0.0, 10.0, 25.0, 40.0], size=(sw.size, 2))
    levels[0] = 0.0
    u = greybox.PiecewiseConstant(sw, levels, t[-1] + float(np.median(np.diff(t))))
    a, b = tclab_matrices(TRUTH)
    qc = np.diag([NOISE["process.heaters"]] * 2 + [0.0, 0.0, NOISE["output_walk.shared"]])
    A = sla.block_diag(a, 0.0)
    B = np.vstack([b, np.zeros((1, 2))])
    x = np.zeros(5)
    x[:4] = X0
    grid = np.unique(np.concatenate([t, sw[sw > 0]]))
    states = {0.0: x.copy()}
    for t_a, t_b in zip(grid[:-1], grid[1:]):
        h = t_b - t_a
        m = np.zeros((12, 12))
        m[:5, :5], m[:5, 5:10], m[5:10, 5:10] = -A, qc, A.T
        m[10:, 5:10] = B.T
        E = sla.expm(m * h)
        ad = E[5:10, 5:10].T
        bd = E[10:, 5:10].T
        qd = ad @ E[:5, 5:10]
        qd = 0.5 * (qd + qd.T) + 1e-18 * np.eye(5)
        x = ad @ x + bd @ u(t_a).reshape(-1) + np.linalg.cholesky(qd) @ rng.normal(size=5)
        states[t_b] = x.copy()
    xs = np.array([states[tk] for tk in t])
    y = AMBIENT + xs[:, 2:4] + xs[:, 4:5]
    y = y + rng.normal(size=y.shape) * [NOISE["measurement.T1"], NOISE["measurement.T2"]]
    y[[40, 41, 300, 477]] = np.nan  # dropped frames
    y[500, 1] = np.nan
    settings = {
        "ambient_K": AMBIENT,
        "initial_T1_K": AMBIENT + X0[0],
        "initial_T2_K": AMBIENT + X0[1],
    }
    return greybox.Experiment("synthetic", t, y, u, settings=settings)


def physical_free():
    table = {p.path: p for p in SPEC.free_parameters(OPTIONS)}
    return [table[k] for k in TRUTH]


def cli_model(disturbances=STRUCTURE.disturbances, values=None, **structure):
    """The stochastic device `greybox fit` builds from the folder below (device defaults)."""
    st = greybox.NoiseStructure(STRUCTURE.process_groups, disturbances, **structure)
    return greybox.stochastic.stochastic_device(
        SPEC.model(OPTIONS), st, outputs=SPEC.outputs, inputs=SPEC.inputs, values=values
    )


@pytest.fixture(scope="module")
def data():
    # single-threaded BLAS: thousands of 12x12 products were far slower multithreaded on the
    # shared 2-core machine (as in tests/test_kalman.py)
    with threadpool_limits(1):
        return simulate_truth()


@pytest.fixture(scope="module")
def stochastic_fit(data):
    sd = cli_model()
    free = physical_free() + greybox.stochastic.noise_parameters(sd, UNITS)
    return greybox.fit(sd, [data], free, noise=greybox.ProcessNoise(sd.structure), n_starts=1)


def test_stochastic_fit_recovers_truth(stochastic_fit):
    res = stochastic_fit
    assert res.status == "converged", res.message
    z = res.z_scores(TRUTH | NOISE)
    print({k: round(v, 2) for k, v in z.items()})
    assert set(z) == set(TRUTH) | set(NOISE)
    assert all(abs(v) < 3.0 for v in z.values()), z
    for p in res.parameters:
        assert p.verdict == "identifiable", p
        assert p.ci95[0] < p.value < p.ci95[1]
    run = res.runs[0]
    p_values = [w.p_value for w in run.whiteness]
    print("Ljung-Box p (innovations):", p_values)
    assert all(p > 0.01 for p in p_values)
    # labelled horizons: one-step beats 10-step beats the free-run simulation (the walk)
    assert [h[0] for h in run.horizons] == [
        "simulation",
        "one-step prediction",
        "10-step prediction",
    ]
    for s, o, k in zip(
        run.simulation_fit_percent, run.one_step_fit_percent, run.k_step_fit_percent
    ):
        assert o > k > s, (o, k, s)


def deterministic_mean(p, e):
    """Free-run prediction of the readings (N, 2) by the numpy network, exact ZOH per step."""
    a, b = tclab_matrices(p)
    ends, h, levels = steps_of(e)
    big = np.zeros((h.size, 6, 6))
    big[:, :4, :4], big[:, :4, 4:] = a, b
    E = sla.expm(big * h[:, None, None])
    x, xs = X0.copy(), {0.0: X0.copy()}
    for k in range(h.size):
        x = E[k, :4, :4] @ x + E[k, :4, 4:] @ levels[k]
        xs[ends[k]] = x
    return AMBIENT + np.array([xs[tk][2:4] for tk in e.t_s])


def test_deterministic_fit_is_not_white(data):
    """Free-run least squares (the deterministic fit, scipy on the numpy network) on the same
    record: non-white residuals (the walk and the process noise land in them)."""
    ok = np.isfinite(data.y)
    names = list(TRUTH)

    def residuals(log_p):
        p = dict(zip(names, np.exp(log_p)))
        return (data.y - deterministic_mean(p, data))[ok]

    start = np.log([1.2 * TRUTH[k] for k in names])
    with threadpool_limits(1):
        sol = so.least_squares(residuals, start, x_scale=1.0, xtol=1e-10, ftol=1e-10)
        r = np.full(data.y.shape, np.nan)
        r[ok] = residuals(sol.x)
    assert sol.success
    p_values = [greybox.metrics.ljung_box(r[:, j], 20).p_value for j in range(2)]
    lag1 = [
        np.corrcoef(r[np.isfinite(r[:, j]), j][1:], r[np.isfinite(r[:, j]), j][:-1])[0, 1]
        for j in range(2)
    ]
    print("deterministic fit: Ljung-Box p", p_values, "lag-1 autocorrelation", lag1)
    print(
        "estimates / truth:",
        {k: round(float(np.exp(v)) / TRUTH[k], 3) for k, v in zip(names, sol.x)},
    )
    assert all(p < 1e-10 for p in p_values)
    assert all(c > 0.7 for c in lag1)


def test_ekf_equals_kalman_on_linear_device(data, stochastic_fit):
    vals = NOISE | {"process.heaters": 3e-3}
    # the exact filter through the fit's compiled diagnostics (same structure and record)
    kalman = greybox.stochastic.device_filter(cli_model(values=vals), data).log_likelihood
    ekf = greybox.stochastic.device_log_likelihood(cli_model(values=vals, filter="ekf"), data)
    assert abs(ekf - kalman) <= 1e-8 * abs(kalman)


def test_ekf_zero_noise_equals_deterministic_likelihood():
    """No process noise, known initial state: the EKF likelihood of the nonlinear (radiation)
    TCLab is the Gaussian likelihood of the simulation residuals (default sub-steps)."""
    dev = SPEC.model({"radiation": True})
    rng = np.random.default_rng(7)
    t = np.cumsum(rng.uniform(0.5, 1.5, 300))
    t -= t[0]
    u = greybox.PiecewiseConstant(
        np.array([0.0, 30.0, 120.0, 200.0]),
        np.array([[0, 0], [60, 20], [10, 80], [40, 40.0]]),
        t[-1] + 1.0,
    )
    settings = {"initial_T1_K": 297.0, "initial_T2_K": 296.5}
    z = greybox.simulate(
        greybox.parameters.set_values(dev, list(settings), list(settings.values())),
        u,
        t,
        rtol=1e-12,
        atol=1e-12,
    )
    sd = np.array([0.1, 0.2])
    y = z + rng.normal(size=z.shape) * sd
    y[[10, 150]] = np.nan
    e = greybox.Experiment("nl", t, y, u, settings=settings)
    r = (y - z) / sd
    ok = np.isfinite(r)
    ref = (
        -0.5 * np.sum(r[ok] ** 2)
        - np.sum(np.log(np.broadcast_to(sd, r.shape)[ok]))
        - 0.5 * ok.sum() * np.log(2 * np.pi)
    )
    m = greybox.stochastic.stochastic_device(
        dev,
        greybox.NoiseStructure(),
        outputs=SPEC.outputs,
        values={"measurement.T1": 0.1, "measurement.T2": 0.2},
    )
    assert m.ekf_substeps == 4  # the default for a nonlinear device
    ll = greybox.stochastic.device_log_likelihood(m, e)
    print("EKF", ll, "reference", ref, "relative", (ll - ref) / abs(ref))
    assert abs(ll - ref) <= 1e-7 * abs(ref)


def test_kalman_equals_dynamax_on_a_regular_grid():
    """On a regular grid with the input constant over each frame interval the continuous-
    discrete filter is a discrete-time LGSSM: greybox's likelihood equals dynamax's
    `lgssm_filter` given the discretised matrices (numpy Van Loan, written here)."""
    import jax
    import jax.numpy as jnp

    precision = jax.config.jax_default_matmul_precision
    dynamax = pytest.importorskip("dynamax.linear_gaussian_ssm")
    # importing dynamax (1.0.3, through tensorflow-probability) sets the global
    # jax_default_matmul_precision to "float32": a different jit cache key for every later
    # compilation in this process (and lower matmul precision where a backend honours it)
    jax.config.update("jax_default_matmul_precision", precision)

    rng = np.random.default_rng(11)
    n_frames, h = 200, 1.5
    t = h * np.arange(1, n_frames + 1)
    levels = rng.uniform(0.0, 40.0, (n_frames, 2))
    a, b = tclab_matrices(TRUTH)
    qc = np.diag([3e-3, 3e-3, 1e-4, 1e-4])
    c = np.array([[0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
    r = np.diag([0.08, 0.1]) ** 2
    x0, p0 = np.array([1.0, 0.5, 1.0, 0.5]), np.diag([0.2, 0.2, 0.05, 0.05])
    m = np.zeros((10, 10))
    m[:4, :4], m[:4, 4:8], m[4:8, 4:8], m[8:, 4:8] = -a, qc, a.T, b.T
    E = sla.expm(m * h)
    ad, bd = E[4:8, 4:8].T, E[8:, 4:8].T
    qd = ad @ E[:4, 4:8]
    qd = 0.5 * (qd + qd.T)
    x, y = rng.multivariate_normal(x0, p0), np.empty((n_frames, 2))
    for k in range(n_frames):
        x = ad @ x + bd @ levels[k] + rng.multivariate_normal(np.zeros(4), qd)
        y[k] = c @ x + rng.normal(size=2) * np.sqrt(np.diag(r))
    sde = greybox.stochastic.LinearGaussianSDE(a, b, qc, c, r, x0, p0)
    grid = greybox.stochastic.FilterGrid(t, t - h, levels, t0_s=0.0)
    ours = float(greybox.stochastic.log_likelihood(sde, grid, jnp.asarray(y)))
    # dynamax: p(z_1) is the state at the first frame (one step from t0); entry t of the
    # dynamics' time-varying input weights is used from frame t-1 to t
    params = dynamax.ParamsLGSSM(
        initial=dynamax.ParamsLGSSMInitial(
            mean=jnp.asarray(ad @ x0 + bd @ levels[0]), cov=jnp.asarray(ad @ p0 @ ad.T + qd)
        ),
        dynamics=dynamax.ParamsLGSSMDynamics(
            weights=jnp.asarray(ad),
            bias=jnp.zeros(4),
            input_weights=jnp.asarray(bd),
            cov=jnp.asarray(qd),
        ),
        emissions=dynamax.ParamsLGSSMEmissions(
            weights=jnp.asarray(c),
            bias=jnp.zeros(2),
            input_weights=jnp.zeros((2, 2)),
            cov=jnp.asarray(r),
        ),
    )
    # dynamax applies inputs[t] on the step into frame t: frame t's step holds levels[t]
    ref = float(dynamax.lgssm_filter(params, jnp.asarray(y), jnp.asarray(levels)).marginal_loglik)
    print("greybox", ours, "dynamax", ref)
    assert abs(ours - ref) <= 1e-8 * abs(ref)


# ---------------------------------------------------------------------------------------------
# The command: [fit] noise_model = "process" and greybox simulate on its params.json

TOML = """\
[experiment]
device = "tclab"

[model]
radiation = false
shared_sensor_lag = true

[fit]
noise_model = "process"
free = ["U_W_per_m2K", "Us_W_per_m2K", "alpha1_W_per_pct", "alpha2_W_per_pct", "tau1_s"]

[noise]
process = {{ heaters = [0, 1] }}
disturbances = [{disturbance}]

[[runs]]
name = "synthetic"
file = "run.csv"
role = "estimation"
waveform = {{ type = "logged" }}
settings = {{ ambient_K = 296.15, initial_T1_K = 297.15, initial_T2_K = 296.65 }}
"""


def write_folder(folder, data, disturbance='"ambient_random_walk_shared"'):
    folder.mkdir()
    (folder / "experiment.toml").write_text(TOML.format(disturbance=disturbance))
    u = data.inputs(data.t_s).reshape(data.n_frames, -1)
    lines = ["t_s,H1_pct,H2_pct,T1_C,T2_C"]
    for k in range(data.n_frames):
        temps = ["" if not np.isfinite(v) else f"{v - 273.15:.6f}" for v in data.y[k]]
        lines.append(",".join([f"{data.t_s[k]:.9f}", f"{u[k, 0]:g}", f"{u[k, 1]:g}", *temps]))
    (folder / "run.csv").write_text("\n".join(lines) + "\n")
    return folder


def test_cli_fit_and_simulate_process_noise(tmp_path, data, stochastic_fit, capsys):
    from greybox.cli import main

    folder = write_folder(tmp_path / "exp", data)
    out = tmp_path / "result"
    assert main(["fit", str(folder), "--out", str(out), "--quiet"]) == 0
    doc = json.loads((out / "params.json").read_text())
    assert doc["noise_model"]["kind"] == "process noise"
    assert doc["noise_model"]["likelihood"] == (
        "maximum likelihood, continuous-discrete (extended) Kalman filter, prediction-error form"
    )
    assert set(doc["noise_model"]["values"]) == set(NOISE)
    # the same likelihood maximum as the library fit on the same record (the CSV rounds
    # temperatures to 1e-6 C)
    by_path = {p["path"]: p for p in doc["parameters"]}
    for p in stochastic_fit.parameters:
        assert by_path[p.path]["value"] == pytest.approx(p.value, rel=1e-3)
        assert by_path[p.path]["ci95"][0] < by_path[p.path]["value"] < by_path[p.path]["ci95"][1]
    report = (out / "report.md").read_text()
    assert "prediction-error form" in report and "one-step prediction" in report
    assert "Ljung-Box" in report
    metrics = (out / "metrics.csv").read_text().splitlines()
    assert metrics[0] == "run,role,output,horizon,unit,n,fit_percent,rmse,mae,sae"
    horizons = {line.split(",")[3] for line in metrics[1:]}
    assert horizons == {"simulation", "one-step prediction", "10-step prediction"}
    assert doc["runs"]["synthetic"]["whiteness"]["T1"]["white"]
    assert "10-step prediction" in report
    assert doc["parameters"][5]["unit"] == "K^2/s"  # process.heaters: a real unit
    assert (out / "figures" / "fit_synthetic.png").is_file()
    assert (out / "figures" / "innovations_T1.png").is_file()
    assert json.loads((out / "validation_runs.json").read_text())["runs"] == {}
    printed = capsys.readouterr().out
    assert "K^2/s" in printed and "mK^2/s" not in printed and "state" not in printed

    sim = tmp_path / "sim"
    args = ["simulate", "--params", str(out / "params.json"), "--out", str(sim), "--dt-ms", "5000"]
    args += ["--waveform", "H1=pulse:H1_pct=30,period_s=400,duty=0.5,n=1"]
    args += ["--waveform", "H2=const:0"]
    assert main(args) == 0
    meta = json.loads((sim / "simulation.json").read_text())
    assert "process noise" in meta["band"]["kind"]
    table = np.genfromtxt(sim / "simulation.csv", delimiter=",", names=True)
    width = table["T1_hi95_C"] - table["T1_lo95_C"]
    # the band starts at the known initial state and widens with the process noise and the
    # ambient random walk: sd of the walk alone after t is sqrt(q t)
    assert width[0] < 0.05
    walk_sd_end = np.sqrt(NOISE["output_walk.shared"] * table["t_s"][-1])
    assert width[-1] > 2 * 1.96 * walk_sd_end * 0.7


@pytest.mark.parametrize(
    ("disturbance", "field"),
    [('"ambient_walk"', "noise.disturbances[0]"), ("3", "noise.disturbances")],
)
def test_cli_noise_table_errors(tmp_path, data, capsys, disturbance, field):
    from greybox.cli import main

    folder = write_folder(tmp_path / "exp", data, disturbance)
    assert main(["fit", str(folder), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert f"experiment.toml:14: {field}:" in err, err


def test_cli_noise_prior_on_an_unknown_parameter_is_refused(tmp_path, data, capsys):
    from greybox.cli import main

    folder = write_folder(tmp_path / "exp", data)
    toml = folder / "experiment.toml"
    line = 'disturbances = ["ambient_random_walk_shared"]'
    prior = 'priors = { "measurement.T9" = { median = 0.1, log_sd = 0.5 } }'
    toml.write_text(toml.read_text().replace(line, f"{line}\n{prior}"))
    assert main(["fit", str(folder), "--out", str(tmp_path / "r"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "measurement.T9" in err and "not a noise parameter" in err
    assert "measurement.T1" in err  # the message lists what there is
    assert not (tmp_path / "r").exists()


def test_covariance_hessian_equals_exact_second_derivatives(stochastic_fit, data):
    # the fit's observed information is central differences of the compiled gradient, probed
    # by the optimiser's own loop; the reference is forward-over-forward AD of the same
    # negative log-likelihood at the point the optimiser returns
    import jax
    import jax.numpy as jnp

    from greybox._estimate import likelihood as _likelihood

    res = stochastic_fit
    problem = _likelihood._build(res.model, [data], res.free)
    out = _likelihood._newton(problem, jnp.asarray(res.raw), 1)  # from the estimate: one step
    exact = np.asarray(jax.jit(jax.jacfwd(jax.jacfwd(problem.data_nll)))(out["raw"]))
    fd = np.asarray(out["hessian"]) - np.asarray(out["prior_hessian"])
    assert np.max(np.abs(fd - exact)) <= 1e-6 * np.max(np.abs(exact))


def test_runs_of_similar_lengths_share_one_compiled_filter():
    """A fit's diagnostics (`device_filter`: one-step, k-step and simulation predictions)
    run each record padded to a bucketed length, so two records of 195 and 205 frames
    compile the filter once; the padding changes nothing: each record's one-step
    innovations and log-likelihood are the independent numpy filter's
    (tests/ou_reference.py), to rounding."""
    from tests import ou_device as od
    from tests import ou_reference as ou
    from tests.helpers import backend_compiles

    model = od.model(ou.TRUTH)
    for n, seed in ((195, 3), (205, 4)):
        y = ou.simulate(ou.TRUTH, n, seed)
        with backend_compiles() as compiled:
            run = greybox.stochastic.device_filter(model, od.experiment(y))
        v, _ = ou.innovations(ou.TRUTH, y)
        np.testing.assert_allclose(run.innovation[1:, 0], v, rtol=1e-9, atol=1e-12)
        assert run.y_one_step.shape == (n, 1) and run.y_k_step.shape == (n, 1)
        sd = ou.TRUTH["sd"]  # the first reading's own term: the initial state is known
        first = -0.5 * ((y[0] - ou.T0) ** 2 / sd**2 + np.log(2 * np.pi * sd**2))
        assert run.log_likelihood == pytest.approx(ou.loglik(ou.TRUTH, y) + first, rel=1e-12)
        filters = [f for f in compiled if "_filter_arrays" in f]
        assert len(filters) == (1 if n == 195 else 0), compiled


def test_runs_that_start_at_different_times_share_one_compiled_filter():
    """The same record started at 300, 600 and 900 s (frames, inputs and `t_start_s`
    shifted together): the filter is time-invariant, so each run's innovations are the
    numpy reference's, and the start time is an argument of the compiled filter, not a
    constant of it: after the first, no run compiles it again (it did once per start
    time while the start was passed as a Python float)."""
    from tests import ou_device as od
    from tests import ou_reference as ou
    from tests.helpers import backend_compiles

    model = od.model(ou.TRUTH)
    y = ou.simulate(ou.TRUTH, 120, 6)
    v, _ = ou.innovations(ou.TRUTH, y)
    t = ou.frames(y.size)
    base = od.inputs(float(t[-1]) + ou.DT)
    for shift in (300.0, 600.0, 900.0):
        u = greybox.PiecewiseConstant(
            np.asarray(base.times_s) + shift, base.values, float(t[-1]) + ou.DT + shift
        )
        run = greybox.Experiment("shifted", t + shift, y[:, None], u, t_start_s=shift)
        with backend_compiles() as compiled:
            out = greybox.stochastic.device_filter(model, run)
        np.testing.assert_allclose(out.innovation[1:, 0], v, rtol=1e-9, atol=1e-12)
        if shift > 300.0:
            assert not [f for f in compiled if "_filter_arrays" in f], compiled


def test_runs_of_different_lengths_stack_into_one_likelihood():
    """A fit's runs are padded to the longest, rounded up to a bucketed length, and mapped
    over by one compiled filter (`stacked_records`): the objective's -log L of two records
    of 150 and 200 frames is the sum of the independent numpy filter's over each
    (tests/ou_reference.py), whether the records are padded to 200 frames or to 208."""
    import jax.numpy as jnp

    from greybox._estimate import likelihood as lik
    from tests import ou_device as od
    from tests import ou_reference as ou

    ys = [ou.simulate(ou.TRUTH, n, seed) for n, seed in ((150, 7), (200, 8))]
    runs = [od.experiment(y, name=f"r{i}") for i, y in enumerate(ys)]
    noise = greybox.ProcessNoise(od.STRUCTURE, start_noise=False)
    expected = sum(ou.loglik(ou.TRUTH, y) for y in ys)
    truth = [ou.TRUTH[name] for name in od.NAMES]
    for pad, frames in ((False, 200), (True, 208)):
        su = lik.setup(od.model(ou.TRUTH), runs, od.FREE, noise, pad_records=pad)
        assert np.shape(su.obj.y) == (2, frames, 1)  # stacked, the shorter run padded
        raw = jnp.asarray([float(p.to_raw(v)) for p, v in zip(su.obj.flat, truth)])
        assert -float(su.obj.data_nll(raw)) == pytest.approx(expected, rel=1e-12)
