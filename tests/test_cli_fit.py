"""`greybox fit` on the embedded data set: the files it writes, the truth it recovers, and
that an interrupted or failed run leaves no result behind.

One fit of the embedded set is shared by this module and tests/test_cli_simulate.py
(`fitted_dir`), so the suite compiles and runs it once.
"""

import atexit
import functools
import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest

import greybox
from greybox.cli import main

ROOT = Path(__file__).resolve().parents[1]
EMBEDDED = ROOT / "experiments" / "chevron_laser"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
RUNS = [
    "e1_5mW_200ms",
    "e2_10mW_200ms",
    "e3_10mW_300ms",
    "e4_15mW_400ms",
    "e5_20mW_600ms",
    "e6_30mW_1000ms",
    "v1_8mW_250ms",
    "v2_12mW_500ms",
    "v3_25mW_800ms",
]


@functools.cache
def fitted_dir() -> Path:
    """The result folder of `greybox fit experiments/chevron_laser` (run once per process)."""
    base = Path(tempfile.mkdtemp(prefix="greybox-test-fit-"))
    atexit.register(shutil.rmtree, base, ignore_errors=True)
    out = base / "result"
    assert main(["fit", str(EMBEDDED), "--out", str(out), "--quiet"]) == 0
    return out


@pytest.fixture(scope="module")
def result():
    return fitted_dir()


@pytest.fixture(scope="module")
def params(result):
    def no_nan(name):
        raise AssertionError(f"params.json holds {name}: not strict JSON")

    return json.loads((result / "params.json").read_text(), parse_constant=no_nan)


@pytest.fixture(scope="module")
def truth():
    return json.loads((EMBEDDED / "truth.json").read_text())


def test_params_json_schema(params):
    assert params["schema"] == "greybox.params/3"
    assert params["noise_model"]["kind"] == "output error"
    assert params["noise_model"]["horizons"] == ["simulation"]
    assert params["device"]["name"] == "chevron_laser"
    assert params["device"]["options"]["kinematics"] == "exact"
    options = greybox.get_device("chevron_laser").options
    assert set(params["device"]["options"]) == {o.name for o in options}
    assert params["greybox_version"]
    assert params["model"]["camera"] == {"m_per_px": 0.645e-6, "exposure_s": 0.01, "fps": 30.0}
    assert set(params["model"]["fitted"]) == {"absorptance", "thermal.tau_s"}
    entries = params["parameters"]
    assert len(entries) == 2 + 6  # two shared values and one offset per estimation run
    for p in entries:
        assert set(p) >= {
            "name",
            "path",
            "unit",
            "value",
            "se",
            "ci95",
            "verdict",
            "experiment",
            "prior",
        }
        assert p["verdict"] in ("identifiable", "prior-dominated", "not identifiable")
        lo, hi = p["ci95"]
        assert lo < p["value"] < hi and p["se"] > 0
    units = {p["path"]: p["unit"] for p in entries}
    assert units == {"absorptance": "1", "thermal.tau_s": "s", "camera.offset_m": "m"}
    owners = [p["experiment"] for p in entries if p["path"] == "camera.offset_m"]
    assert owners == RUNS[:6]
    n = len(params["raw"])
    assert n == 8 and np.asarray(params["covariance_raw"]).shape == (n, n)
    assert [f["path"] for f in params["free"]] == [
        "absorptance",
        "thermal.tau_s",
        "camera.offset_m",
    ]
    fp = params["fit_percent"]
    assert fp["horizon"] == "simulation"
    assert list(fp["estimation"]) == RUNS[:6] and list(fp["validation"]) == RUNS[6:]
    assert fp["outputs"] == ["y"]  # one figure per output channel and run
    assert all(len(v) == 1 for v in fp["estimation"].values())
    assert params["convergence"]["converged"] is True
    assert params["convergence"]["status"] == "converged"
    assert params["convergence"]["valid"] is True
    assert params["sigma"]["estimated"] is True
    assert params["sigma"]["goodness_of_fit"] is None  # no known noise to test against
    assert params["residuals"]["white"] is True
    assert params["residuals"]["verdict"].startswith("residuals consistent with white noise")
    assert params["standard_errors"]["headline"] == "gauss-newton"
    for p in entries:
        assert p["se"] == p["se_gauss_newton"] and p["se_hac"] > 0 and p["bound"] is None
    assert params["identifiability"]["weak_directions"] == []


