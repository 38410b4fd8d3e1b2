"""Experiment folders: loading, unit conversion, and the bad-input contract of `greybox fit`.

Every bad input must give exit status 2, one line on stderr naming the file (and line where
there is one) and the field, and leave no result folder (not even a partial one).
"""

import importlib.util
import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from greybox._model.errors import InputError
from greybox.cli import main
from greybox.io import load_experiment_set
from greybox.io._toml import TomlLines
from tests.helpers import GOOD_TOML

ROOT = Path(__file__).resolve().parents[1]
EMBEDDED = ROOT / "experiments" / "chevron_laser"


def _write_csv(path, t, y, *, col="y_px", laser=None, laser_col="laser_mW"):
    lines = ["t_s," + col + (f",{laser_col}" if laser is not None else "")]
    for k in range(len(t)):
        cells = [f"{t[k]:.6f}", "nan" if not np.isfinite(y[k]) else f"{y[k]:.4f}"]
        if laser is not None:
            cells.append(f"{laser[k]:g}")
        lines.append(",".join(cells))
    path.write_text("\n".join(lines) + "\n")


def _frames():
    t = (np.arange(42) + 0.5) / 30.0
    y = 312.0 + 1.5 * (np.sin(2 * np.pi * t / 0.4) > 0) * (t > 0.2)
    return t, y


@pytest.fixture
def good(tmp_path):
    """A small valid experiment folder; tests break one thing at a time."""
    folder = tmp_path / "exp"
    folder.mkdir()
    (folder / "experiment.toml").write_text(GOOD_TOML)
    t, y = _frames()
    _write_csv(folder / "est.csv", t, y)
    _write_csv(folder / "val.csv", t, y - 2.0)
    return folder


def _bad(tmp_path, capsys, folder, *needles, line=None):
    """Run `greybox fit` on a bad folder: exit 2, one line naming everything, no output."""
    out = tmp_path / "result"
    rc = main(["fit", str(folder), "--out", str(out), "--quiet"])
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert rc == 2, err
    assert len(err.splitlines()) == 1, err
    assert err.startswith("greybox fit: error: "), err
    for needle in needles:
        assert str(needle) in err, f"{needle!r} not in {err!r}"
    if line is not None:
        assert re.search(rf":{line}: ", err), f"line {line} not in {err!r}"
    assert not out.exists()
    assert not list(tmp_path.glob(".result*")), "a partial result was left behind"
    assert captured.out == ""
    return err


def test_good_folder_loads_and_converts_units(good):
    fs = load_experiment_set(good)
    assert [e.name for e in fs.estimation] == ["est"]
    assert [e.name for e in fs.validation] == ["val"]
    assert fs.camera == {"fps": 30.0, "exposure_s": 0.01, "m_per_px": 0.645e-6, "noise_m": None}
    assert fs.model.camera.exposure_s == 0.01
    t, y = _frames()
    e = fs.estimation[0]
    np.testing.assert_allclose(e.t_s, np.round(t, 6))
    np.testing.assert_allclose(e.y[:, 0], np.round(y, 4) * 0.645e-6)  # px -> m, once
    assert float(np.max(e.inputs.values)) == pytest.approx(0.020)  # mW -> W
    assert e.inputs.switch_times()[0] == pytest.approx(0.2)
    # the per-run offset starts at the estimation runs' rest reading, not at 0
    offset = next(p for p in fs.free if p.path == "camera.offset_m")
    assert offset.per_experiment and offset.initial == pytest.approx(312.0 * 0.645e-6)


def test_embedded_set_loads():
    fs = load_experiment_set(EMBEDDED)
    assert len(fs.estimation) == 6 and len(fs.validation) == 3
    powers = [float(np.max(e.inputs.values)) * 1e3 for e in fs.estimation]
    assert powers == pytest.approx([5, 10, 10, 15, 20, 30])
    n_frames = sum(e.n_frames for e in fs.estimation)
    assert 1800 <= n_frames <= 2200
    dropped = sum(int((~e.mask).sum()) for e in fs.estimation)
    assert 0.02 * n_frames < dropped < 0.1 * n_frames
    assert fs.run_info("v2_12mW_500ms").input_source == "described (log checked)"


