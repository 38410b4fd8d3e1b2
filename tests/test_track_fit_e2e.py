"""End to end: chevron parameters -> rendered microscope video -> `greybox track` ->
`greybox fit` -> the identifiable parameters come back within 3 standard errors.

The video is rendered from the model itself: the shuttle displacement is simulated at
sub-exposure instants (`greybox.video._render.exposure_times`, frame stamped at the END of its
exposure, as `greybox.blocks._camera.Camera` averages over [t - T_e, t]) with an
instantaneous camera, converted to px and drawn by `render_shuttle` (exact sub-pixel
translation, motion blur, shot/read noise, lamp drift, one glare frame). Everything after
that is the user's path: a lossless video file, the CLI tracker, an experiment folder, the
CLI fitter, params.json.
"""

import json

import numpy as np
import pytest

import greybox
from greybox._model.waveforms import PulseTrain
from greybox._simulate.simulate import simulate
from greybox.cli import main
from greybox.io._video import write_video
from greybox.video._render import exposure_times, render_shuttle

chevron_laser = greybox.device_module("chevron_laser")

TRUE_TAU_S = 0.050
TRUE_ABSORPTANCE = 0.55
UM_PER_PX = 0.5
EXPOSURE_S = 0.005
FPS = 100.0
# Laser off for the first 150 ms (15 frames: the reference), four 30 mW pulses of
# 200 ms (tau = 50 ms spans five frames), 100 ms tail: 105 frames.
PULSES = dict(power_W=0.030, period_s=0.200, duty=0.5, n_pulses=4, delay_s=0.150, tail_s=0.100)
REST_FRAMES = 12
GLARE_FRAME = 40

# JAX (imported by the fit) warns on any os.fork; subprocess forks only to exec ffmpeg at
# once, which is safe.
pytestmark = pytest.mark.filterwarnings("ignore:os.fork\\(\\) was called:RuntimeWarning")


@pytest.fixture(scope="module")
def tracked_run(tmp_path_factory):
    """(experiment folder with the tracked CSV, the rendered sequence)."""
    wave = PulseTrain(**PULSES)
    n = int(
        round(
            (PULSES["delay_s"] + PULSES["n_pulses"] * PULSES["period_s"] + PULSES["tail_s"]) * FPS
        )
    )
    t = np.arange(n) / FPS
    # Instantaneous camera (exposure 0, offset 0): the true position at each instant.
    truth_model = greybox.devices.with_camera(
        chevron_laser.SPEC.model(absorptance=TRUE_ABSORPTANCE, thermal__tau_s=TRUE_TAU_S),
        exposure_s=0.0,
        m_per_px=UM_PER_PX * 1e-6,
    )
    t_sub = exposure_times(t, EXPOSURE_S, n_sub=8)
    y_m = np.asarray(simulate(truth_model, wave, t_sub.ravel())).reshape(t_sub.shape)
    seq = render_shuttle(
        y_m / (UM_PER_PX * 1e-6), shape=(96, 128), seed=7, bad_frames={GLARE_FRAME: "glare"}
    )
    folder = tmp_path_factory.mktemp("e2e")
    video = write_video(folder / "video" / "run1.avi", seq.frames, fps=FPS)
    exp_dir = folder / "experiment"
    rc = main(
        [
            "track",
            str(video),
            "--roi",
            "32,16,64,64",
            "--um-per-px",
            str(UM_PER_PX),
            "--ref-frames",
            str(REST_FRAMES),
            "--out",
            str(exp_dir / "run1.csv"),
        ]
    )
    assert rc == 0
    p = PULSES
    (exp_dir / "experiment.toml").write_text(f"""\
[experiment]
device = "chevron_laser"
description = "rendered from known parameters (tests/test_track_fit_e2e.py)"

[camera]
um_per_px = {UM_PER_PX}
exposure_ms = {EXPOSURE_S * 1e3}
fps = {FPS}

[fit]
loss = "huber"
free = ["absorptance", "thermal.tau_s", "camera.offset_m"]

[[runs]]
name = "run1"
file = "run1.csv"
role = "estimation"
y_column = "y_um"
waveform = {{ type = "pulse_train", power_mW = {p["power_W"] * 1e3}, period_ms = {p["period_s"] * 1e3}, duty = {p["duty"]}, n_pulses = {p["n_pulses"]}, delay_ms = {p["delay_s"] * 1e3}, tail_ms = {p["tail_s"] * 1e3} }}
""")
    return exp_dir, seq


def _csv(path):
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    rows = [line.split(",") for line in lines[1:]]
    return {h: [r[i] for r in rows] for i, h in enumerate(header)}


def test_tracked_csv_matches_the_rendered_truth(tracked_run):
    exp_dir, seq = tracked_run
    cols = _csv(exp_dir / "run1.csv")
    reason = np.array(cols["reason"])
    assert list(np.flatnonzero(reason != "")) == [GLARE_FRAME]
    y_um = np.array(cols["y_um"], float)
    good = reason == ""
    # Truth in um from the render (exposure-averaged px x scale); <= 0.05 px RMS.
    err_px = (y_um[good] / UM_PER_PX) - seq.truth_px[good]
    assert np.sqrt(np.mean(err_px**2)) <= 0.05
    # The motion is real and large: several px of stroke.
    assert np.nanmax(y_um) / UM_PER_PX > 2.0


def test_fit_recovers_tau_and_absorptance_within_3_se(tracked_run, tmp_path):
    exp_dir, _ = tracked_run
    out = tmp_path / "result"
    assert main(["fit", str(exp_dir), "--out", str(out), "--quiet", "--no-figures"]) == 0
    doc = json.loads((out / "params.json").read_text())
    assert doc["model"]["camera"]["exposure_s"] == pytest.approx(EXPOSURE_S)
    assert doc["model"]["camera"]["m_per_px"] == pytest.approx(UM_PER_PX * 1e-6)
    est = {p["path"]: p for p in doc["parameters"] if p["experiment"] is None}
    for path, truth in (("thermal.tau_s", TRUE_TAU_S), ("absorptance", TRUE_ABSORPTANCE)):
        p = est[path]
        assert p["verdict"] == "identifiable", p
        assert p["se"] is not None and 0 < p["se"] < 0.05 * truth, p  # informative
        assert abs(p["value"] - truth) <= 3.0 * p["se"], (path, p["value"], truth, p["se"])
    # The glare frame (flagged by the tracker, NaN in the CSV) is a dropped frame, and the
    # per-run offset (zero: the reference is the device at rest) is found.
    assert doc["runs"]["run1"]["valid_frames"] == doc["runs"]["run1"]["frames"] - 1
    offset = next(p for p in doc["parameters"] if p["path"] == "camera.offset_m")
    assert abs(offset["value"]) <= max(3.0 * offset["se"], 0.01 * UM_PER_PX * 1e-6)