def test_true_values_inside_reported_intervals(params, truth):
    est = {p["name"]: p for p in params["parameters"]}
    for path, t in truth["parameters"].items():
        p = est[path]
        assert p["verdict"] == "identifiable"
        lo, hi = p["ci95"]
        assert lo <= t["value"] <= hi, (path, t["value"], p["ci95"])
        # the fit moved away from the nominal start: the nominal value is excluded
        assert not lo <= t["nominal"] <= hi, (path, t["nominal"], p["ci95"])
    # Per-run offsets are nuisance values: eight 95 % intervals all cover their truth only
    # ~2/3 of the time, and the corrupted burst biases its run's offset by ~2 nm under the
    # Huber loss (each outlier keeps a pull of c = 1.5 sigma). Each must still be within
    # 3.5 standard errors, i.e. a few nm of ~200 um.
    offsets = {p["experiment"]: p for p in params["parameters"] if p["experiment"]}
    assert set(offsets) == set(RUNS[:6])
    for run, p in offsets.items():
        error = p["value"] - truth["camera_offset_m"][run]
        assert abs(error) < 3.5 * p["se"], (run, error, p["se"])


def test_fit_quality_is_at_the_noise_level(params, truth):
    sigma_um = params["sigma"]["value"][0] * 1e6
    assert sigma_um == pytest.approx(truth["camera"]["noise_um"], rel=0.15)
    # the 30 mW run has ~5 um swing on 0.05 um noise: a right model fits it closely
    assert params["fit_percent"]["estimation"]["e6_30mW_1000ms"][0] > 90
    assert min(v[0] for v in params["fit_percent"]["validation"].values()) > 60
    # fitted down to the noise: every run within 2 points of its noise ceiling
    for role in ("estimation", "validation"):
        for run, (pct,) in params["fit_percent_robust"][role].items():
            assert pct == pytest.approx(params["noise_ceiling"][role][run][0], abs=2.0), run
    # the corrupted burst (8 frames, one may be dropped) is flagged in its run only
    flagged = {r: v["outliers_flagged"] for r, v in params["runs"].items()}
    assert 6 <= flagged[truth["camera"]["burst_run"]] <= 8
    assert sum(flagged.values()) == flagged[truth["camera"]["burst_run"]]


def test_report_states_what_the_numbers_are(result):
    text = (result / "report.md").read_text()
    assert "free-run simulation" in text and "not one-step" in text
    assert "fit % (simulation, all valid frames)" in text
    assert "fit % without flagged frames" in text
    assert "estimated from the residuals" in text
    assert "Outliers flagged" in text and "converged" in text
    assert "every fitted parameter is identifiable" in text
    head = text.split("## ")[0]  # status and residual verdict come first
    assert "**Fit status: converged**" in head
    assert "residuals consistent with white noise" in head
    assert "## Residual analysis" in text and "Ljung-Box" in text
    assert "s.e. HAC (Newey-West)" in text and "headline standard errors are the Gauss" in text
    for run in RUNS:
        assert run in text
    assert "| `thermal.tau_s` |" in text and "| ms |" in text


def test_figures_are_png(result):
    names = [f"fit_{r}.png" for r in RUNS] + [
        "residuals.png",
        "residual_tests.png",
        "correlation.png",
    ]
    assert sorted(p.name for p in (result / "figures").iterdir()) == sorted(names)
    for name in names:
        data = (result / "figures" / name).read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 10_000, name
    text = (result / "report.md").read_text()
    assert all(f"figures/{n}" in text for n in names)


