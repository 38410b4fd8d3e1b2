"""The TCLab comparison, as functions shared by compare.py, the benchmark and the test.

Every number here is a free-run simulation result (never one-step prediction): the grey-box
model is simulated from the first measured temperatures; the black-box models use the first
max-lag measured samples as initial conditions and then feed back their own outputs.
"""

from __future__ import annotations

import dataclasses

import numpy as np

import greybox
from greybox import Experiment, FitResult, fit, simulate
from greybox import blackbox as bb
from greybox.metrics import sae

tclab = greybox.device_module("tclab")

# Park et al. (2020), sae_summary.xlsx: SAE [degC] (estimation, validation)
PAPER = {
    "two_heaters": {
        "physics-based energy balance": (270.26, 840.95),
        "ARX (na=2, nb=2)": (308.74, 3196.26),
        "Hammerstein neural network": (1886.73, 1855.92),
    },
    "one_heater": {
        "physics-based energy balance": (121.6, 1991.23),
        "ARX (na=2, nb=2)": (110.59, 3099.01),
        "FOPDT": (243.9, 3068.37),
        "Hammerstein neural network": (2299.27, 997.35),
    },
}
# Published MIMO ARX (tclab_farx.txt, GEKKO sysid, na = nb = 2): y(k+1) = sum_i alpha[i] y(k-i)
# + sum_i beta[j, i, l] u_l(k-i) + gamma, per output j.
PAPER_ARX = {
    "alpha": np.array([[1.93747665, 1.93540545], [-0.93782503, -0.93572505]]),
    "beta": np.array(
        [
            [[0.00099529, -0.00075913], [-0.00064673, 0.00077492]],
            [[-0.0013549, 0.00162968], [0.00137134, -0.00146352]],
        ]
    ),
    "gamma": np.array([0.00554484, 0.00915965]),
}


# The two grey-box structures of the benchmark and the tests: {label: shared_sensor_lag}. The
# experiment's structure selection is `greybox compare` on the folders' [[candidates]].
STRUCTURES = {"per-sensor lag (tau1, tau2)": False, "paper: shared lag tau": True}


def free_parameters(one_heater: bool = False, shared_sensor_lag: bool = False):
    """The device's free parameters for a structure; alpha2 is fixed when heater 2 never runs."""
    free = tclab.default_free_parameters(shared_sensor_lag)
    return [p for p in free if not (one_heater and p.path == "alpha2_W_per_pct")]


def fit_greybox(
    estimation: Experiment,
    *,
    one_heater: bool = False,
    loss: str = "l2",
    shared_sensor_lag: bool = False,
    extra_free=(),
) -> FitResult:
    """Fit U, Us, alpha1, (alpha2), tau1 (, tau2) and any `extra_free` on the estimation run
    (adaptive solver, simulation error on both sensors); `shared_sensor_lag=True` is the
    paper's structure."""
    return fit(
        tclab.SPEC.model(shared_sensor_lag=shared_sensor_lag),
        [estimation],
        free_parameters(one_heater, shared_sensor_lag) + list(extra_free),
        method="adaptive",
        loss=loss,
    )


def information_criteria(y, y_hat, k: int) -> tuple[float, float]:
    """(AIC, BIC) of a model with `k` fitted parameters from its residuals y - y_hat.

    Gaussian log-likelihood with the noise variance at its maximum-likelihood value RSS/n,
    up to a constant common to every model scored on the same data: AIC = n ln(RSS/n) + 2k,
    BIC = n ln(RSS/n) + k ln n, n = number of finite residuals (both sensors pooled).
    """
    r = (np.asarray(y) - np.asarray(y_hat)).ravel()
    r = r[np.isfinite(r)]
    n = r.size
    base = n * np.log(np.sum(r**2) / n)
    return float(base + 2 * k), float(base + k * np.log(n))


def simulate_run(model, exp: Experiment) -> np.ndarray:
    """Free-run simulation (N, 2) [K] of `exp` with its known initial temperatures."""
    return np.asarray(
        simulate(
            exp.apply_settings(model),
            exp.inputs,
            exp.t_s,
            method="adaptive",
            t_start_s=exp.t_start_s,
        )
    ).reshape(exp.n_frames, 2)


def scores(y, y_hat, outputs=(0, 1)) -> float:
    """SAE [degC = K] summed over the chosen sensor columns."""
    idx = list(outputs)
    return sae(np.asarray(y)[:, idx], np.asarray(y_hat)[:, idx])


def fit_arx22(data: bb.UniformData, nk: int = 1) -> bb.ARX:
    """The paper's ARX: na = nb = 2, diagonal A, all inputs, constant offset (GEKKO sysid)."""
    return bb.fit_arx(data, 2, 2, nk, offset=True)


def paper_arx() -> bb.ARX:
    """The published ARX coefficients as a greybox ARX (MATLAB sign: A = 1 - alpha q^-1 ...).

    GEKKO's nk = 0 means y(k+1) depends on u(k): our nk = 1 (one sample of delay).
    """
    alpha, beta, gamma = PAPER_ARX["alpha"], PAPER_ARX["beta"], PAPER_ARX["gamma"]
    ny, nb, nu = beta.shape
    a = np.concatenate([np.ones((ny, 1)), -alpha.T], axis=1)
    b = np.zeros((ny, nu, nb + 1))
    b[:, :, 1:] = np.transpose(beta, (0, 2, 1))
    nan = np.full((ny, 1), np.nan)
    return bb.ARX(
        a=a,
        b=b,
        offset=gamma,
        na=2,
        nb=(2,) * nu,
        nk=(1,) * nu,
        has_offset=True,
        parameters=nan,
        covariance=nan[:, :, None],
        noise_variance=nan[:, 0],
        dt=1.0,
        resampled=False,
        n_rows=0,
    )


def rise_data(data: bb.UniformData) -> bb.UniformData:
    """Temperatures as rises above the paper's 23 C ambient (ARMAX/OE fit no offset)."""
    return dataclasses.replace(data, y=data.y - (tclab.AMBIENT_K - 273.15))


# Per-sensor black-box structures on rise data: {kind: (fit, parameters per sensor for 2 inputs)}
MISO = {
    "armax": (lambda d: bb.fit_armax(d, 2, 2, 2, 1), 2 + 2 * 2 + 2),
    "oe": (lambda d: bb.fit_oe(d, 2, 1, 1), 2 * 2 + 2 * 1),
    "oe22": (lambda d: bb.fit_oe(d, 2, 2, 1), 2 * 2 + 2 * 2),
}


def fit_miso(data: bb.UniformData, kind: str):
    """One single-output model per sensor on rise data: ARMAX [2 2 2 1], OE [2 1 1] (first-
    order F per input) or OE [2 2 1] ("oe22", second-order F per input: the simulation-error
    counterpart of ARX(2,2))."""
    rises = rise_data(data)
    return [MISO[kind][0](dataclasses.replace(rises, y=rises.y[:, [j]])) for j in range(data.ny)]


def simulate_miso(models, data: bb.UniformData) -> np.ndarray:
    """Free-run simulation (N, ny) [degC] of per-sensor models fitted by `fit_miso`."""
    rises = rise_data(data)
    cols = [
        bb.simulate(m, dataclasses.replace(rises, y=rises.y[:, [j]]))[:, 0]
        for j, m in enumerate(models)
    ]
    return np.column_stack(cols) + (tclab.AMBIENT_K - 273.15)
