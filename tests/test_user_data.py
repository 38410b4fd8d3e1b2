"""Data as users have it, results as users need them (issue 16).

Raw TCLab-style logs written here (``Time,T1,T2,Q1,Q2`` mapped with [columns], a header-less
MATLAB csvwrite file with declared columns, a single-sensor log, a log whose clock starts at
1000 s with ``Time (sec)`` / ``(degC)`` headers) are fitted by `greybox fit` on a small linear
TCLab (ZOH, three free parameters); the SAE in metrics.csv is recomputed by hand from the
predictions CSV and from an independent simulation of the fitted model. Loader problems of a
whole folder are reported together; `greybox simulate` drives both heaters and writes every
channel; the python-control export matches the fitted model's steady state.
"""

import json

import numpy as np
import pytest

import greybox
from greybox.cli import main
from greybox.cli._fit import fit_experiment_dir

tclab = greybox.device_module("tclab")

DT = 3.0
N = 60
TRUE = {"U_W_per_m2K": 7.0, "alpha1_W_per_pct": 0.011, "alpha2_W_per_pct": 0.0075}
AMBIENT_C = 21.0


def _steps(t, edges):
    """Levels (N,) [%] from [(t_on, level), ...] held until the next edge."""
    u = np.zeros_like(t)
    for t_on, level in edges:
        u[t >= t_on] = level
    return u


def _record(h1, h2, seed):
    """(t, T1 degC, T2 degC, H1 %, H2 %) of the true linear board starting at rest."""
    t = np.arange(N) * DT
    u = np.column_stack([_steps(t, h1), _steps(t, h2)])
    amb = 273.15 + AMBIENT_C
    model = tclab.SPEC.model(
        radiation=False,
        ambient_K=amb,
        initial_T1_K=amb,
        initial_T2_K=amb,
        **TRUE,
    )
    y = np.asarray(greybox.simulate(model, greybox.waveforms.from_samples(t, u), t)).reshape(N, 2)
    y = y + np.random.default_rng(seed).normal(0.0, 0.05, y.shape)
    return t, y[:, 0] - 273.15, y[:, 1] - 273.15, u[:, 0], u[:, 1]


def _rows(*cols):
    return "".join(",".join(f"{v:.6g}" for v in row) + "\n" for row in zip(*cols))


TOML = """\
[experiment]
device = "tclab"

[model]
radiation = false

[experiment.settings]
ambient_K = {ambient_K}

[fit]
loss = "l2"
free = ["U_W_per_m2K", "alpha1_W_per_pct", "alpha2_W_per_pct"]

[columns]   # the TCLab logger's own names, for every run that does not say otherwise
time = {{ column = "Time", unit = "s" }}
T1 = {{ column = "T1", unit = "degC" }}
T2 = {{ column = "T2", unit = "degC" }}
H1 = {{ column = "Q1", unit = "%" }}
H2 = {{ column = "Q2", unit = "%" }}

[[runs]]
name = "logger"
file = "logger.csv"
role = "estimation"

[[runs]]
name = "matlab"
file = "matlab.csv"
role = "estimation"
header = false
columns = ["t_s", "T1_degC", "T2_degF", "H1_pct", "H2_pct"]

[[runs]]
name = "one_sensor"
file = "one_sensor.csv"
role = "estimation"
columns = {{ time = "Time (sec)", T1 = "Temperature 1 (degC)", H1 = "Heater 1 (%)" }}
constant_inputs = {{ H2 = 0 }}

[[runs]]
name = "late_clock"
file = "late_clock.csv"
role = "validation"
time_origin = "first_row"
columns = {{ time = "Time (sec)", T1 = "T1 [K]", T2 = "T2 [K]", H1 = "Q1", H2 = "Q2" }}
"""


