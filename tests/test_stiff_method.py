"""`method = "stiff"`: the implicit adaptive path for devices whose time scales lie far apart.

A heated plate (time constant 60 s) read through a sensor that lags it by 10 ms
(tests/lagged_plate_device.py, an `AbstractODEDevice` as a user writes one). The explicit
solver (Tsit5) must take steps of the fastest scale over the whole record, so on a 10-minute
record it runs out of its step budget; Kvaerno5 does not. The truth is the closed form, the
matrix exponential of the linear system between input steps (scipy.linalg.expm), independent
of greybox's solvers.
"""

from pathlib import Path

import numpy as np
from scipy.linalg import expm

import greybox
from tests.lagged_plate_device import FREE, GAIN_K_PER_W, T_AMB, TAU_PLATE_S, TAU_SENSOR_S, build

STEP_TIMES, POWERS_W = [0.0, 150.0, 330.0], [2.0, 0.5, 1.5]
END_S, DT_S = 600.0, 2.0


def _model(gain=GAIN_K_PER_W, tau=TAU_PLATE_S):
    return build(gain, tau)


def _inputs():
    return greybox.PiecewiseConstant(np.array(STEP_TIMES), np.array(POWERS_W), END_S)


def _truth(t):
    """Sensor temperature at `t` [K]: exact, x' = A x + b per step, by the augmented expm."""
    a = np.array([[-1 / TAU_PLATE_S, 0.0], [1 / TAU_SENSOR_S, -1 / TAU_SENSOR_S]])
    out, x, t0 = np.empty_like(t), np.full(2, T_AMB), 0.0
    edges = [*STEP_TIMES[1:], np.inf]
    for p, t_end in zip(POWERS_W, edges):
        b = np.array([(GAIN_K_PER_W * p + T_AMB) / TAU_PLATE_S, 0.0])
        aug = np.zeros((3, 3))
        aug[:2, :2], aug[:2, 2] = a, b
        inside = (t >= t0) & (t < t_end)
        for k in np.flatnonzero(inside):
            out[k] = (expm(aug * (t[k] - t0)) @ np.append(x, 1.0))[1]
        if np.isfinite(t_end):
            x = (expm(aug * (t_end - t0)) @ np.append(x, 1.0))[:2]
        t0 = t_end
    return out


T_S = np.arange(0.0, END_S + DT_S / 2, DT_S)


def test_stiff_method_matches_the_closed_form_where_the_explicit_one_runs_out_of_steps():
    truth = _truth(T_S)
    budget = 2000  # the explicit solver needs ~ END_S / TAU_SENSOR_S steps
    stiff = greybox.simulate(_model(), _inputs(), T_S, method="stiff", max_steps=budget)
    # the global error of rtol = 1e-8 per step (on ~350 K): 1.0e-4 K measured, 8.9e-6 K for
    # Tsit5 given the steps it needs
    assert np.max(np.abs(stiff - truth) / truth) < 1e-6
    explicit = greybox.simulate(
        _model(), _inputs(), T_S, method="adaptive", max_steps=budget, throw=False
    )
    assert np.all(np.isnan(explicit))


def test_fit_with_the_stiff_method_recovers_the_plate():
    # seed 0: the start stalls at the truth (a Gauss-Newton step of 9e-4 standard errors
    # still to take, the cost resolved to the solver's tolerance), "not converged" under the
    # likelihood's 1e-9; converged at `fit.SETTLED_DECREMENT`
    rng = np.random.default_rng(0)
    y = _truth(T_S) + 0.05 * rng.standard_normal(T_S.size)
    run = greybox.Experiment("steps", T_S, y, _inputs())
    fit = greybox.fit(
        _model(30.0, 100.0), [run], FREE, method="stiff", solver_max_steps=2000, n_starts=1
    )
    assert fit.status == "converged" and fit.valid and fit.method == "stiff"
    truth = {"gain_K_per_W": GAIN_K_PER_W, "tau_plate_s": TAU_PLATE_S}
    for p in fit.parameters:
        assert abs(p.value - truth[p.path]) < 3 * p.se, (p.path, p.value, p.se)
    assert float(np.atleast_1d(fit.fit_percent["steps"])[0]) > 99.0


def test_cli_names_the_stiff_method_when_a_validation_run_cannot_be_simulated(tmp_path, capsys):
    """A short estimation run fits within the explicit solver's step budget, a long validation
    run does not: a clear error at [fit] method, exit 2, nothing written (it was reported as an
    internal error of greybox)."""
    from greybox.cli import main

    exp, out = tmp_path / "exp", tmp_path / "out"
    exp.mkdir()
    rng = np.random.default_rng(4)
    for name, end in (("short", 40.0), ("long", END_S)):
        t = T_S[T_S <= end]
        y = _truth(t) + 0.05 * rng.standard_normal(t.size)
        rows = ["t_s,T_K"] + [f"{a:.1f},{b:.6f}" for a, b in zip(t, y)]
        (exp / f"{name}.csv").write_text("\n".join(rows) + "\n")

    def steps(end):
        keep = [i for i, t in enumerate(STEP_TIMES) if t < end]
        times, powers = [STEP_TIMES[i] for i in keep], [POWERS_W[i] for i in keep]
        return f"times_s = {times}, P_W = {powers}, end_s = {end}"

    # a copy, as a user's file: a device file's folder is the user's code from then on (its
    # tracebacks are blamed on it), and tests/ must stay greybox's
    device = tmp_path / "lagged_plate.py"
    device.write_text(Path(__file__).with_name("lagged_plate_device.py").read_text())
    (exp / "experiment.toml").write_text(
        f'[experiment]\ndevice = "{device}:SPEC"\n\n[fit]\nn_starts = 1\n'
        "solver_max_steps = 3000\n\n"
        '[[runs]]\nname = "short"\nfile = "short.csv"\nrole = "estimation"\n'
        f'waveform = {{ type = "steps", {steps(40.0)} }}\n\n'
        '[[runs]]\nname = "long"\nfile = "long.csv"\nrole = "validation"\n'
        f'waveform = {{ type = "steps", {steps(END_S)} }}\n'
    )
    assert main(["fit", str(exp), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "experiment.toml: [fit] method: a validation run's simulation failed" in err
    assert 'method = "stiff"' in err and "internal error" not in err
    assert not out.exists()