def test_logged_laser_trace_and_micrometre_column(good):
    t = np.arange(0, 1.6, 0.001)  # a DAQ log at 1 kHz, with camera frames every 33 ms
    laser = np.where((t >= 0.2) & (t < 0.4), 20.0, 0.0)
    y = np.full(t.size, np.nan)
    y[::33] = 201.0 + 0.5 * (t[::33] > 0.3)  # a response (a constant series is refused)
    _write_csv(good / "est.csv", t, y, col="y_um", laser=laser)
    text = (
        (good / "experiment.toml")
        .read_text()
        .replace(
            'waveform = { type = "pulse_train", power_mW = 20, period_ms = 400, n_pulses = 3, '
            "delay_ms = 200 }",
            'waveform = { type = "logged" }',
            1,
        )
    )
    (good / "experiment.toml").write_text(text)
    fs = load_experiment_set(good)
    e = fs.estimation[0]
    assert fs.run_info("est").input_source == "logged"
    np.testing.assert_allclose(e.inputs.switch_times(), [0.2, 0.4], atol=1e-9)
    assert np.nanmax(e.y) == pytest.approx(201.5e-6)


def test_tracker_csv_with_two_scales_needs_y_column(good, tmp_path, capsys):
    t, y = _frames()
    lines = ["t_s,y_px,y_um,quality,reason,sigma_px"]
    lines += [f"{a:.6f},{b:.4f},{b * 0.645:.5f},0.99,,0.05" for a, b in zip(t, y)]
    (good / "est.csv").write_text("\n".join(lines) + "\n")
    _bad(tmp_path, capsys, good, "est.csv", "y_px", "y_column", line=1)
    # every run tracked: the known noise (sigma_px) is then in every run, as it must be
    (good / "val.csv").write_text("\n".join(lines) + "\n")
    text = (
        (good / "experiment.toml")
        .read_text()
        .replace('file = "est.csv"', 'file = "est.csv"\ny_column = "y_um"')
        .replace('file = "val.csv"', 'file = "val.csv"\ny_column = "y_um"')
    )
    (good / "experiment.toml").write_text(text)
    fs = load_experiment_set(good)
    assert fs.run_info("est").y_column == "y_um"
    assert fs.estimation[0].y[0, 0] == pytest.approx(y[0] * 0.645e-6, rel=1e-6)


def test_toml_line_locator():
    text = (
        '[camera]\nfps = 30  # frames/s\n\n[[runs]]\nname = "a"\n'
        'waveform = { power_mW = 5, duty = 0.5 }\n[[runs]]\nname = "b"\n[runs.waveform]\n'
        'period_ms = 200\n[experiment.settings]\n"thermal.tau_s" = 0.04\n[fit]\n'
        'free = [\n  "absorptance",\n  { path = "thermal.resistance_K_per_W", lower = 0 },\n'
        ']\nloss = "l2"\n'
    )
    where = TomlLines(text)
    assert where.line("camera", "fps") == 2
    assert where.line("runs", 0, "waveform", "duty") == 6
    assert where.line("runs", 1, "name") == 8
    assert where.line("runs", 1, "waveform", "period_ms") == 10
    assert where.line("runs", 1, "file") == 7  # missing key -> its table
    assert where.line("experiment", "settings", "thermal.tau_s") == 12
    assert where.line("fit", "free", 1, "lower") == 16
    assert where.line("fit", "loss") == 18


# ---- the bad-input contract, one distinct problem per case ------------------------------


def test_bad_missing_column(good, tmp_path, capsys):
    t, _ = _frames()
    (good / "est.csv").write_text("t_s,quality\n" + "".join(f"{x:.6f},1\n" for x in t))
    _bad(tmp_path, capsys, good, good / "est.csv", "y_um", "missing column", line=1)


def test_bad_wrong_unit_suffix(good, tmp_path, capsys):
    # any length unit pint knows is converted (y_mm); a unit of another dimension is refused
    t, y = _frames()
    _write_csv(good / "est.csv", t, y, col="y_degC")
    _bad(tmp_path, capsys, good, good / "est.csv", "y_degC", "y_um, y_nm, y_px", line=1)


