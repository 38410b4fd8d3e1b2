"""Experiment design (greybox.design._design): the information it optimises is the fit's, the
tracking waveform meets its target within its constraints, and impossible requests raise."""

import tomllib

import jax.numpy as jnp
import numpy as np
import pytest

import greybox
from greybox.design import _design as D
from greybox.io import experiment_toml, waveform_from_description

INTEREST = ("absorptance", "thermal.tau_s")
NOISE_M = 0.05e-6


@pytest.fixture(scope="module")
def chevron():
    spec = greybox.get_device("chevron_laser")
    model = greybox.devices.with_camera(spec.model(), exposure_s=0.010)
    return spec, model, tuple(spec.free_parameters())


@pytest.fixture(scope="module")
def small_constraints():
    return D.LabConstraints(
        power_max_W=0.03,
        run_duration_s=2.0,
        n_runs=2,
        average_power_max_W=0.008,
        min_pulse_s=0.02,
    )


def test_fisher_information_is_the_fits_gauss_newton_information(chevron, small_constraints):
    """inv(sum of per-run marginal information) == the fit's covariance of the shared raw
    parameters, from noise-free data at the true parameters (two independent code paths)."""
    spec, model, free = chevron
    c = small_constraints
    waves = [
        greybox.PulseTrain(0.02, 0.2, 0.3, 8, delay_s=0.3, tail_s=0.1).to_piecewise(),
        greybox.PulseTrain(0.03, 0.5, 0.2, 3, delay_s=0.3, tail_s=0.2).to_piecewise(),
    ]
    t = c.frame_times()
    problem = D.design_problem(model, free, INTEREST, NOISE_M)
    info = D.run_information(problem, waves, t)  # (1, R, ns, ns)
    assert info.shape == (1, 2, 2, 2)
    exps = [
        greybox.Experiment(f"r{i}", t, np.asarray(greybox.simulate(model, w, t)), w)
        for i, w in enumerate(waves)
    ]
    res = greybox.fit(model, exps, free, loss="l2", sigma=NOISE_M)
    # the Gauss-Newton covariance (a fit may headline a sandwich covariance instead, which is
    # zero for noise-free residuals)
    cov_fit = np.asarray(getattr(res, "covariance_gauss_newton_raw", res.covariance_raw))[:2, :2]
    cov_design = np.linalg.inv(info[0].sum(axis=0))
    np.testing.assert_allclose(cov_design, cov_fit, rtol=1e-6)
    # and the standard errors in SI the design reports are the fit's
    se = D.design_standard_errors(problem, info[0].sum(axis=0))
    for k, p in enumerate(free[:2]):
        se_fit = abs(p.value_derivative(res.raw[k])) * np.sqrt(cov_fit[k, k])
        assert se[p.path] == pytest.approx(se_fit, rel=1e-6)