def _write_folder(folder):
    folder.mkdir()
    (folder / "experiment.toml").write_text(TOML.format(ambient_K=273.15 + AMBIENT_C))
    t, y1, y2, h1, h2 = _record([(10, 60)], [(80, 40)], seed=1)
    (folder / "logger.csv").write_text("Time,T1,T2,Q1,Q2\n" + _rows(t, y1, y2, h1, h2))
    t, y1, y2, h1, h2 = _record([(0, 20), (100, 70)], [(40, 80)], seed=2)
    (folder / "matlab.csv").write_text(_rows(t, y1, y2 * 9 / 5 + 32, h1, h2))
    t, y1, _, h1, _ = _record([(20, 90), (140, 10)], [], seed=3)
    (folder / "one_sensor.csv").write_text(
        "Time (sec),Temperature 1 (degC),Heater 1 (%)\n" + _rows(t, y1, h1)
    )
    t, y1, y2, h1, h2 = _record([(30, 40)], [(10, 70), (120, 20)], seed=4)
    (folder / "late_clock.csv").write_text(
        "Time (sec),Q1,Q2,T1 [K],T2 [K]\n" + _rows(t + 1000.0, h1, h2, y1 + 273.15, y2 + 273.15)
    )
    return {"late_clock": (t, y1, y2)}


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
    import jax

    jax.config.update("jax_enable_x64", True)
    root = tmp_path_factory.mktemp("userdata")
    truth = _write_folder(root / "exp")
    # the tests read the numbers written (predictions, metrics), not the figures
    outcome = fit_experiment_dir(root / "exp", root / "result", lambda m: None, figure_format=None)
    return root, outcome, truth


def _read_csv(path):
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    data = np.array([[float(c) if c else np.nan for c in line.split(",")] for line in lines[1:]])
    return header, data


def test_raw_logs_fit_and_recover_the_board(fitted):
    _, outcome, _ = fitted
    r = outcome.result
    for path, value in TRUE.items():
        assert r.estimate(path).value == pytest.approx(value, rel=0.03)
    fs = outcome.fitset
    one = fs.run_info("one_sensor")
    assert one.output_columns[1] is None  # no T2 in the single-sensor log
    e = next(e for e in fs.estimation if e.name == "one_sensor")
    assert np.all(np.isnan(e.y[:, 1]))
    # initial temperatures from each sensor's first reading (T2 missing: T1's)
    assert dict(one.defaults)["initial_T2_K"] == pytest.approx(e.y[0, 0])
    assert fs.run_info("late_clock").time_shift_s == pytest.approx(1000.0)


def test_predictions_reproduce_hand_computed_sae(fitted):
    root, outcome, truth = fitted
    out = root / "result"
    header, d = _read_csv(out / "predictions" / "late_clock.csv")
    assert header[:3] == ["t_s", "T1_K", "T1_sim_K"]
    assert "T2_lo95_K" in header and "T2_residual_K" in header
    t, y1, y2 = truth["late_clock"]
    np.testing.assert_allclose(d[:, 0], t, atol=1e-6)  # clock shifted to the first row
    np.testing.assert_allclose(d[:, header.index("T1_K")], y1 + 273.15, atol=1e-3)
    col = {h: d[:, k] for k, h in enumerate(header)}
    hand = {
        ch: float(np.nansum(np.abs(col[f"{ch}_K"] - col[f"{ch}_sim_K"]))) for ch in ("T1", "T2")
    }
    lo, hi = col["T1_lo95_K"], col["T1_hi95_K"]
    assert np.all(lo <= col["T1_sim_K"] + 1e-9) and np.all(col["T1_sim_K"] <= hi + 1e-9)
    # metrics.csv agrees with the hand computation
    rows = [line.split(",") for line in (out / "metrics.csv").read_text().splitlines()]
    assert rows[0] == ["run", "role", "output", "unit", "n", "fit_percent", "rmse", "mae", "sae"]
    got = {r[2]: float(r[8]) for r in rows[1:] if r[0] == "late_clock"}
    for ch in ("T1", "T2"):
        assert got[ch] == pytest.approx(hand[ch], rel=1e-6)
    # and an independent simulation of the fitted model from the first readings
    v = next(e for e in outcome.fitset.validation if e.name == "late_clock")
    model = outcome.result.model
    measured = np.column_stack([col["T1_K"], col["T2_K"]])  # as written: 6 digits
    model = greybox.parameters.set_values(
        model, ["initial_T1_K", "initial_T2_K"], list(measured[0])
    )
    z = np.asarray(greybox.simulate(model, v.inputs, v.t_s)).reshape(-1, 2)
    independent = float(np.sum(np.abs(measured - z)))
    assert got["T1"] + got["T2"] == pytest.approx(independent, rel=1e-4)
    # single-sensor run: T2 has no reading, no metric
    one = {r[2]: r for r in rows[1:] if r[0] == "one_sensor"}
    assert one["T2"][4] == "0" and one["T2"][8] == ""
    assert outcome.metrics["runs"]["late_clock"]["outputs"]["T1"]["unit"] == "K"
    units = {r[0]: r[3] for r in rows[1:] if r[2] == "T2"}
    assert units == {"logger": "degC", "matlab": "degF", "one_sensor": "degC", "late_clock": "K"}
    total = outcome.metrics["sae_total"]["validation"]["T1"]
    assert total["unit"] == "degC" and total["sae"] == pytest.approx(got["T1"], rel=1e-9)
    val = json.loads((out / "validation_runs.json").read_text())
    assert val["runs"]["late_clock"]["time_shift_s"] == pytest.approx(1000.0)
    assert "initial_T1_K" in val["runs"]["late_clock"]["settings_from_data"]


