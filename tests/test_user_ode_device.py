"""A nonlinear ODE device written by a user (`vector_field(t, x, u)`) works end to end.

The device file is DEVELOPING.md's tank example, extracted verbatim and written to a folder
outside the repository as a user would. Its data come from scipy's `solve_ivp` (an
independent integrator of A dh/dt = q - a sqrt(2 g h), piecewise between the inflow steps);
the fit must recover the tank and orifice areas within 3 standard errors, and `greybox
describe` must show the file device's parameters.
"""

import re
from pathlib import Path

import diffrax._integrate as integrate
import numpy as np
import pytest
from scipy.integrate import solve_ivp

import greybox
from greybox.io import load_experiment_set

ROOT = Path(__file__).resolve().parents[1]
AREA, OUTLET, G, NOISE_M = 0.012, 2.6e-5, 9.81, 5e-4
TIMES, FLOWS_ML, END = [0.0, 100.0, 250.0], [20.0, 40.0, 10.0], 400.0
LEVEL0 = (0.05, 0.12)  # each run's starting level [m], a known per-run setting


def _example() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    m = re.search(r"<!-- device example: tank.py -->\n```python\n(.*?)```", text, flags=re.S)
    assert m, "DEVELOPING.md lost its ODE device example"
    return m.group(1)


def _truth(t, level0, scale):
    """Level [m] at `t`: solve_ivp between the inflow steps (RK45, tight tolerances)."""
    edges = [*TIMES, END]
    out, h0 = np.empty_like(t), level0
    for i, q_ml in enumerate(FLOWS_ML):
        q = q_ml * scale * 1e-6
        sol = solve_ivp(
            lambda _, h, q=q: [(q - OUTLET * np.sqrt(2 * G * max(h[0], 0.0))) / AREA],
            (edges[i], edges[i + 1]),
            [h0],
            rtol=1e-10,
            atol=1e-12,
            dense_output=True,
        )
        inside = (t >= edges[i]) & (t <= edges[i + 1])
        out[inside] = sol.sol(t[inside])[0]
        h0 = sol.y[0, -1]
    return out


STEP_BUDGET = 4000  # the adaptive solver's, set in [fit]: not the default (16384)


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp("lab")
    (root / "my_devices").mkdir()
    (root / "my_devices" / "tank.py").write_text(_example())
    exp = root / "exp"
    exp.mkdir()
    rng = np.random.default_rng(5)
    runs = []
    for i, (level0, scale) in enumerate(zip(LEVEL0, (1.0, 0.7))):
        t = np.arange(2.0, END, 2.0)
        y = _truth(t, level0, scale) + rng.normal(0, NOISE_M, t.size)
        rows = ["t_s,h_mm"] + [f"{a:.3f},{b * 1e3:.4f}" for a, b in zip(t, y)]
        (exp / f"run{i}.csv").write_text("\n".join(rows) + "\n")
        flows = ", ".join(f"{v * scale:g}" for v in FLOWS_ML)
        runs.append(
            f'[[runs]]\nname = "run{i}"\nfile = "run{i}.csv"\nrole = "estimation"\n'
            f"settings = {{ initial_level_m = {level0} }}\n"
            f'waveform = {{ type = "steps", times_s = {TIMES}, q_mL_per_s = [{flows}], '
            f"end_s = {END} }}\n"
        )
    (exp / "experiment.toml").write_text(
        '[experiment]\ndevice = "../my_devices/tank.py:SPEC"\n\n[fit]\nloss = "l2"\n'
        f"solver_max_steps = {STEP_BUDGET}\n\n"
        + "\n".join(runs)
    )
    es = load_experiment_set(exp)
    traced = []  # diffrax's integration loop, each time JAX runs it to trace it
    loop = integrate.loop

    def counted(*args, **kwargs):
        traced.append(1)
        return loop(*args, **kwargs)

    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(integrate, "loop", counted)
        result = greybox.fit(es.model, es.estimation, es.free, **es.fit_options)
    return root, es, result, len(traced)