def test_pulse_train_design_beats_a_plain_union_and_writes_a_loadable_toml(
    chevron, small_constraints, tmp_path
):
    spec, model, free = chevron
    c = small_constraints
    problem = D.design_problem(model, free, INTEREST, NOISE_M)
    design = D.design_experiment(problem, c, n_periods=6, duties=[0.1, 0.2, 0.3, 0.5])
    assert len(design.runs) == c.n_runs
    for r in design.runs:
        assert r.peak_W <= c.power_max_W + 1e-12
        assert r.energy_J / c.run_duration_s <= c.average_power_max_W + 1e-12
        assert r.waveform.duration_s == pytest.approx(c.run_duration_s)
    # a 50 % duty train at the same average power (the thesis habit) is worse
    plain = D.DesignedRun(
        "plain",
        greybox.PulseTrain(0.016, 0.4, 0.5, 4, delay_s=0.3, tail_s=0.1).to_piecewise(),
        {},
        "pulse_train",
    )
    base = D.evaluate_design(problem, [plain] * c.n_runs, c)
    assert design.score > base.score
    rows = D.comparison_table(problem, design, base)
    assert all(r["ratio"] > 1 for r in rows)
    # the experiment.toml parses and its waveforms are the designed ones
    text = experiment_toml(
        design,
        device="chevron_laser",
        free=free,
        m_per_px=0.645e-6,
        default_free=[p.path for p in free],
    )
    doc = tomllib.loads(text)
    assert doc["experiment"]["device"] == "chevron_laser"
    assert doc["camera"]["exposure_ms"] == pytest.approx(10.0)
    for run, r in zip(doc["runs"], design.runs):
        wave, _ = waveform_from_description(
            run["waveform"], greybox.devices.LASER_POWER, lambda m, *_: ValueError(m)
        )
        tt = np.linspace(0, c.run_duration_s, 2001)[:-1]
        np.testing.assert_allclose(wave(tt), r.waveform(tt), atol=1e-12)
    # a multilevel ("steps") run writes too, and the folder loads once the runs are recorded
    steps = greybox.PiecewiseConstant(
        np.array([0.0, 0.3, 0.5, 1.1]), np.array([0, 0.02, 0, 0.01]), 2.0
    )
    mixed = D.evaluate_design(
        problem,
        [
            design.runs[0],
            D.DesignedRun(
                "ml",
                steps,
                {
                    "type": "steps",
                    "times_s": [0.0, 0.3, 0.5, 1.1],
                    "power_mW": [0, 20, 0, 10],
                    "end_s": 2.0,
                },
                "multilevel",
            ),
        ],
        c,
    )
    (tmp_path / "experiment.toml").write_text(
        experiment_toml(mixed, device="chevron_laser", free=free, m_per_px=0.645e-6)
    )
    t = c.frame_times()
    for r in mixed.runs:
        y_px = np.asarray(greybox.simulate(model, r.waveform, t)) / 0.645e-6 + 300.0
        lines = ["t_s,y_px"] + [f"{a:.6f},{b:.4f}" for a, b in zip(t, y_px)]
        (tmp_path / f"{r.name}.csv").write_text("\n".join(lines) + "\n")
    loaded = greybox.io.load_experiment_set(tmp_path)
    assert [e.name for e in loaded.estimation] == [r.name for r in mixed.runs]
    assert {p.path for p in loaded.free} == {p.path for p in free}
    for e, r in zip(loaded.estimation, mixed.runs):
        np.testing.assert_allclose(e.inputs(t), r.waveform(t), atol=1e-12)


def test_inverse_design_meets_target_within_constraints(chevron):
    """A step to 1 um, settled within 60 ms (tau = 40 ms: needs overdrive), held to 2 %."""
    spec, model, free = chevron
    p_max, cap, hold = 0.03, 0.015, 0.005
    tr = D.track_target(
        model,
        stroke_m=1e-6,
        step_time_s=0.1,
        settling_s=0.06,
        duration_s=0.6,
        power_max_W=p_max,
        average_power_max_W=cap,
        hold_s=hold,
        tolerance=0.02,
    )
    assert tr.met
    # independent check with the public simulator on the written waveform (no exposure)
    m0 = greybox.devices.with_camera(model, exposure_s=0.0)
    y = greybox.simulate(m0, tr.waveform, tr.t_s)
    err = np.abs(y - tr.target)[tr.settled]
    assert err.max() <= 0.02 * 1e-6
    # before the step the shuttle rests; the response overshoots by no more than the tolerance
    assert np.max(y) <= 1e-6 * 1.02
    w = tr.waveform
    assert np.all(w.values >= 0) and np.all(w.values <= p_max + 1e-12)
    assert w.mean() * w.duration_s / 0.6 <= cap + 1e-12
    assert np.min(np.diff(np.append(w.times_s, w.end_s))) >= hold - 1e-9  # min pulse width
    # with a posterior the response has a band
    res_raw = np.array(
        [float(p.to_raw(greybox.parameters.get_value(model, p.path))) for p in free[:2]]
    )
    cov = np.diag([0.05, 0.02]) ** 2
    tr2 = D.track_target(
        model,
        stroke_m=1e-6,
        step_time_s=0.1,
        settling_s=0.06,
        duration_s=0.6,
        power_max_W=p_max,
        n_iter=5,
        free=free[:2],
        raw=res_raw,
        covariance_raw=cov,
    )
    assert tr2.band is not None and np.all(tr2.band.upper[-1] > tr2.band.y[-1])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(average_power_max_W=0.0), "average_power_max_W"),
        (dict(run_duration_s=0.3), "run_duration_s"),
        (dict(exposure_s=0.05), "exposure_s"),
        (dict(power_max_W=-1.0), "power_max_W"),
        (dict(power_min_W=0.02, average_power_max_W=1e-6), "average_power_max_W"),
    ],
)
def test_infeasible_constraints_raise(kwargs, field):
    base = dict(power_max_W=0.03, run_duration_s=2.0, n_runs=1)
    with pytest.raises(ValueError, match=field):
        D.LabConstraints(**{**base, **kwargs})