def test_bad_time_column_unit(good, tmp_path, capsys):
    # t_ms is a time unit (converted); a suffix that is no time unit is refused
    t, y = _frames()
    (good / "est.csv").write_text(
        "t_px,y_px\n" + "".join(f"{a * 1e3:.3f},{b:.4f}\n" for a, b in zip(t, y))
    )
    _bad(tmp_path, capsys, good, good / "est.csv", "t_px", "t_s", line=1)


def test_bad_time_values_in_milliseconds(good, tmp_path, capsys):
    t, y = _frames()
    _write_csv(good / "est.csv", t * 1e3, y)
    _bad(tmp_path, capsys, good, good / "est.csv", "t_s", "milliseconds")


def test_bad_empty_csv(good, tmp_path, capsys):
    (good / "val.csv").write_text("")
    _bad(tmp_path, capsys, good, good / "val.csv", "header", "empty", line=1)


def test_bad_header_only_csv(good, tmp_path, capsys):
    (good / "val.csv").write_text("t_s,y_px\n")
    _bad(tmp_path, capsys, good, good / "val.csv", "no data rows", line=2)


def test_bad_nan_only_run(good, tmp_path, capsys):
    t, _ = _frames()
    _write_csv(good / "est.csv", t, np.full(t.size, np.nan))
    _bad(tmp_path, capsys, good, good / "est.csv", "y_px", "NaN", line=2)


def test_bad_duplicate_timestamp(good, tmp_path, capsys):
    t, y = _frames()
    t[10] = t[9]
    _write_csv(good / "est.csv", t, y)
    _bad(tmp_path, capsys, good, good / "est.csv", "t_s", "repeats", line=12)  # row 10 = line 12


def test_bad_decreasing_timestamp(good, tmp_path, capsys):
    t, y = _frames()
    t[20] = t[18]
    _write_csv(good / "est.csv", t, y)
    _bad(tmp_path, capsys, good, good / "est.csv", "t_s", "backwards", line=22)


def test_bad_unknown_device_model(good, tmp_path, capsys):
    text = (good / "experiment.toml").read_text().replace('"chevron_laser"', '"chevron_lazer"')
    (good / "experiment.toml").write_text(text)
    _bad(
        tmp_path,
        capsys,
        good,
        good / "experiment.toml",
        "experiment.device",
        "chevron_lazer",
        "chevron_laser",
        line=2,
    )


def test_bad_waveform_contradicts_logged_trace(good, tmp_path, capsys):
    t, y = _frames()
    laser = np.where((t >= 0.2) & (((t - 0.2) % 0.4) < 0.2) & (t < 1.4), 20.0, 0.0)
    k = 27  # a sample further than one frame interval (the timing slack) from any edge
    r = (t[k] - 0.2) % 0.2
    assert min(r, 0.2 - r) > 1 / 30
    laser[k] = 20.0 if laser[k] == 0 else 0.0
    _write_csv(good / "est.csv", t, y, laser=laser)
    _bad(
        tmp_path,
        capsys,
        good,
        good / "est.csv",
        "laser_mW",
        "contradicts",
        "experiment.toml:14",
        line=k + 2,
    )


def test_logged_trace_matching_description_is_accepted(good):
    t, y = _frames()
    laser = np.where((t >= 0.2) & (((t - 0.2) % 0.4) < 0.2) & (t < 1.4), 20.0, 0.0)
    _write_csv(good / "est.csv", t, y, laser=laser * 1.02)  # a power meter 2 % high
    fs = load_experiment_set(good)
    assert fs.run_info("est").input_source == "described (log checked)"


def test_bad_unreadable_toml(good, tmp_path, capsys):
    text = (good / "experiment.toml").read_text().replace("exposure_ms = 10", "exposure_ms = ten")
    (good / "experiment.toml").write_text(text)
    _bad(tmp_path, capsys, good, good / "experiment.toml", "exposure_ms", "not valid TOML", line=7)


