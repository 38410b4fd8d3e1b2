"""Residual analysis: is what a fit leaves over white noise?

Truths: the textbook Ljung-Box statistic; the chi-square false-alarm rate on white noise
with dropped frames and missing timestamps; the long-run variance of an AR(1) series (for the
Newey-West meat); and, on fits, an independent two-node thermal chevron simulator written
here in numpy (exact exponentials of a 3-state linear system, exposure average by
Gauss-Legendre on each constant-input piece, the same static stroke map as
models/chevron_laser.py). The one-node model fitted to its data leaves residuals the test
calls not white (p < 1e-6); fitted to well-specified data it calls them white. With the
noise known, the misfit shows as estimated / known noise well above 1.
"""

import dataclasses

import numpy as np
import pytest
from scipy.special import erf

import greybox
from greybox._estimate.fit import fit
from greybox._estimate.residuals import (
    LjungBox,
    analyse,
    analyse_run,
    ljung_box,
    portmanteau,
)
from greybox._estimate.sandwich import hac_meat, model_error_residuals
from greybox._model.data import Experiment
from greybox._model.parameters import set_values
from greybox._model.waveforms import PiecewiseConstant
from greybox.report._markdown import fit_report
from tests.helpers import chevron_runs

CHEVRON = greybox.get_device("chevron_laser")
default_model = CHEVRON.model


def default_free_parameters():
    return list(CHEVRON.free_parameters())


RUNS = ((10, 0.3), (30, 0.6))  # (mW, period s): the shapes tests/test_fit.py also compiles
DURATION_S = 4.0
NOISE_M = 0.05e-6

# ------------------------------------------------------------------ pure numpy machinery


def test_ljung_box_matches_the_textbook_form_without_gaps():
    rng = np.random.default_rng(0)
    n, m = 300, 20
    e = rng.normal(size=n)
    r = analyse_run(
        "a", np.arange(n) / 30.0, e[:, None], np.ones((n, 1), bool), None, m, permutations=0
    )
    x = e - e.mean()
    k = np.arange(1, m + 1)
    r_biased = np.array([x[j:] @ x[: n - j] for j in k]) / (x @ x)
    # pairwise estimator = biased * N / (N - k), plus the mean-removal correction 1/(N - 1)
    np.testing.assert_allclose(
        r.autocorrelation[0, 1:], r_biased * n / (n - k) + 1 / (n - 1), rtol=1e-12
    )
    q_textbook = n * (n + 2) * np.sum((r_biased + (n - k) / (n * (n - 1))) ** 2 / (n - k))
    assert r.q[0] == pytest.approx(q_textbook, rel=1e-12)
    from scipy.stats import chi2

    assert r.p_value[0] == pytest.approx(chi2.sf(q_textbook, m), rel=1e-10)


def test_false_alarm_rate_with_dropped_frames_and_missing_timestamps():
    """White noise, three runs of ~170 frames, 10 % NaN frames, 5 % timestamps missing,
    2 ms jitter at 30 fps: the pooled test rejects at about its nominal rate."""
    rng = np.random.default_rng(1)
    reps, p = 400, []
    for _ in range(reps):
        runs = []
        for i in range(3):
            t = np.arange(180) / 30.0 + rng.normal(0, 2e-3, 180)
            keep = rng.uniform(size=180) > 0.05  # timestamps that never arrived
            t = np.sort(t[keep])
            e = rng.normal(size=t.size)
            valid = rng.uniform(size=t.size) > 0.10
            runs.append((f"r{i}", t, np.where(valid, e, np.nan)[:, None], valid[:, None], None))
        p.append(analyse(runs, permutations=199, seed=len(p)).p_value[0])
    p = np.asarray(p)
    # binomial 99 % intervals around the nominal rates (400 replicates): the shuffled null
    # is exact for white noise, gaps and pooling included
    assert (p < 0.01).mean() <= 0.025
    assert 0.025 <= (p < 0.05).mean() <= 0.08


