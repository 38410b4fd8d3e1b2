"""`greybox simulate` from a fitted params.json: the band covers the true model's response to a
waveform the fit never saw; CSV columns and units; bad input; the band's handling of
parameter combinations the data do not determine."""

import json

import jax
import numpy as np
import pytest
from test_cli_fit import EMBEDDED, fitted_dir

import greybox
from greybox._estimate.prediction import prediction_band
from greybox._model.parameters import get_value, set_values
from greybox._model.waveforms import PulseTrain
from greybox._simulate.simulate import simulate
from greybox.cli import main
from greybox.io._params_file import load_params

chevron_laser = greybox.device_module("chevron_laser")

NEW_WAVE = "pulse:power_mW=25,period_ms=300,duty=0.5,n=10,delay_ms=100,tail_ms=400"


def _read(path):
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    data = np.array([[float(c) for c in line.split(",")] for line in lines[1:]])
    return header, data


def _true_model():
    truth = json.loads((EMBEDDED / "truth.json").read_text())
    cam = truth["camera"]
    model = greybox.devices.with_camera(
        chevron_laser.SPEC.model(),
        exposure_s=cam["exposure_ms"] * 1e-3,
        m_per_px=cam["um_per_px"] * 1e-6,
    )
    paths = list(truth["parameters"])
    return set_values(model, paths, [truth["parameters"][p]["value"] for p in paths])


@pytest.fixture(scope="module")
def params_file():
    return fitted_dir() / "params.json"


def test_band_contains_the_true_response_to_a_new_waveform(params_file, tmp_path, capsys):
    out = tmp_path / "sim"
    assert (
        main(["simulate", "--params", str(params_file), "--waveform", NEW_WAVE, "--out", str(out)])
        == 0
    )
    assert "confidence band" in capsys.readouterr().out
    header, d = _read(out / "simulation.csv")
    assert header == ["t_s", "y_um", "y_lo95_um", "y_hi95_um", "laser_mW"]
    t, y, lo, hi, laser = d.T
    np.testing.assert_allclose(np.diff(t), 1e-3, atol=1e-9)
    assert t[-1] == pytest.approx(0.1 + 10 * 0.3 + 0.4)
    assert set(np.unique(laser)) == {0.0, 25.0}
    wave = PulseTrain(25e-3, 0.3, 0.5, 10, delay_s=0.1, tail_s=0.4)
    true = simulate(_true_model(), wave, t) * 1e6
    assert np.all((lo <= true + 1e-9) & (true <= hi + 1e-9)), np.max(np.abs(true - y))
    width = hi - lo
    assert 0 < np.max(width) < 0.02 * np.max(true)  # informative, not trivially wide
    assert np.max(true) > 1.5  # a 25 mW response of ~1.8 um: a real test of the gain
    assert (out / "simulation.png").read_bytes().startswith(b"\x89PNG\r\n\x1a\n")
    meta = json.loads((out / "simulation.json").read_text())
    assert meta["band"]["includes_noise"] is False and meta["band"]["level"] == 0.95
    assert meta["fit_verdict"] == json.loads(params_file.read_text())["headline"]["verdict"]


def test_simulating_a_rejected_structure_says_so(params_file, tmp_path, capsys):
    """The fit's verdict travels with its params.json: a structure the residual test
    rejected is named beside the band, which covers only its values' uncertainty."""
    doc = json.loads(params_file.read_text())
    doc["headline"]["verdict"] = "structure rejected"
    rejected = tmp_path / "params.json"
    rejected.write_text(json.dumps(doc))
    out = tmp_path / "sim"
    argv = ["simulate", "--params", str(rejected), "--waveform", NEW_WAVE, "--out", str(out)]
    assert main(argv) == 0
    assert "is 'structure rejected' (its headline)" in capsys.readouterr().out
    assert json.loads((out / "simulation.json").read_text())["fit_verdict"] == "structure rejected"


def test_noise_option_gives_a_prediction_interval(params_file, tmp_path):
    out = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                "--params",
                str(params_file),
                "--waveform",
                "pulse:power_mW=10,period_ms=500,duty=0.5,n=2",
                "--out",
                str(out),
                "--noise",
            ]
        )
        == 0
    )
    _, d = _read(out / "simulation.csv")
    sigma_um = load_params(params_file).sigma[0] * 1e6
    assert np.min(d[:, 3] - d[:, 2]) >= 2 * 1.959 * sigma_um
    assert json.loads((out / "simulation.json").read_text())["band"]["includes_noise"]