def test_bad_negative_exposure(good, tmp_path, capsys):
    text = (good / "experiment.toml").read_text().replace("exposure_ms = 10", "exposure_ms = -10")
    (good / "experiment.toml").write_text(text)
    _bad(tmp_path, capsys, good, good / "experiment.toml", "camera.exposure_ms", ">= 0", line=7)


def test_bad_run_file_missing(good, tmp_path, capsys):
    (good / "val.csv").unlink()
    _bad(
        tmp_path,
        capsys,
        good,
        good / "experiment.toml",
        "runs[1].file",
        "val.csv",
        "does not exist",
        line=18,
    )


def test_bad_non_numeric_cell(good, tmp_path, capsys):
    t, y = _frames()
    _write_csv(good / "est.csv", t, y)
    lines = (good / "est.csv").read_text().splitlines()
    lines[7] = lines[7].split(",")[0] + ",31x.2"
    (good / "est.csv").write_text("\n".join(lines) + "\n")
    _bad(tmp_path, capsys, good, good / "est.csv", "y_px", "'31x.2'", line=8)


def test_bad_zero_frames_in_estimation_set(good, tmp_path, capsys):
    text = (
        (good / "experiment.toml").read_text().replace('role = "estimation"', 'role = "validation"')
    )
    (good / "experiment.toml").write_text(text)
    _bad(tmp_path, capsys, good, good / "experiment.toml", "runs[0].role", "zero frames")


def test_bad_unknown_key(good, tmp_path, capsys):
    text = (good / "experiment.toml").read_text().replace("um_per_px", "um_per_pixel")
    (good / "experiment.toml").write_text(text)
    _bad(
        tmp_path,
        capsys,
        good,
        good / "experiment.toml",
        "camera.um_per_pixel",
        "unknown key",
        line=8,
    )


def test_bad_missing_description_and_folder(tmp_path, capsys):
    empty = tmp_path / "empty"
    empty.mkdir()
    _bad(tmp_path, capsys, empty, empty / "experiment.toml", "does not exist")
    _bad(tmp_path, capsys, tmp_path / "nowhere", "nowhere", "EXPERIMENT_DIR")


def test_bad_free_parameter_path(good, tmp_path, capsys):
    text = (
        (good / "experiment.toml")
        .read_text()
        .replace(
            "[[runs]]",
            '[fit]\nfree = ["absorptance", { path = "thermal.tau", lower = 1e-4 }]\n\n[[runs]]',
            1,
        )
    )
    (good / "experiment.toml").write_text(text)
    _bad(
        tmp_path,
        capsys,
        good,
        good / "experiment.toml",
        "fit.free[1].path",
        "thermal.tau_s",
        line=11,
    )
    # a bare path outside the parameter table (here a structural, static field) is refused
    text = text.replace('"absorptance"', '"camera.n_quadrature"')
    (good / "experiment.toml").write_text(text)
    _bad(tmp_path, capsys, good, good / "experiment.toml", "fit.free[0]", "the parameters are")


def test_bad_start_on_a_bound(good, tmp_path, capsys):
    """A free parameter whose start (the device's own value) lies on its bound has no image
    under the fit's transform: exit 2 at the free list (it was an internal error). With a
    start_values hook (chevron_laser's) the fit finds it; without one, the loader does, before
    any fit (tests/lagged_plate_device.py; gain_K_per_W starts at 30)."""
    toml = good / "experiment.toml"
    text = toml.read_text()
    free = '[fit]\nfree = [{ path = "thermal.tau_s", lower = 0.01, upper = 0.04 }]\n\n[[runs]]'
    toml.write_text(text.replace("[[runs]]", free, 1))
    _bad(tmp_path, capsys, good, toml, "[fit] free", "thermal.tau_s: starting value 0.04")
    plate = tmp_path / "lagged_plate.py"  # a user's copy: tests/ is not a device folder
    plate.write_text((ROOT / "tests" / "lagged_plate_device.py").read_text())
    rows = ["t_s,P_W,T_K"] + [f"{k * 2.0},1.0,{295.0 + k}" for k in range(20)]
    (good / "est.csv").write_text("\n".join(rows) + "\n")
    toml.write_text(
        f'[experiment]\ndevice = "{plate}:SPEC"\n\n'
        '[fit]\nfree = [{ path = "gain_K_per_W", lower = 30.0 }]\n\n'
        '[[runs]]\nname = "est"\nfile = "est.csv"\nrole = "estimation"\n'
        'waveform = { type = "logged" }\n'
    )
    _bad(tmp_path, capsys, good, toml, "fit.free[0]", 'path = "gain_K_per_W"', line=5)