def test_interrupted_fit_leaves_the_previous_result(result, tmp_path, monkeypatch, capsys):
    """Ctrl-C while the figures are written: exit 130, the earlier result stays whole."""
    import greybox.report._plots

    out = tmp_path / "result"
    shutil.copytree(result, out)
    before = (out / "params.json").read_bytes()

    def interrupt(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(greybox.report._plots, "correlation_figure", interrupt)
    assert main(["fit", str(EMBEDDED), "--out", str(out)]) == 130
    err = capsys.readouterr().err
    assert "[" in err and "fitting" in err  # progress lines were shown
    assert "no result was written" in err
    assert (out / "params.json").read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["result"]  # no partial folder


def test_failed_fit_leaves_no_result(tmp_path, monkeypatch, capsys):
    import importlib

    def broken(*args, **kwargs):
        raise RuntimeError("solver exploded")

    # the module, not the function that greybox/__init__ re-exports under the same name
    monkeypatch.setattr(importlib.import_module("greybox._estimate.fit"), "fit", broken)
    out = tmp_path / "result"
    assert main(["fit", str(EMBEDDED), "--out", str(out), "--quiet"]) == 3  # a bug, not input
    assert "solver exploded" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_prior_dominated_parameter_is_reported(tmp_path):
    """Freeing the thermal resistance with a log-normal prior: the report calls it
    prior-dominated and names the absorptance x resistance combination."""
    import jax

    jax.config.update("jax_enable_x64", True)
    from greybox._estimate.fit import fit
    from greybox.io import load_experiment_set
    from greybox.io._results import report_text

    folder = tmp_path / "prior"
    shutil.copytree(EMBEDDED, folder, ignore=shutil.ignore_patterns("*.py", "v*.csv"))
    text = (folder / "experiment.toml").read_text()
    text = text.replace(
        'free = ["absorptance", "thermal.tau_s", "camera.offset_m"]',
        'free = ["absorptance", "thermal.tau_s", { path = '
        '"thermal.resistance_K_per_W", lower = 0.0, prior_median = 1355.0, '
        'prior_log_sd = 0.3 }, "camera.offset_m"]',
    )
    runs = text.split("[[runs]]")
    text = "[[runs]]".join(r for r in runs if 'role = "validation"' not in r)
    (folder / "experiment.toml").write_text(text)
    fs = load_experiment_set(folder)
    res = fit(fs.model, fs.estimation, fs.free, **fs.fit_options)
    verdicts = {p.name: p.verdict for p in res.parameters}
    assert verdicts["thermal.resistance_K_per_W"] == "prior-dominated"
    assert verdicts["thermal.tau_s"] == "identifiable"
    report = report_text(fs, res, None, [])
    assert "| `thermal.resistance_K_per_W` |" in report and "prior-dominated" in report
    ident = report.split("## Identifiability")[1]
    assert "`absorptance` x `thermal.resistance_K_per_W`" in ident


def test_posterior_from_the_fit_equals_the_one_loaded_from_params_json(result, tmp_path):
    """One posterior object: what a fit returns and what params.json gives back are the same
    model, free set, raw estimate, covariance, method and solver settings, so they predict
    the same band."""
    from greybox.cli._fit import fit_experiment_dir
    from greybox.io import load_params

    # figures are not what this compares (test_params_json_schema's result draws them)
    outcome = fit_experiment_dir(EMBEDDED, tmp_path / "again", lambda _m: None, figure_format=None)
    live = outcome.result.posterior
    loaded = load_params(tmp_path / "again" / "params.json").posterior
    np.testing.assert_allclose(loaded.raw, live.raw, rtol=1e-12)
    np.testing.assert_allclose(loaded.covariance_raw, live.covariance_raw, rtol=1e-9, atol=1e-300)
    assert [p.path for p in loaded.free] == [p.path for p in live.free]
    assert loaded.method == live.method
    assert loaded.solver == live.solver == outcome.result.solver
    assert set(live.solver) == {"solver_rtol", "solver_atol", "solver_max_steps"}
    wave = greybox.PulseTrain(0.02, 0.3, 0.5, 3, delay_s=0.1)
    t = np.linspace(0.0, 1.2, 25)
    a, b = live.band(wave, t), loaded.band(wave, t)
    np.testing.assert_allclose(b.y, a.y, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(b.upper - b.y, a.upper - a.y, rtol=1e-6, atol=1e-15)


def test_report_units_prefix_only_plain_leading_factors():
    # 2.4e-7 J/K reads 240 nJ/K; a prefix on a squared unit would square too (1e-9 m^2/s is
    # not 1 nm^2/s, which is 1e-18 m^2/s), so such units keep their SI form
    from greybox.report._markdown import display_unit

    f, unit = display_unit("J/K", 2.4e-7)
    assert unit == "nJ/K" and f * 2.4e-7 == pytest.approx(240.0)
    assert display_unit("m^2/s", 1e-9) == (1.0, "m^2/s")
    assert display_unit("K^2/s", 1e-4) == (1.0, "K^2/s")


def test_a_params_2_file_of_the_previous_version_still_loads(result, tmp_path):
    """greybox.params/3 is /2 plus the noise_model section: a /2 file (no noise_model) loads
    to the same least-squares model, raw estimate and covariance."""
    from greybox.io import load_params

    doc = json.loads((result / "params.json").read_text())
    doc["schema"] = "greybox.params/2"
    del doc["noise_model"]
    old = tmp_path / "params.json"
    old.write_text(json.dumps(doc))
    a, b = load_params(result / "params.json"), load_params(old)
    assert a.noise_model == b.noise_model == "output error"
    np.testing.assert_array_equal(a.raw, b.raw)
    np.testing.assert_array_equal(a.covariance_raw, b.covariance_raw)
    doc["schema"] = "greybox.params/9"
    old.write_text(json.dumps(doc))
    with pytest.raises(greybox.InputError, match="reads greybox.params/2 and greybox.params/3"):
        load_params(old)


def test_figure_format_svg_writes_vector_figures(tmp_path):
    """`--figure-format svg`: every figure is an SVG document (no PNG), and report.md links
    the .svg files. Two runs of the embedded set (one estimation, one validation) keep the
    fit small."""
    folder = tmp_path / "two runs"
    shutil.copytree(EMBEDDED, folder, ignore=shutil.ignore_patterns("*.py"))
    head, *runs = (folder / "experiment.toml").read_text().split("\n[[runs]]\n")
    keep = [r for r in runs if "e4_15mW" in r or "v1_8mW" in r]
    (folder / "experiment.toml").write_text("\n[[runs]]\n".join([head, *keep]))
    out = tmp_path / "out"
    assert main(["fit", str(folder), "--out", str(out), "--quiet", "--figure-format", "svg"]) == 0
    names = sorted(p.name for p in (out / "figures").iterdir())
    assert names == sorted(
        ["fit_e4_15mW_400ms.svg", "fit_v1_8mW_250ms.svg", "residuals.svg", "residual_tests.svg",
         "correlation.svg"]
    )  # fmt: skip
    for name in names:
        data = (out / "figures" / name).read_text()
        assert data.lstrip().startswith("<?xml") and "<svg" in data, name
    text = (out / "report.md").read_text()
    assert all(f"figures/{n}" in text for n in names)


def test_no_figures_writes_the_same_result_without_figures(result, tmp_path):
    """`--no-figures`: no figures/ folder and no figure named in report.md; every other file
    is the one a fit with figures writes (the same fit: the same bytes)."""
    out = tmp_path / "out"
    assert main(["fit", str(EMBEDDED), "--out", str(out), "--quiet", "--no-figures"]) == 0
    assert not (out / "figures").exists()
    assert "figures/" not in (out / "report.md").read_text()
    written = sorted(p.relative_to(out) for p in out.rglob("*") if p.is_file())
    drawn = sorted(
        p.relative_to(result) for p in result.rglob("*") if p.is_file() and "figures" not in p.parts
    )
    assert written == drawn
    for rel in written:
        if rel.name != "report.md":
            assert (out / rel).read_bytes() == (result / rel).read_bytes(), rel
