"""Figures of a user's device take their labels and units from its channels and files.

The device is DEVELOPING.md's mass-spring-damper (extracted verbatim), whose position is
logged as ``x_mm``: every figure must draw it in mm (never um, never the chevron's wording),
its 95 % band must be drawn, and `greybox simulate` must honour --figure-format,
--duration-s, --initial-state and the force's own unit (N). The checks read the axis labels
and the drawn data back from the figure objects; the drawn numbers are compared with the
fit's predictions converted by hand (1 m = 1000 mm)."""

import json
import re
from pathlib import Path

import numpy as np
import pytest

import greybox
from greybox import plots
from greybox.cli import main

ROOT = Path(__file__).resolve().parents[1]


def _example() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    m = re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, flags=re.S)
    return m.group(1)


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    import jax

    jax.config.update("jax_enable_x64", True)
    root = tmp_path_factory.mktemp("plots")
    (root / "dev").mkdir()
    (root / "dev" / "msd.py").write_text(_example())
    exp = root / "exp"
    exp.mkdir()
    rng = np.random.default_rng(0)
    t = np.arange(0.01, 2.0, 0.01)
    k, c, m = 55.0, 1.5, 2.0  # an underdamped step response, closed form
    wn, z = np.sqrt(k / m), c / (2 * np.sqrt(k * m))
    wd = wn * np.sqrt(1 - z * z)
    step = 3.0 / k * (1 - np.exp(-z * wn * t) * (np.cos(wd * t) + z * wn / wd * np.sin(wd * t)))
    y_mm = (step + 0.004 + rng.normal(0, 2e-5, t.size)) * 1e3
    (exp / "run.csv").write_text(
        "t_s,x_mm\n" + "".join(f"{a:.4f},{b:.6f}\n" for a, b in zip(t, y_mm))
    )
    (exp / "experiment.toml").write_text(
        '[experiment]\ndevice = "../dev/msd.py:SPEC"\n\n[model]\nmass_kg = 2.0\n\n'
        '[fit]\nloss = "l2"\nfree = ["stiffness_N_per_m", "damping_N_s_per_m", '
        '{ path = "readout.offset", per_run = true, scale = 1e-3 }]\n\n'
        '[[runs]]\nname = "step"\nfile = "run.csv"\nrole = "estimation"\n'
        'waveform = { type = "steps", times_s = [0.0], F_N = [3.0], end_s = 2.0 }\n'
    )
    out = root / "result"
    from greybox.cli._fit import fit_experiment_dir

    # one fit: its result for the API figures, its folder (params.json) for the commands
    outcome = fit_experiment_dir(exp, out, lambda message: None)
    return root, exp, out, outcome


def test_simulate_units_format_duration_and_initial_state(lab, tmp_path, capsys):
    _, _, out, _ = lab
    sim = tmp_path / "sim"
    argv = ["simulate", "--params", str(out / "params.json"), "--out", str(sim),
            "--waveform", "pulse:F_N=2,period_s=1,duty=0.5,n=1", "--duration-s", "3",
            "--dt-ms", "10", "--figure-format", "svg"]  # fmt: skip
    assert main(argv) == 0
    assert "peak" in capsys.readouterr().out
    assert (sim / "simulation.svg").read_text().lstrip().startswith("<?xml")
    header = (sim / "simulation.csv").read_text().splitlines()[0].split(",")
    assert header[:2] == ["t_s", "x_mm"] and header[-1] == "F_N"  # not F_mN
    table = np.genfromtxt(sim / "simulation.csv", delimiter=",", skip_header=1)
    assert table[-1, 0] == pytest.approx(3.0)  # the whole duration, past the pulse
    meta = json.loads((sim / "simulation.json").read_text())
    assert meta["file_units"] == {"x": "mm"}


def test_initial_state_is_refused_for_a_device_without_one(lab, tmp_path, capsys):
    _, _, out, _ = lab
    argv = ["simulate", "--params", str(out / "params.json"), "--out", str(tmp_path / "s"),
            "--waveform", "pulse:F_N=2,period_s=1,duty=0.5,n=1",
            "--initial-state", "stiffness_N_per_m=3"]  # fmt: skip
    assert main(argv) == 2
    assert "not an initial-state parameter" in capsys.readouterr().err


def test_band_figure_reads_back_in_mm(lab, tmp_path):
    from greybox.io._params_file import load_params
    from greybox.report import _plots

    _, _, out, _ = lab
    fitted = load_params(out / "params.json")
    wave = greybox.PiecewiseConstant(np.array([0.0, 0.5]), np.array([0.0, 2.0]), 1.5)
    t = np.linspace(0, 1.5, 151)
    band = fitted.posterior.band(wave, t)
    spec = fitted.spec
    fig = _plots.band_figure(
        tmp_path / "b.png", band, wave, output_channels=spec.outputs,
        input_channels=spec.inputs, file_units={"x": "mm"}, fmt="pdf",
    )  # fmt: skip
    assert (tmp_path / "b.pdf").read_bytes()[:4] == b"%PDF"
    top, bottom = fig.axes
    assert "mass position" in top.get_ylabel() and "[mm]" in top.get_ylabel()
    assert "[N]" in bottom.get_ylabel() and "laser" not in top.get_ylabel() + bottom.get_ylabel()
    line = next(ln for ln in top.get_lines() if ln.get_label() == "model (simulation)")
    np.testing.assert_allclose(line.get_ydata(), np.asarray(band.y).reshape(-1) * 1e3, rtol=1e-12)
    # the band is drawn (a filled area with its own legend entry)
    labels = [t.get_text() for t in top.get_legend().get_texts()]
    assert any(lbl.startswith("95 % confidence band") for lbl in labels)
    assert top.collections and top.collections[0].get_alpha() >= 0.3


def test_fit_figure_through_the_api(lab):
    _, _, out, outcome = lab
    fs, result = outcome.fitset, outcome.result
    fig = plots.plot_fit(result, 0, outputs=fs.spec.outputs, inputs=fs.spec.inputs,
                         file_units={"x": "mm"})  # fmt: skip
    top, bottom = fig.axes
    assert "[mm]" in top.get_ylabel() and "[N]" in bottom.get_ylabel()
    model = next(ln for ln in top.get_lines() if ln.get_label() == "model (simulation)")
    np.testing.assert_allclose(model.get_ydata(), np.asarray(result.predict(0)).reshape(-1) * 1e3)
    measured = next(ln for ln in top.get_lines() if ln.get_label() == "measured")
    np.testing.assert_allclose(measured.get_ydata(), fs.estimation[0].y.reshape(-1) * 1e3)
    # the residual tests: titles wrapped (two lines), no chevron words
    rfig = plots.plot_residual_tests(result.residuals, outputs=fs.spec.outputs,
                                     inputs=fs.spec.inputs)  # fmt: skip
    titles = [ax.get_title() for ax in rfig.axes]
    assert all("\n" in t for t in titles) and not any("laser" in t for t in titles)
    # the CLI's fit figure with the channels: mm, not um
    from greybox.report import _plots

    e = fs.estimation[0]
    _plots.run_figure(
        Path(out) / "x.svg", name=e.name, role="estimation", t_s=e.t_s, y=e.y,
        y_model=result.predict(0), inputs=e.inputs, sigma=result.sigma,
        fit_percent=result.fit_percent[e.name], outputs=fs.spec.outputs,
        input_labels=fs.spec.inputs, file_units={"x": "mm"},
    )  # fmt: skip
    assert (Path(out) / "x.svg").is_file()