def test_free_list_with_a_prior(good):
    text = (
        (good / "experiment.toml")
        .read_text()
        .replace(
            "[[runs]]",
            """[fit]
free = [
  "absorptance",
  { path = "thermal.resistance_K_per_W", lower = 0.0, prior_median = 1355.0, prior_log_sd = 0.3 },
  "camera.offset_m",
]

[[runs]]""",
            1,
        )
    )
    (good / "experiment.toml").write_text(text)
    fs = load_experiment_set(good)
    assert [p.path for p in fs.free] == [
        "absorptance",
        "thermal.resistance_K_per_W",
        "camera.offset_m",
    ]
    r = fs.free[1]
    assert (r.unit, r.lower, r.prior_median, r.prior_log_sd) == ("K/W", 0.0, 1355.0, 0.3)
    assert fs.free[2].per_experiment and fs.free[0].upper == 1.0  # the device's standard specs


def test_a_free_table_changes_only_what_it_gives(good, tmp_path, capsys):
    """A [fit] free table is the bare path's parameter with what the table gives changed: a
    start alone keeps the bounds (the standard set's for thermal.tau_s, the parameter table's
    for the resistance) and a per-run path stays per run; a bound given sets the pair (lower
    only: no upper); a start outside the kept bounds is refused at the list, exit 2. (A start
    alone used to drop the bounds: the heating-system plate's radiation then ran to 483
    against its declared 50.)"""
    toml = good / "experiment.toml"
    text = toml.read_text()

    def free(entries):
        toml.write_text(text.replace("[[runs]]", f"[fit]\nfree = [{entries}]\n\n[[runs]]", 1))

    free(
        '{ path = "thermal.tau_s", initial = 0.05 }, '
        '{ path = "thermal.resistance_K_per_W", initial = 2000.0 }, '
        '{ path = "camera.offset_m", scale = 1e-5 }, { path = "absorptance", lower = 0.1 }'
    )
    tau, resistance, offset, absorptance = load_experiment_set(good).free
    assert (tau.lower, tau.upper, tau.initial) == (1e-4, 2.0, 0.05)
    assert (resistance.lower, resistance.upper, resistance.initial) == (20.0, 1e5, 2000.0)
    assert offset.per_experiment and (offset.scale, offset.lower) == (1e-5, None)
    assert (absorptance.lower, absorptance.upper) == (0.1, None)
    free('{ path = "thermal.tau_s", initial = 5.0 }')
    _bad(tmp_path, capsys, good, toml, "fit.free[0].initial", "(0.0001, 2.0) [s]", "device")


def test_missing_waveform_needs_description_or_log(good, tmp_path, capsys):
    text = (
        (good / "experiment.toml")
        .read_text()
        .replace(
            'waveform = { type = "pulse_train", power_mW = 10, period_ms = 400, n_pulses = 3, '
            "delay_ms = 200 }\n",
            "",
        )
    )
    (good / "experiment.toml").write_text(text)
    _bad(
        tmp_path, capsys, good, good / "experiment.toml", "runs[1].waveform", "laser_mW", line=16
    )  # the run's [[runs]] line: the key is missing


def test_input_error_format():
    err = InputError("is not a number", file="a.csv", line=7, field="y_px")
    assert str(err) == "a.csv:7: y_px: is not a number"