def test_logged_trace_csv_waveform(params_file, tmp_path):
    trace = tmp_path / "trace.csv"
    t = np.arange(0, 1.0, 0.01)
    p = np.where((t >= 0.2) & (t < 0.6), 12.5, 0.0)
    trace.write_text("t_s,laser_mW\n" + "".join(f"{a:.2f},{b:g}\n" for a, b in zip(t, p)))
    out = tmp_path / "sim"
    assert (
        main(
            [
                "simulate",
                "--params",
                str(params_file),
                "--waveform",
                str(trace),
                "--out",
                str(out),
                "--dt-ms",
                "5",
            ]
        )
        == 0
    )
    _, d = _read(out / "simulation.csv")
    np.testing.assert_allclose(
        d[:, 4], np.where((d[:, 0] >= 0.2 - 1e-9) & (d[:, 0] < 0.6 - 1e-9), 12.5, 0.0)
    )
    assert d[0, 1] == 0.0 and d[:, 1].max() > 0.5


def test_params_file_rebuilds_the_fitted_model(params_file):
    fitted = load_params(params_file)
    doc = fitted.document
    for path, value in doc["model"]["fitted"].items():
        assert float(get_value(fitted.model, path)) == pytest.approx(value, rel=1e-12)
    assert fitted.model.camera.exposure_s == 0.01
    assert float(fitted.model.camera.offset_m) == 0.0  # per-run offsets are not carried over
    assert fitted.raw.size == fitted.covariance_raw.shape[0] == 8


@pytest.mark.parametrize(
    "argv, field",
    [
        (["--waveform", "pulse:power_mW=25,period_ms=-3,n=2"], "--waveform"),
        (["--waveform", "square:power_mW=25"], "--waveform"),
        (
            ["--waveform", "pulse:power_mW=25,period_ms=300,n=2", "--params", "missing.json"],
            "missing.json",
        ),
        (["--waveform", "missing_trace.csv"], "missing_trace.csv"),
    ],
)
def test_bad_simulate_input_exit_2(params_file, tmp_path, capsys, argv, field):
    out = tmp_path / "sim"
    if "--params" not in argv:
        argv = argv + ["--params", str(params_file)]
    assert main(["simulate", *argv, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("greybox simulate: error:")
    assert field in err
    assert list(tmp_path.iterdir()) == []


def test_band_ignores_only_combinations_the_output_does_not_depend_on():
    """Absorptance and thermal resistance enter only as a product: a covariance that leaves
    their ratio undetermined gives a finite band; leaving one of them alone undetermined
    gives an infinite one (never a falsely narrow band)."""
    from greybox._model.freeparams import FreeParameter

    jax.config.update("jax_enable_x64", True)
    model = chevron_laser.SPEC.model(kinematics="linear")  # linear kinematics: y exactly ~ A R
    free = (
        FreeParameter("absorptance", unit="1", lower=0.05, upper=1.0),
        FreeParameter("thermal.resistance_K_per_W", unit="K/W", lower=0.0),
    )
    raw = np.array(
        [
            float(free[0].to_raw(0.67)),
            float(free[1].to_raw(get_value(model, "thermal.resistance_K_per_W"))),
        ]
    )
    wave = PulseTrain(20e-3, 0.4, 0.5, 2)
    t = np.linspace(0.01, 0.8, 40)
    # d/d raw of log(A R): the only direction the output depends on
    a = 0.67
    grad_log_product = np.array([(a - 0.05) * (1 - (a - 0.05) / 0.95) / a, 1.0])
    u = grad_log_product / np.linalg.norm(grad_log_product)
    null = np.array([u[1], -u[0]])  # changes A and R keeping A R fixed
    # sd 0.01 of log(A R) (1 % on the product), nothing on the ratio
    cov = (0.01 / np.linalg.norm(grad_log_product)) ** 2 * np.outer(u, u)
    band = prediction_band(model, free, raw, cov, wave, t, null_directions=null[None])
    assert np.all(np.isfinite(band.upper))
    rel = (band.sd_model / np.maximum(band.y, 1e-300))[band.y[:, 0] > 1e-8]
    np.testing.assert_allclose(rel, 0.01, rtol=1e-6)  # sd of y = 1 % of y, as the product's
    bad = prediction_band(model, free, raw, cov, wave, t, null_directions=np.eye(2)[:1])
    assert np.all(np.isinf(bad.upper[band.y[:, 0] > 1e-8]))