def test_ode_device_recovers_both_areas(lab):
    _, es, result, _ = lab
    assert es.fit_options["method"] == "adaptive"  # a nonlinear device: the ODE solver
    assert result.valid and result.residuals.all_white
    for path, truth in (("tank_area_m2", AREA), ("outlet_area_m2", OUTLET)):
        est = result.estimate(path)
        assert est.verdict == "identifiable"
        assert abs(est.value - truth) < 3 * est.se, (path, est.value, est.se, truth)
        assert est.se < 0.02 * truth  # and the data pin it down


def test_the_adaptive_solve_is_traced_once_for_the_simulation_and_its_derivative(lab):
    """The fit traces the simulation twice, as it is and with its tangents, but diffrax's
    `diffeqsolve` (a jitted function) only once for both: the vector field is a module of
    the device and its input (`greybox._simulate.simulate._InputDriven`), equal from one call
    to the next where a closure made at each call was not, and every greybox program is
    traced in one mesh context (`greybox._compile._traced_once`), where the tangents' trace,
    made as optimistix takes the shape of its first linearisation, ran in another. Twice
    before 2026-11-29 (the stiff plate's first fit, tests/test_stiff_method.py: tracing 4.5
    -> 2.8 s)."""
    assert lab[3] == 1


def test_validation_predictions_and_bands_simulate_with_the_fit_s_solver_settings(
    lab, monkeypatch
):
    """The fit's adaptive-solver settings (here its step budget from [fit]) are the ones its
    validation, its predictions and its bands simulate with, in the library as in the
    command: each call is stopped where it hands them to the simulation."""
    import greybox._estimate.fit as fit_module
    import greybox._estimate.prediction as prediction_module
    import greybox._simulate.simulate as simulate_module

    _, es, result, _ = lab
    want = {"solver_rtol": 1e-8, "solver_atol": 1e-10, "solver_max_steps": STEP_BUDGET}
    assert result.solver == want
    handed = []

    class Handed(Exception):
        pass

    def response(problem, raw):
        handed.append(dict(problem.solver_opts))
        raise Handed

    def simulate(*args, rtol, atol, max_steps, **kwargs):
        handed.append({"rtol": rtol, "atol": atol, "max_steps": max_steps})
        raise Handed

    def response_and_jacobian(base, shared, raw, row, method, solver):
        handed.append(dict(zip(("rtol", "atol", "max_steps"), solver)))
        raise Handed

    monkeypatch.setattr(fit_module, "_response", response)
    monkeypatch.setattr(simulate_module, "simulate", simulate)
    monkeypatch.setattr(prediction_module, "_response_and_jacobian", response_and_jacobian)
    run = es.estimation[0]
    for call in (
        lambda: greybox.validate(result, [run]),
        lambda: result.predict(0),
        lambda: result.posterior.band(run.inputs, run.t_s),
    ):
        with pytest.raises(Handed):
            call()
    assert handed == [{k.removeprefix("solver_"): v for k, v in want.items()}] * 3


def test_describe_shows_a_file_device_and_its_physical_ranges(lab, capsys):
    from greybox.cli import main

    root, _, _, _ = lab
    assert main(["describe", str(root / "my_devices" / "tank.py")]) == 0
    text = capsys.readouterr().out
    assert "device tank: Tank" in text
    assert re.search(r"\*outlet_area_m2 .* bounds 0\.\.- +physical 1e-07\.\.0\.001", text)
    assert main(["describe", str(root / "my_devices" / "tank.py"), "--option", "x=1"]) == 2


def test_option_error_hint_names_a_describe_command_that_works(lab, tmp_path, capsys):
    from greybox._model.errors import InputError
    from greybox.cli import main

    root, _, _, _ = lab
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "experiment.toml").write_text(
        f'[experiment]\ndevice = "{root / "my_devices" / "tank.py"}:SPEC"\n\n'
        "[model]\nno_such_option = 1\n"
    )
    with pytest.raises(InputError) as err:
        load_experiment_set(exp)
    hint = re.search(r"`greybox (describe [^`]+)`", str(err.value))
    assert hint, str(err.value)
    assert main(hint.group(1).split()) == 0  # from another folder, as printed
    assert "device tank" in capsys.readouterr().out
