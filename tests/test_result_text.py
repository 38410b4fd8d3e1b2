"""A FitResult as a user meets it in a console or a notebook: a one-line repr (it was 119,659
characters), `summary()` with the parameter table, an HTML table, and DataFrames of the
parameters and of a run's predictions whose numbers are the result's own."""

import re
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import greybox
from greybox.io import load_experiment_set, predictions_to_dataframe

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def demo():
    import jax

    jax.config.update("jax_enable_x64", True)
    fs = load_experiment_set(ROOT / "experiments" / "chevron_laser")
    result = greybox.fit(fs.model, fs.estimation[:1], fs.free, **{**fs.fit_options, "n_starts": 1})
    return fs, result


def test_repr_is_one_short_line(demo):
    _, r = demo
    text = repr(r)
    assert "\n" not in text and len(text) < 200
    n = len(r.parameters)
    assert f"{r.status}, simulation-error fit, {n} parameters, 1 run, cost " in text
    assert float(text.split("cost ")[1].rstrip(">")) == pytest.approx(r.cost, rel=1e-5)


def test_one_step_fits_report_log_likelihood():
    from greybox._estimate.result_text import short_repr

    fake = SimpleNamespace(
        status="converged", process_noise=True, parameters=(1, 2, 3), experiments=(1, 2),
        cost=5.0, log_likelihood=-1234.5678,
    )
    assert short_repr(fake) == (
        "<FitResult: converged, one-step likelihood fit, 3 parameters, 2 runs, log L -1234.57>"
    )


def test_summary_and_html_carry_every_parameter(demo):
    _, r = demo
    text = r.summary()
    lines = text.splitlines()
    assert lines[0] == f"FitResult: {repr(r)[12:-1]}"
    assert len(lines) == 3 + len(r.parameters)
    for p, line in zip(r.parameters, lines[3:]):
        assert line.startswith(p.name) and p.verdict in line
        from greybox._estimate.result_text import display_unit

        f, unit = display_unit(p.unit, p.value)
        shown = float(line.split()[1])  # the estimate, in the display unit
        assert shown == pytest.approx(p.value * f, abs=max(abs(p.se * f), 1e-12 * abs(p.value * f)))
    html = r._repr_html_()
    assert html.count("<tr>") == 1 + len(r.parameters) and "<table>" in html


def test_parameter_dataframe_is_the_results_numbers(demo):
    pytest.importorskip("pandas")
    _, r = demo
    df = r.to_dataframe()
    assert list(df.columns) == [
        "parameter", "value", "sd", "ci95_low", "ci95_high", "unit", "verdict", "experiment"
    ]
    assert list(df["parameter"]) == [p.name for p in r.parameters]
    np.testing.assert_array_equal(df["value"], [p.value for p in r.parameters])
    np.testing.assert_array_equal(df["sd"], [p.se for p in r.parameters])
    ok = np.isfinite(df["sd"])
    assert ok.any()
    # the headline interval is value +- 1.96 sd on the raw (transformed) scale: it contains
    # the value and is at least as wide as the normal one's first-order width
    assert np.all(df["ci95_low"][ok] < df["value"][ok])
    assert np.all(df["value"][ok] < df["ci95_high"][ok])


def test_predictions_dataframe_matches_the_fit(demo):
    pytest.importorskip("pandas")
    fs, r = demo
    run = r.experiments[0]
    df = predictions_to_dataframe(r, run.name, fs.spec)
    assert df.index.name == "t_s"
    np.testing.assert_array_equal(df.index, run.t_s)
    np.testing.assert_allclose(df["y_um"], run.y[:, 0] * 1e6)
    sim = np.asarray(r.predictions[run.name]["simulation"]).reshape(-1)
    np.testing.assert_allclose(df["y_um simulation"], sim * 1e6)
    with pytest.raises(KeyError, match="not a run of this fit"):
        predictions_to_dataframe(r, "nope")


def test_missing_pandas_names_the_extra(demo, monkeypatch):
    _, r = demo
    monkeypatch.setitem(sys.modules, "pandas", None)  # import pandas -> ModuleNotFoundError
    with pytest.raises(ImportError, match=re.escape('pip install "greybox[dataframe]"')):
        r.to_dataframe()


def test_predictions_dataframe_carries_every_horizon_and_its_sd(demo):
    """A process-noise result's shape (one-step and k-step with sds), in SI without a device."""
    pytest.importorskip("pandas")
    _, r = demo
    run = r.experiments[0]
    n = run.n_frames
    z = np.linspace(0.0, 1.0, n)[:, None]
    fake = SimpleNamespace(
        experiments=(run,),
        predictions={run.name: {"simulation": z, "one-step": 2 * z}},
        prediction_sd={run.name: {"one-step": 3 * z}},
    )
    df = predictions_to_dataframe(fake, run.name)
    assert list(df.columns) == ["y1_SI", "y1_SI simulation", "y1_SI one-step", "y1_SI one-step sd"]
    np.testing.assert_array_equal(df["y1_SI one-step sd"], 3 * z[:, 0])
    np.testing.assert_array_equal(df["y1_SI"], run.y[:, 0])
