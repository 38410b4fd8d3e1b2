"""The sandwich's meat in stacked passes (`greybox._estimate.sandwich`): every model-error
regression of many runs and every HAC meat of many fits at once, each equal to what a
reference computation of it alone gives (`np.linalg.lstsq` per output; Newey-West summed
slot by slot), whatever the other fits stacked beside it."""

import numpy as np

from greybox._estimate import sandwich
from greybox._estimate.residuals import FrameGrid


def _run(rng, n, n_y=2, n_u=1, gaps=0.1, dropped=0.15):
    """A run of n frames at ~30 fps with missing timestamps, dropped readings and inputs."""
    t = np.cumsum(np.where(rng.random(n) < gaps, 2.0, 1.0)) / 30.0
    e = rng.normal(size=(n, n_y))
    e[:, 0] += 0.5 * np.sin(7 * t)  # something the inputs can explain
    valid = rng.random((n, n_y)) > dropped
    e[~valid & (rng.random((n, n_y)) < 0.5)] = np.nan  # some unused readings are NaN
    u = rng.normal(size=(n, n_u))
    u[rng.random((n, n_u)) < 0.05] = np.nan  # unknown levels at some frames
    return t, e, valid, u


def _lstsq_reference(t, e, valid, u, lags):
    """Per output: np.linalg.lstsq of the valid residuals on a constant and the inputs at
    lags 0..k-1 (k cut to two readings per coefficient), columns scaled to unit maximum."""
    n, n_y = e.shape
    n_u = u.shape[1]
    out, fitted = np.zeros_like(e), 0
    for j in range(n_y):
        ok = valid[:, j] & np.isfinite(e[:, j])
        m = int(ok.sum())
        if m == 0:
            continue
        k = max(0, min(lags, (m // 2 - 1) // n_u))
        lagged = sandwich._input_lags(t, FrameGrid.build(t), u, n, k)
        x = np.concatenate([np.ones((n, 1)), lagged], axis=1)[ok]
        scale = np.max(np.abs(x), axis=0)
        x = x / np.where(scale > 0, scale, 1.0)
        beta, _, rank, _ = np.linalg.lstsq(x, e[ok, j], rcond=None)
        out[ok, j] = e[ok, j] - x @ beta
        fitted += int(rank)
    return out, fitted


def test_stacked_regressions_equal_lstsq_run_by_run(monkeypatch):
    rng = np.random.default_rng(4)
    runs = []
    for n, lags, n_u in [(40, 6, 1), (73, 11, 1), (25, 25, 1), (90, 4, 2), (8, 3, 1), (55, 0, 1)]:
        runs.append((*_run(rng, n, n_u=n_u), lags))
    t, e, valid, u, _ = runs[-2]
    valid[:, 1] = False  # an output with no valid reading: nothing fitted, zero left
    got = sandwich.model_error_residuals_many(runs)
    for (t, e, valid, u, lags), (left, fitted) in zip(runs, got):
        want, want_fitted = _lstsq_reference(t, e, valid, u, lags)
        assert fitted == want_fitted
        np.testing.assert_allclose(left, want, rtol=1e-9, atol=1e-12 * np.nanmax(np.abs(e)))
    # one run alone gives what it gives among the others, and so does one pass a run
    alone = sandwich.model_error_residuals(*runs[1])
    np.testing.assert_array_equal(alone[0], got[1][0])
    monkeypatch.setattr(sandwich, "REGRESSION_BLOCK", 1)
    for (left, fitted), (left_1, fitted_1) in zip(got, sandwich.model_error_residuals_many(runs)):
        assert fitted_1 == fitted
        np.testing.assert_array_equal(left_1, left)


def test_regressions_on_an_input_function_use_its_values_at_lagged_times():
    rng = np.random.default_rng(5)
    t, e, valid, _ = _run(rng, 60, n_y=1, gaps=0.0)
    steps = rng.normal(size=(200, 2))  # two random staircases of 50 ms steps

    def u_of_t(s):
        return steps[np.clip((np.asarray(s) / 0.05).astype(int) + 20, 0, 199)]

    left, fitted = sandwich.model_error_residuals(t, e, valid, u_of_t, 5)
    ok = valid[:, 0] & np.isfinite(e[:, 0])
    dt = float(np.median(np.diff(t)))
    x = np.concatenate([np.ones((t.size, 1))] + [u_of_t(t - k * dt) for k in range(5)], axis=1)
    x = x[ok] / np.max(np.abs(x[ok]), axis=0)
    beta, _, rank, _ = np.linalg.lstsq(x, e[ok, 0], rcond=None)
    assert fitted == rank == 11
    np.testing.assert_allclose(left[ok, 0], e[ok, 0] - x @ beta, rtol=1e-9, atol=1e-12)
    assert np.all(left[~ok, 0] == 0.0)


def _newey_west_reference(runs, bandwidth):
    """Sum over runs of Gamma_0 + sum_l (1 - l/(L+1)) (Gamma_l + Gamma_l^T), each Gamma_l
    summed pair by pair of slots l apart on the run's frame grid (no prewhitening)."""
    p = np.asarray(runs[0][1]).shape[1]
    omega = np.zeros((p, p))
    for t, g in runs:
        grid = FrameGrid.build(t)
        at = {int(s): g[i] for i, s in enumerate(grid.slots)}
        for s, gs in at.items():
            omega += np.outer(gs, gs)
            for lag in range(1, bandwidth + 1):
                if s - lag in at:
                    w = 1.0 - lag / (bandwidth + 1.0)
                    gam = np.outer(gs, at[s - lag])
                    omega += w * (gam + gam.T)
    return omega


def test_stacked_meats_equal_each_fit_alone_and_newey_west():
    rng = np.random.default_rng(6)
    fits = []
    for n_runs, p in [(1, 3), (4, 3), (2, 2), (3, 3)]:
        runs = []
        for _ in range(n_runs):
            n = int(rng.integers(20, 80))
            t = np.cumsum(np.where(rng.random(n) < 0.1, 2.0, 1.0)) / 30.0
            g = rng.normal(size=(n, p))
            g[:, 0] = np.convolve(rng.normal(size=n + 4), np.ones(5) / 2, "valid")[:n]
            runs.append((t, g))
        fits.append(runs)
    fits[3] = [(t, np.where(np.arange(g.shape[1]) == 1, 0.0, g)) for t, g in fits[3]]  # unused
    n_readings, n_fitted = [200, 300, 120, 250], [5, 9, 2, 7]
    for prewhiten, bandwidth in [(True, None), (False, 3)]:
        many = sandwich.hac_meats(
            fits, bandwidth=bandwidth, prewhiten=prewhiten, n_readings=n_readings, n_fitted=n_fitted
        )
        for runs, m, nr, nf in zip(fits, many, n_readings, n_fitted):
            alone = sandwich.hac_meat(
                runs, bandwidth=bandwidth, prewhiten=prewhiten, n_readings=nr, n_fitted=nf
            )
            assert m.bandwidth == alone.bandwidth
            np.testing.assert_allclose(m.meat, alone.meat, rtol=1e-12, atol=0)
            np.testing.assert_allclose(m.var1, alone.var1, rtol=1e-10, atol=1e-14)
            assert m.dof_factor == nr / (nr - nf)
            if not prewhiten:
                want = _newey_west_reference(runs, bandwidth) * nr / (nr - nf)
                np.testing.assert_allclose(m.meat, want, rtol=1e-10)
    # a score component that is zero throughout stays out of the VAR and of the meat
    prewhitened = sandwich.hac_meats([fits[3]])[0]
    assert np.all(prewhitened.var1[1] == 0) and np.all(prewhitened.var1[:, 1] == 0)
    assert np.all(prewhitened.meat[1] == 0)