def test_gaps_keep_lags_in_frames():
    """An AR(1) series (r(1) = 0.6 per frame) with 40 % of the timestamps missing, NaN frames
    and jitter: the slot grid puts every frame at its true lag, so r(1), r(2) come out as 0.6
    and 0.36; counting lags by position in the record would give (1 - m) rho / (1 - m rho)."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(2)
    n, rho, missing = 20000, 0.6, 0.4
    e = lfilter([1.0], [1.0, -rho], rng.normal(size=n))
    t = np.arange(n) / 30.0 + rng.normal(0, 3e-3, n)
    keep = rng.uniform(size=n) > missing
    valid = rng.uniform(size=keep.sum()) > 0.1
    r = analyse_run("a", t[keep], e[keep][:, None], valid[:, None], None, 5, permutations=0)
    np.testing.assert_allclose(r.autocorrelation[0, 1:3], [rho, rho**2], atol=0.03)
    by_position = analyse_run(
        "b", np.arange(keep.sum()) / 30.0, e[keep][:, None], valid[:, None], None, 5, permutations=0
    )
    ignored = (1 - missing) * rho / (1 - missing * rho)  # 0.47
    assert by_position.autocorrelation[0, 1] == pytest.approx(ignored, abs=0.03)


def test_hac_meat_matches_the_long_run_variance_of_ar1_and_var1_series():
    """Closed forms: an AR(1) series x_t = rho x_(t-1) + e_t (unit innovations) has long-run
    variance 1 / (1 - rho)^2; a VAR(1) g_t = A g_(t-1) + e_t, (I - A)^-1 S (I - A)^-T. The
    prewhitened meat (Andrews-Monahan) recovers both on average over replicates; plain
    Newey-West with the same plug-in bandwidth falls short on the AR(1) (its known bias)."""
    from scipy.signal import lfilter

    rng = np.random.default_rng(3)
    n, rho, reps = 2000, 0.7, 20
    t = np.arange(n) / 30.0
    long_run = 1.0 / (1 - rho) ** 2
    pw, nw = [], []
    for _ in range(reps):
        g = lfilter([1.0], [1.0, -rho], rng.normal(size=n))[:, None]
        h = hac_meat([(t[: n // 2], g[: n // 2]), (t[n // 2 :], g[n // 2 :])])  # two runs
        pw.append(h.meat[0, 0] / n)
        nw.append(hac_meat([(t, g)], prewhiten=False).meat[0, 0] / n)
        assert h.var1[0, 0] == pytest.approx(rho, abs=0.05)
    assert np.mean(pw) == pytest.approx(long_run, rel=0.05)
    assert np.mean(nw) < 0.95 * long_run

    a = np.array([[0.6, 0.2], [-0.1, 0.4]])
    chol = np.array([[1.0, 0.0], [0.5, 0.8]])
    b = np.linalg.inv(np.eye(2) - a)
    truth = b @ chol @ chol.T @ b.T
    est = []
    for _ in range(reps):
        e = rng.normal(size=(n, 2)) @ chol.T
        g = np.zeros((n, 2))
        for k in range(1, n):
            g[k] = a @ g[k - 1] + e[k]
        est.append(hac_meat([(t, g)]).meat / n)
    np.testing.assert_allclose(np.mean(est, axis=0), truth, rtol=0.08, atol=0.05 * truth.max())

    white = rng.normal(size=(n, 1))
    hw = hac_meat([(t, white)], n_readings=n, n_fitted=n // 10)
    assert hw.bandwidth <= 3 and hw.dof_factor == pytest.approx(10 / 9)
    assert hw.meat[0, 0] == pytest.approx(n * 10 / 9, rel=0.1)


def test_model_error_residuals_remove_what_the_input_explains():
    """Residuals = a known FIR response of the input (a deterministic misfit) + white noise,
    with dropped frames and missing timestamps: the model-error regression recovers the FIR
    (least squares on the lagged input, checked against numpy's on the same columns), what it
    leaves is the noise less its projection, and a HAC meat of misfit-only scores is ~0."""
    rng = np.random.default_rng(4)
    n, k = 600, 6
    t_all = np.arange(n) / 30.0
    u_all = (np.sin(2 * np.pi * t_all / 0.7) > 0).astype(float) * 0.02 + rng.normal(0, 0.005, n)

    def u_of_t(t):  # the input as a function of time (levels held for a frame)
        return u_all[np.clip(np.rint(np.asarray(t) * 30.0).astype(int), 0, n - 1)][:, None]

    fir = np.array([0.0, 3.0, 2.0, 1.0, 0.5, 0.2])
    misfit_all = np.convolve(np.concatenate([np.full(k, u_all[0]), u_all]), fir)[k : k + n]
    keep = rng.uniform(size=n) > 0.05  # timestamps that never arrived
    t, misfit = t_all[keep], misfit_all[keep]
    noise = rng.normal(0, 0.01, t.size)
    valid = rng.uniform(size=t.size) > 0.05
    y = (misfit + noise)[:, None]
    cleaned, fitted = model_error_residuals(t, y, valid[:, None], u_of_t, k)
    assert fitted == k + 1
    # the same regression by hand on the lagged input (first level before the start)
    padded = np.concatenate([np.full(k, u_all[0]), u_all])
    lagged = np.column_stack([padded[k - j : k - j + n] for j in range(k)])
    x = np.column_stack([np.ones(t.size), lagged[keep]])[valid]
    beta = np.linalg.lstsq(x, y[valid, 0], rcond=None)[0]
    np.testing.assert_allclose(cleaned[valid, 0], y[valid, 0] - x @ beta, atol=1e-10)
    np.testing.assert_allclose(beta[1:], fir, atol=0.15)
    assert np.all(cleaned[~valid] == 0.0)
    assert np.std(cleaned[valid]) == pytest.approx(0.01, rel=0.1)  # only the noise is left
    only, _ = model_error_residuals(t, misfit[:, None], valid[:, None], u_of_t, k)
    assert np.max(np.abs(only)) < 1e-9 * np.max(np.abs(misfit))
    # levels at the frames instead of a function: the same without missing timestamps
    full, _ = model_error_residuals(
        t_all, misfit_all[:, None], np.ones((n, 1), bool), u_all[:, None], k
    )
    assert np.max(np.abs(full)) < 1e-9 * np.max(np.abs(misfit_all))


def test_one_portmanteau_core():
    """`greybox._estimate.stochastic_fit.ljung_box` is the core's; the core's textbook
    Ljung-Box equals `analyse_run`'s statistic on a gap-free series without the mean-removal
    correction."""
    import greybox._estimate.stochastic_fit as stochastic

    assert stochastic.ljung_box is ljung_box and stochastic.LjungBox is LjungBox
    rng = np.random.default_rng(5)
    x = rng.normal(size=300)
    lb = ljung_box(x, 12)
    xc = x - x.mean()
    k = np.arange(1, 13)
    r = np.array([xc[j:] @ xc[:-j] for j in k]) / (xc @ xc)
    assert lb.statistic == pytest.approx(300 * 302 * np.sum(r**2 / (300 - k)), rel=1e-12)
    assert portmanteau(r, 1.0 / 300) == pytest.approx(300 * np.sum(r**2), rel=1e-12)


# ------------------------------------------------- an independent two-node chevron in numpy

L_M, ANGLE, CTE = 3.5e-3, np.deg2rad(2.0), 2.6e-6
WAIST_M, PAD_M = 150e-6, 200e-6
# pad node -> beam node -> elongation lag: time constants 4, 21 and 79 ms
C1, C2, G12, G1, G2, LAG_S = 1.0e-5, 2.0e-5, 2e-4, 2e-4, 2e-4, 0.004
ABSORPTANCE = 0.25


def _stroke_m(lagged_rise_K):
    """Beam elongation through the rigid-link chevron onto the shuttle (m)."""
    dl = CTE * L_M * lagged_rise_K
    ls = L_M * np.sin(ANGLE)
    growth = 2 * L_M * dl + dl**2
    return growth / (np.sqrt(ls**2 + growth) + ls)


def two_node_readings(times_s, levels_W, end_s, t_frames, exposure_s=0.010):
    """Exposure-averaged shuttle displacement at `t_frames` for a piecewise-constant laser."""
    a = np.array(
        [
            [-(G12 + G1) / C1, G12 / C1, 0.0],
            [G12 / C2, -(G12 + G2) / C2, 0.0],
            [0.0, 1.0 / LAG_S, -1.0 / LAG_S],
        ]
    )
    b = np.array([1.0 / C1, 0.0, 0.0])
    lam, vec = np.linalg.eig(a)
    lam, vec = lam.real, vec.real
    inv = np.linalg.inv(vec)
    fraction = erf(np.sqrt(2) / WAIST_M * PAD_M / 2) ** 2  # centred Gaussian on a square pad

    def steady(q):
        return -np.linalg.solve(a, b * q)

    breaks = np.append(times_s, end_s + 10.0)
    state = [np.zeros(3)]
    for k in range(len(times_s)):  # state at each breakpoint, exactly
        q = ABSORPTANCE * fraction * levels_W[k]
        xs = steady(q)
        dt = breaks[k + 1] - breaks[k]
        state.append(xs + vec @ (np.exp(lam * dt) * (inv @ (state[-1] - xs))))

    def lagged_rise(t):
        k = np.searchsorted(times_s, t, side="right") - 1
        if k < 0:
            return 0.0
        xs = steady(ABSORPTANCE * fraction * levels_W[k])
        x = xs + vec @ (np.exp(lam * (t - times_s[k])) * (inv @ (state[k] - xs)))
        return x[2]

    nodes, weights = np.polynomial.legendre.leggauss(6)
    out = []
    for tf in t_frames:
        lo = tf - exposure_s
        cuts = np.concatenate([[lo], times_s[(times_s > lo) & (times_s < tf)], [tf]])
        total = 0.0
        for u, v in zip(cuts[:-1], cuts[1:]):
            ts = (u + v) / 2 + (v - u) / 2 * nodes
            total += (
                (v - u) / 2 * np.sum(weights * _stroke_m(np.array([lagged_rise(x) for x in ts])))
            )
        out.append(total / exposure_s)
    return np.asarray(out)


def two_node_runs(seed: int, *, known_noise: bool = False):
    """Pulse runs of the two-node chevron filmed at 30 fps (2 ms jitter, 5 % dropped frames,
    0.05 um noise), as `Experiment`s; with `known_noise` each carries its per-frame sigma."""
    rng = np.random.default_rng(seed)
    exps = []
    for i, (p_mw, period) in enumerate(RUNS):
        n_pulses = int(np.ceil(DURATION_S / period))
        rises = np.arange(n_pulses) * period
        times = np.column_stack([rises, rises + period / 2]).reshape(-1)
        levels = np.tile([p_mw * 1e-3, 0.0], n_pulses)
        end = n_pulses * period
        t = np.sort((np.arange(int(end * 30)) + 0.5) / 30 + rng.normal(0, 2e-3, int(end * 30)))
        t = t[(t > 0.011) & (t < end)]
        y = two_node_readings(times, levels, end, t) + rng.normal(0, NOISE_M, t.size)
        y[rng.uniform(size=t.size) < 0.05] = np.nan
        exps.append(
            Experiment(
                f"run{i + 1}",
                t,
                y,
                PiecewiseConstant(times, levels, end),
                sigma=np.full(t.size, NOISE_M) if known_noise else None,
            )
        )
    return exps


def start_model():
    return set_values(default_model(), ["absorptance", "thermal.tau_s"], [0.5, 0.05])


@pytest.fixture(scope="module")
def misspecified():
    return fit(start_model(), two_node_runs(11), default_free_parameters())


@pytest.fixture(scope="module")
def well_specified():
    truth = set_values(default_model(), ["absorptance", "thermal.tau_s"], [0.62, 0.045])
    exps, _ = chevron_runs(truth, runs=RUNS, duration_s=DURATION_S, seed=12)
    return exps, fit(start_model(), exps, default_free_parameters())


def test_one_node_fit_of_two_node_data_is_not_white(misspecified, tmp_path):
    r = misspecified
    assert r.status == "converged", r.message  # the optimiser is content ...
    a = r.residuals
    assert a.p_value[0] < 1e-6  # ... but the residuals say the model misses dynamics
    assert not a.all_white and a.verdict.startswith("residuals not white")
    assert 1 in a.lags_outside[0]  # the misfit is slow: neighbouring frames agree
    # sandwich errors are the headline. Here the noise is white on a deterministic misfit:
    # the Gauss-Newton scale absorbs the misfit and is too wide (benchmarks/whiteness.py,
    # 400 replicates: se 1.6x the estimates' spread), while the HAC meat, with the misfit the
    # inputs explain taken out, sees the noise (1.2x): the sandwich is the narrower here
    tau = r.estimate("thermal.tau_s")
    assert r.se_method == "hac" and tau.se == tau.se_hac
    assert 0.5 * tau.se_gauss_newton < tau.se_hac < 0.95 * tau.se_gauss_newton
    text = fit_report(r, title="two-node data", device_name="chevron_laser")
    head = text.split("## ")[0]
    assert "residuals not white" in head and "Fit status: converged" in head
    from greybox.report._plots import residual_correlation_figure

    residual_correlation_figure(tmp_path / "resid.png", a)
    assert (tmp_path / "resid.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")


def test_well_specified_fit_is_white(well_specified):
    _, r = well_specified
    assert r.status == "converged", r.message
    assert r.residuals.all_white and r.residuals.p_value[0] > 0.01
    assert r.residuals.verdict.startswith("residuals consistent with white noise")
    assert r.se_method == "gauss-newton"
    tau = r.estimate("thermal.tau_s")
    assert tau.se == tau.se_gauss_newton
    assert tau.se_hac == pytest.approx(tau.se_gauss_newton, rel=0.3)  # both estimate one thing


def test_known_noise_shows_the_misfit_as_a_ratio(well_specified):
    bad = fit(start_model(), two_node_runs(11, known_noise=True), default_free_parameters())
    assert bad.sigma_source == "per-frame"
    np.testing.assert_allclose(bad.sigma, [NOISE_M])  # not re-estimated
    gof = bad.goodness_of_fit
    assert gof.ratio[0] > 1.3 and gof.p_value < 1e-6
    # the ceiling comes from the known noise, and the misfit run falls short of it
    e = bad.experiments[1]
    assert bad.noise_ceiling[e.name][0] == pytest.approx(
        100 * (1 - NOISE_M / np.nanstd(e.y[:, 0])), abs=1e-9
    )
    assert bad.fit_percent[e.name][0] < bad.noise_ceiling[e.name][0] - 1.0

    exps, _ = well_specified
    known = [dataclasses.replace(e, sigma=np.full(e.n_frames, NOISE_M)) for e in exps]
    good = fit(start_model(), known, default_free_parameters())
    assert good.goodness_of_fit.ratio[0] == pytest.approx(1.0, abs=0.12)
    assert good.goodness_of_fit.p_value > 1e-3
    assert "estimated / known noise" in fit_report(good, title="t", device_name="chevron_laser")
    with pytest.raises(ValueError, match="per-frame noise"):
        fit(start_model(), known, default_free_parameters(), sigma=NOISE_M)
    with pytest.raises(ValueError, match="every run or for none"):
        fit(start_model(), [known[0], exps[1]], default_free_parameters())


def test_p_values_read_as_sentences():
    """A p-value below double precision's reach reads "p < 1e-300", never "p = < 1e-300"."""
    from greybox._estimate.residuals import p_phrase, p_value_text

    assert p_phrase(0.0123) == "p = 0.012"
    assert p_phrase(0.0) == "p < 1e-300" and p_value_text(0.0) == "< 1e-300"
    assert p_phrase(float("nan")) == "p = n/a" and p_value_text(None) == "n/a"