def test_unreachable_targets_raise(chevron):
    _, model, _ = chevron
    common = dict(step_time_s=0.1, duration_s=0.6, power_max_W=0.03)
    with pytest.raises(ValueError, match="stroke_m"):
        D.track_target(model, stroke_m=50e-6, settling_s=0.1, **common)
    with pytest.raises(ValueError, match="settling_s"):
        D.track_target(model, stroke_m=1.5e-6, settling_s=0.005, **common)
    with pytest.raises(ValueError, match="average_power_max_W"):
        D.track_target(model, stroke_m=1e-6, settling_s=0.1, average_power_max_W=1e-3, **common)


def test_unidentifiable_interest_raises(chevron, small_constraints):
    spec, model, free = chevron
    with pytest.raises(ValueError, match="interest"):
        D.design_problem(model, free, ["spot.waist_m"], NOISE_M)
    # absorptance and thermal resistance enter only as a product: no waveform separates them
    both = (
        free[0],
        greybox.FreeParameter("thermal.resistance_K_per_W", unit="K/W", lower=100.0, upper=1e5),
        free[1],
        free[2],
    )
    problem = D.design_problem(model, both, ["absorptance", "thermal.resistance_K_per_W"], NOISE_M)
    with pytest.raises(ValueError, match="interest: no pulse_train design"):
        D.design_experiment(problem, small_constraints, n_periods=3, duties=[0.5])


def test_projection_respects_box_and_average():
    rng = np.random.default_rng(0)
    x = rng.normal(0.5, 1.0, (3, 40))
    y = D.project_levels(x, 0.0, 1.0, 0.3)
    assert np.all(y >= 0) and np.all(y <= 1)
    assert np.all(y.mean(axis=1) <= 0.3 + 1e-9)
    # it is the Euclidean projection: no feasible point is closer (random feasible probes)
    for _ in range(200):
        z = D.project_levels(y + rng.normal(0, 0.05, y.shape), 0.0, 1.0, 0.3)
        assert np.all(np.linalg.norm(x - y, axis=1) <= np.linalg.norm(x - z, axis=1) + 1e-9)
    assert float(D.log_criterion(jnp.eye(2) * 4.0, "D")) == pytest.approx(np.log(4.0))


def test_multilevel_criterion_of_a_second_device_is_its_own_and_compiles_nothing(
    chevron, small_constraints, monkeypatch
):
    """The multilevel refinement's criterion and gradient are one compiled function per
    structure (the device's values and the parameters' numbers are its inputs): a second
    device's design compiles nothing for it, and the criterion it climbs is that device's
    own. Truth: at the levels it starts from, the criterion equals the log-determinant of
    the information `run_information` (another compiled path) gives the same runs."""
    from tests.helpers import backend_compiles

    spec, model, free = chevron
    c = small_constraints
    climbed = []
    adam = D.projected_adam

    def recorded(value_and_grad, x, *args, **kwargs):
        climbed.append((value_and_grad, np.array(x)))
        return adam(value_and_grad, x, *args, **kwargs)

    monkeypatch.setattr(D, "projected_adam", recorded)
    problems = []
    for absorptance, tau in ((0.6, 0.045), (0.7, 0.03)):
        m = greybox.parameters.set_values(model, list(INTEREST), [absorptance, tau])
        problems.append(D.design_problem(m, free, INTEREST, NOISE_M))
    D.design_experiment(problems[0], c, family="multilevel", n_periods=4, n_iter=2)
    with backend_compiles() as names:
        D.design_experiment(problems[1], c, family="multilevel", n_periods=4, n_iter=2)
    # (the refinement compiled its criterion at every design before; the designed runs'
    # information, `_batch_information`, compiles where their schedule is of another length)
    assert [n for n in names if "_batch_information" not in n] == []
    (value_and_grad, x0) = climbed[-1]
    value, grad = value_and_grad(x0)
    assert np.all(np.isfinite(np.asarray(grad)))
    _, times = D._hold_grid(c, None)
    waves = [
        greybox.PiecewiseConstant(
            np.concatenate([[0.0], times]), np.concatenate([[0.0], row]), c.run_duration_s
        )
        for row in x0
    ]
    info = D.run_information(problems[1], waves, c.frame_times())[0].sum(axis=0)
    expected = D.log_criterion(jnp.asarray(info + problems[1].prior_information), "D")
    assert float(value) == pytest.approx(float(expected), rel=1e-9)
    other = D.run_information(problems[0], waves, c.frame_times())[0].sum(axis=0)
    assert float(value) != pytest.approx(
        float(D.log_criterion(jnp.asarray(other + problems[0].prior_information), "D")), rel=1e-3
    )