def test_generate_script_reproduces_committed_data(tmp_path):
    """The embedded data are exactly what the committed script makes (provenance)."""
    subprocess.run(
        [sys.executable, str(EMBEDDED / "generate.py"), "--out", str(tmp_path)],
        check=True,
        capture_output=True,
        cwd=ROOT,
    )
    for name in ("experiment.toml", "truth.json"):
        assert (tmp_path / name).read_text() == (EMBEDDED / name).read_text(), name
    csvs = sorted(p.name for p in EMBEDDED.glob("*.csv"))
    assert len(csvs) == 9 and csvs == sorted(p.name for p in tmp_path.glob("*.csv"))
    for name in csvs:
        a = np.genfromtxt(EMBEDDED / name, delimiter=",", names=True)
        b = np.genfromtxt(tmp_path / name, delimiter=",", names=True)
        for col in a.dtype.names:
            np.testing.assert_allclose(a[col], b[col], atol=2e-4, equal_nan=True)
    truth = json.loads((EMBEDDED / "truth.json").read_text())
    assert (
        truth["seed"]
        and truth["parameters"]["thermal.tau_s"]["value"]
        != truth["parameters"]["thermal.tau_s"]["nominal"]
    )


def test_known_noise_from_the_tracker_column_and_from_the_camera(good, tmp_path, capsys):
    """A `sigma_px` column (what `greybox track` writes) becomes each frame's known noise in
    SI; `[camera] noise_um` declares one level for every reading; mixing runs with and
    without the column is a located error."""
    t, y = _frames()
    for name, shift in (("est", 0.0), ("val", 2.0)):
        rows = ["t_s,y_px,sigma_px"] + [
            f"{a:.6f},{b - shift:.4f},{0.05 + 0.01 * (k % 3):.3f}"
            for k, (a, b) in enumerate(zip(t, y))
        ]
        (good / f"{name}.csv").write_text("\n".join(rows) + "\n")
    fs = load_experiment_set(good)
    e = fs.estimation[0]
    np.testing.assert_allclose(e.sigma[:3, 0], np.array([0.05, 0.06, 0.07]) * 0.645e-6)
    assert "sigma" not in fs.fit_options

    _write_csv(good / "val.csv", t, y)  # no noise column in one run
    _bad(tmp_path, capsys, good, good / "experiment.toml", "runs", "per-frame noise")

    for name in ("est", "val"):
        _write_csv(good / f"{name}.csv", t, y)
    text = (good / "experiment.toml").read_text()
    text = text.replace("um_per_px = 0.645", "um_per_px = 0.645\nnoise_um = 0.04")
    (good / "experiment.toml").write_text(text)
    fs = load_experiment_set(good)
    assert fs.fit_options["sigma"] == pytest.approx(0.04e-6)
    assert fs.estimation[0].sigma is None


def test_input_outside_its_channel_range_is_refused_at_its_line(good, tmp_path, capsys):
    """A logged laser power below 0 (the channel's declared minimum) is refused, naming the
    file, the line of the first bad row and the column."""
    t, y = _frames()
    laser = np.where(t > 0.2, 20.0, 0.0)
    laser[7] = -3.0
    _write_csv(good / "est.csv", t, y, laser=laser)
    text = (good / "experiment.toml").read_text()
    text = text.replace(
        'waveform = { type = "pulse_train", power_mW = 20, period_ms = 400, n_pulses = 3, '
        "delay_ms = 200 }",
        'waveform = { type = "logged" }',
        1,
    )
    (good / "experiment.toml").write_text(text)
    _bad(tmp_path, capsys, good, good / "est.csv", "laser_mW", "below 0", line=9)


def test_process_noise_folder_is_what_its_script_makes(tmp_path):
    """experiments/chevron_process/ (results.md's data) is exactly what its generate.py makes."""
    folder = ROOT / "experiments" / "chevron_process"
    spec = importlib.util.spec_from_file_location(
        "chevron_process_generate", folder / "generate.py"
    )
    gen = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(gen)
    gen.main(tmp_path)
    made = sorted(p.name for p in tmp_path.iterdir())
    assert made == sorted(
        p.name for p in folder.iterdir() if p.suffix in (".csv", ".toml", ".json")
    )
    for name in made:
        assert (tmp_path / name).read_text() == (folder / name).read_text(), name