def test_loader_problems_are_reported_together(tmp_path, capsys):
    folder = tmp_path / "bad"
    _write_folder(folder)
    t, y1, y2, h1, h2 = _record([(10, 60)], [], seed=5)
    # three problems in three runs: a heater at 150 %, a clock far from 0, no H2 column
    (folder / "logger.csv").write_text("Time,T1,T2,Q1,Q2\n" + _rows(t, y1, y2, h1 * 2.5, h2))
    (folder / "one_sensor.csv").write_text(
        "Time (sec),Temperature 1 (degC),Heater 1 (%)\n" + _rows(t, y1, h1)
    )
    toml = (folder / "experiment.toml").read_text()
    toml = toml.replace('time_origin = "first_row"\n', "").replace(
        "constant_inputs = { H2 = 0 }\n", ""
    )
    (folder / "experiment.toml").write_text(toml)
    rc = main(["fit", str(folder), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert "3 problems" in err[0]
    assert any("logger.csv" in e and "150 % is above 100 %" in e for e in err)
    assert any("late_clock.csv:2" in e and "time_origin" in e for e in err)
    assert any("one_sensor.csv" in e and "constant_inputs" in e for e in err)
    assert not (tmp_path / "out").exists()


def test_toml_and_csv_problems_are_reported_together(tmp_path, capsys):
    """Problems of the TOML file itself (a misspelt key, a bad option value, an unknown loss,
    a free path that is no parameter, an out-of-range setting) and of the run files (a heater
    at 250 %, a missing H2 column, a clock far from 0) are listed in one report."""
    folder = tmp_path / "bad"
    _write_folder(folder)
    t, y1, y2, h1, h2 = _record([(10, 60)], [], seed=5)
    (folder / "logger.csv").write_text("Time,T1,T2,Q1,Q2\n" + _rows(t, y1, y2, h1 * 2.5, h2))
    (folder / "one_sensor.csv").write_text(
        "Time (sec),Temperature 1 (degC),Heater 1 (%)\n" + _rows(t, y1, h1)
    )
    toml = (folder / "experiment.toml").read_text()
    edits = {
        'device = "tclab"\n': 'device = "tclab"\ndescripton = "typo"\n',
        "radiation = false\n": 'radiation = "no"\n',
        'loss = "l2"\n': 'loss = "l3"\n',
        'free = ["U_W_per_m2K",': 'free = ["U_W_per_m2", ',
        "ambient_K = 294.15": "ambient_K = 400.0",
        'time_origin = "first_row"\n': "",
        "constant_inputs = { H2 = 0 }\n": "",
    }
    for old, new in edits.items():
        assert old in toml, old
        toml = toml.replace(old, new)
    (folder / "experiment.toml").write_text(toml)
    rc = main(["fit", str(folder), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2
    assert "8 problems" in err[0], err
    expected = [  # (file, field, words of the message)
        ("experiment.toml:3", "experiment.descripton", "unknown key"),
        ("experiment.toml:6", "model.radiation", "must be a bool"),
        ("experiment.toml:12", "fit.loss", "l3"),
        ("experiment.toml", "fit.free[0]", "not a parameter of tclab"),
        ("experiment.toml", "experiment.settings.ambient_K", "outside the physical range"),
        ("logger.csv", "Q1", "is above 100 %"),
        ("late_clock.csv:2", "Time (sec)", "time_origin"),
        ("one_sensor.csv", "H2", "constant_inputs"),
    ]
    for where, field, words in expected:
        assert any(where in e and field in e and words in e for e in err[1:]), (where, err)
    assert len(err) == 1 + len(expected)
    assert not (tmp_path / "out").exists()


def test_unit_spellings_convert_through_pint():
    from greybox.io._units import channel_conversion, conversion

    t1 = tclab.OUTPUTS[0]
    assert channel_conversion(t1, "C") == (1.0, 273.15)  # the historic T1_C
    scale, offset = channel_conversion(t1, "degF")
    assert scale * 212 + offset == pytest.approx(373.15)
    assert channel_conversion(tclab.INPUTS[0], "pct") == (1.0, 0.0)
    assert conversion("mW", "W") == pytest.approx((1e-3, 0.0))
    assert conversion("ms", "s") == pytest.approx((1e-3, 0.0))
    with pytest.raises(ValueError, match="not a unit of K"):
        channel_conversion(t1, "mW")


def test_simulate_drives_both_heaters_and_writes_every_channel(fitted, tmp_path):
    root, _, _ = fitted
    params = root / "result" / "params.json"
    out = tmp_path / "sim"
    rc = main(
        [
            "simulate",
            "--params",
            str(params),
            "--waveform",
            "H1=pulse:H1_pct=50,period_s=100,duty=0.5,n=2",
            "--waveform",
            "H2=const:30",
            "--dt-ms",
            "2000",
            "--out",
            str(out),
        ]
    )
    assert rc == 0
    header, d = _read_csv(out / "simulation.csv")
    assert header == [  # outputs in the unit of the fit's files (params.json file_units)
        "t_s",
        "T1_degC",
        "T1_lo95_degC",
        "T1_hi95_degC",
        "T2_degC",
        "T2_lo95_degC",
        "T2_hi95_degC",
        "H1_pct",
        "H2_pct",
    ]
    assert set(d[:, 8]) == {30.0} and set(d[:, 7]) == {0.0, 50.0}
    assert np.all(d[1:, 4] > d[0, 4])  # heater 2 warms sensor 2
    # a CSV with every input column drives the same response
    trace = tmp_path / "trace.csv"
    trace.write_text("t_s,H1_pct,H2_pct\n" + _rows(d[:-1, 0], d[:-1, 7], d[:-1, 8]))
    rc = main(
        ["simulate", "--params", str(params), "--waveform", str(trace), "--dt-ms", "2000",
         "--out", str(tmp_path / "sim2")]
    )  # fmt: skip
    assert rc == 0
    _, d2 = _read_csv(tmp_path / "sim2" / "simulation.csv")
    np.testing.assert_allclose(d2[:, 1:7], d[: len(d2), 1:7], rtol=1e-9)


def test_state_space_export_matches_the_fitted_model(fitted):
    import control

    from greybox.io._export import to_state_space

    _, outcome, _ = fitted
    r = outcome.result
    ex = to_state_space(r.model, fit=r)
    assert not ex.linearised
    # steady state of a constant 50 % on heater 1: python-control's DC gain vs a long
    # simulation of the fitted model
    t = np.array([0.0, 2e4, 4e4])
    wave = greybox.waveforms.from_samples(np.array([0.0]), np.array([[50.0, 0.0]]), end_s=4e4)
    y = np.asarray(greybox.simulate(r.model, wave, t)).reshape(3, 2)
    dc = np.asarray(control.dcgain(ex.system)).reshape(2, 2)
    np.testing.assert_allclose(ex.y_op + dc[:, 0] * 50.0, y[-1], rtol=1e-6)
    assert ex.parameter_paths == tuple(TRUE)
    se = np.sqrt(np.diag(ex.covariance))
    for k, path in enumerate(ex.parameter_paths):
        assert se[k] == pytest.approx(r.estimate(path).se, rel=1e-6)
    discrete = to_state_space(r.model, dt=2.0).system
    assert discrete.dt == 2.0


def test_simulate_figure_has_a_panel_per_output_and_input(tmp_path):
    """`greybox simulate`'s figure: one panel per output (line + band) and per input (step)."""
    from greybox._estimate.prediction import Band
    from greybox.report import _plots as plots

    t = np.linspace(0.0, 10.0, 11)
    y = np.column_stack([t, 2 * t, 3 * t])
    band = Band(t, y, y - 1.0, y + 1.0, np.ones_like(y), np.ones_like(y), 0.95, False)
    wave = greybox.waveforms.from_samples(
        np.array([0.0, 5.0]), np.array([[1.0, 0.0], [0.0, 2.0]]), end_s=10
    )
    outputs = (("sensor 1", "K"), ("sensor 2", "K"), ("position", "m"))
    inputs = (("heater 1", "%"), ("heater 2", "%"))
    fig = plots.band_figure(
        tmp_path / "f.png", band, wave, output_labels=outputs, input_labels=inputs
    )
    assert (tmp_path / "f.png").stat().st_size > 0
    axes = fig.axes
    assert len(axes) == 5
    for j, ax in enumerate(axes[:3]):
        # the model line, and its band: filled and edged by two dashed lines (visible even
        # when narrower than the line)
        assert len(ax.lines) == 3 and len(ax.collections) == 1
        assert outputs[j][0] in ax.get_ylabel()
        scale = 1.0 if j < 2 else 1e6
        model = [ln for ln in ax.lines if ln.get_label() == "model (simulation)"]
        assert len(model) == 1
        np.testing.assert_allclose(model[0].get_ydata(), y[:, j] * scale)
        edges = sorted(
            (ln for ln in ax.lines if ln.get_linestyle() == "--"), key=lambda ln: ln.get_ydata()[0]
        )
        np.testing.assert_allclose(edges[0].get_ydata(), (y[:, j] - 1.0) * scale)
        np.testing.assert_allclose(edges[1].get_ydata(), (y[:, j] + 1.0) * scale)
    for k, ax in enumerate(axes[3:]):
        assert len(ax.lines) == 1 and inputs[k][0] in ax.get_ylabel()
        assert max(ax.lines[0].get_ydata()) == [1.0, 2.0][k]  # each input's own level


def test_robust_sigma_keeps_an_output_without_readings():
    from greybox._estimate.fit import _robust_sigma

    r = np.array([[1.0, np.nan], [-2.0, np.nan], [3.0, np.nan]])  # residuals / sigma
    w = np.array([[1.0, 0.0], [1.0, 0.0], [1.0, 0.0]])  # output 2: no valid reading
    got = _robust_sigma(r, w, np.array([2.0, 5.0]))
    # output 1: 1.4826 x median(|1|, |-2|, |3|) = 2 scaled units x sigma 2; output 2 kept
    np.testing.assert_allclose(got, [1.4826 * 2.0 * 2.0, 5.0])


def test_single_sensor_runs_only_fit_without_nan():
    """Every estimation run lacks T2 (single-sensor logs): the fit uses T1 alone, estimates
    T1's noise and leaves T2 out; no NaN reaches the estimate or its noise."""
    runs = []
    for i, h1 in enumerate(([(10, 60)], [(20, 90), (140, 10)])):
        t, y1, _, u1, _ = _record(h1, [], seed=10 + i)
        y = np.column_stack([y1 + 273.15, np.full(N, np.nan)])
        wave = greybox.waveforms.from_samples(t, np.column_stack([u1, np.zeros(N)]))
        runs.append(greybox.Experiment(f"r{i}", t, y, wave))
    amb = 273.15 + AMBIENT_C
    model = tclab.SPEC.model(
        radiation=False, ambient_K=amb, initial_T1_K=amb, initial_T2_K=amb, **TRUE
    )
    free = [
        greybox.FreeParameter(p, unit="", lower=lo, upper=hi)
        for p, lo, hi in (("U_W_per_m2K", 1.0, 20.0), ("alpha1_W_per_pct", 0.003, 0.03))
    ]
    model = greybox.parameters.set_values(model, ["U_W_per_m2K", "alpha1_W_per_pct"], [5.0, 0.009])
    res = greybox.fit(model, runs, free, loss="l2", n_starts=1)
    assert res.valid and np.all(np.isfinite(res.sigma))
    assert res.sigma[0] == pytest.approx(0.05, rel=0.3)  # the noise written by _record
    for p in ("U_W_per_m2K", "alpha1_W_per_pct"):
        assert res.estimate(p).value == pytest.approx(TRUE[p], rel=0.03)
        assert np.isfinite(res.estimate(p).se)


OFFSETS = {"est": (0.3, -0.5), "val": (-0.6, 0.4)}  # true sensor offsets per run [K]


def _offset_record(h1, h2, offsets, seed):
    """(t, readings T1, T2 degC, H1, H2) of the board at rest at ambient, read by sensors with
    `offsets` [K] (reading = temperature + offset), every 10 s for 600 s (two thermal time
    constants: an offset shows as where the readings settle against the known ambient)."""
    t = np.arange(N) * 10.0
    u = np.column_stack([_steps(t, h1), _steps(t, h2)])
    amb = 273.15 + AMBIENT_C
    model = tclab.SPEC.model(radiation=False, ambient_K=amb, **TRUE)
    # the readings at the start are ambient + offset, so the board starts at ambient
    model = greybox.parameters.set_values(
        model,
        ["readout.offset[0]", "readout.offset[1]", "initial_T1_K", "initial_T2_K"],
        [offsets[0], offsets[1], amb + offsets[0], amb + offsets[1]],
    )
    y = np.asarray(greybox.simulate(model, greybox.waveforms.from_samples(t, u), t)).reshape(N, 2)
    y = y + np.random.default_rng(seed).normal(0.0, 0.05, y.shape)
    return t, y[:, 0] - 273.15, y[:, 1] - 273.15, u[:, 0], u[:, 1]


def test_validation_refits_per_run_offsets(tmp_path):
    """Per-run sensor offsets re-fitted on a validation run (physics fixed) are written to
    validation_runs.json and match the offsets put into that run's data."""
    folder = tmp_path / "exp"
    folder.mkdir()
    for name, h1, h2, seed in (
        ("est", [(30, 60), (300, 0)], [(240, 40)], 21),
        ("val", [(90, 40), (400, 0)], [(30, 70), (360, 20)], 22),
    ):
        t, y1, y2, q1, q2 = _offset_record(h1, h2, OFFSETS[name], seed)
        (folder / f"{name}.csv").write_text(
            "t_s,T1_degC,T2_degC,H1_pct,H2_pct\n" + _rows(t, y1, y2, q1, q2)
        )
    # the readings at the start without their noise (known settings: the first reading's own
    # noise would otherwise persist through the slow thermal response and bias the offsets)
    amb = 273.15 + AMBIENT_C
    start = {
        k: f"{{ initial_T1_K = {amb + o[0]!r}, initial_T2_K = {amb + o[1]!r} }}"
        for k, o in OFFSETS.items()
    }
    (folder / "experiment.toml").write_text(
        f"""[experiment]
device = "tclab"
settings = {{ ambient_K = {273.15 + AMBIENT_C} }}

[model]
radiation = false

[fit]
loss = "l2"
n_starts = 1
free = ["U_W_per_m2K", "alpha1_W_per_pct", "alpha2_W_per_pct",
  {{ path = "readout.offset[0]", per_run = true }},
  {{ path = "readout.offset[1]", per_run = true }}]

[[runs]]
name = "est"
file = "est.csv"
role = "estimation"
waveform = {{ type = "logged" }}
settings = {start["est"]}

[[runs]]
name = "val"
file = "val.csv"
role = "validation"
waveform = {{ type = "logged" }}
settings = {start["val"]}
"""
    )
    outcome = fit_experiment_dir(folder, tmp_path / "result", lambda m: None, figure_format=None)
    doc = json.loads((tmp_path / "result" / "validation_runs.json").read_text())
    assert doc["per_run_parameters"] == ["readout.offset[0]", "readout.offset[1]"]
    refitted = doc["runs"]["val"]["refitted"]
    for j in (0, 1):
        p = refitted[f"readout.offset[{j}]"]
        assert p["unit"] == "K" and 0 < p["se"] < 0.1
        assert abs(p["value"] - OFFSETS["val"][j]) < 3 * p["se"], (j, p)
    # the estimation run's own offsets, fitted with the physics
    for j in (0, 1):
        e = next(q for q in outcome.result.parameters if q.name == f"readout.offset[{j}][est]")
        assert abs(e.value - OFFSETS["est"][j]) < 3 * e.se
    assert set(outcome.validation.refitted("val")) == set(refitted)
