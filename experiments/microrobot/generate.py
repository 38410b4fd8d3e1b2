"""Make the synthetic tracked-pose data set `experiments/microrobot/` (fixed seed).

The laser-steered stick-slip micro-robot (`models/microrobot.py`) walks under pulse trains
of several powers and periods with the (world-fixed) spot at several known positions; a
30 fps camera tracks two body features (front, near the dimple; rear, between the feet) with
timestamp jitter, exposure averaging, tracking noise, dropped frames and one burst of
corrupted frames. The true model is simulated with fine sub-steps (a reference for the
coarser default the fit uses); the true parameters differ from the nominal ones and are
written to `truth.json` with the seed.

Usage (from the repository root):
    .venv/bin/python experiments/microrobot/generate.py [--out DIR]

Re-running it reproduces the committed files.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import jax

import greybox

jax.config.update("jax_enable_x64", True)
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np  # noqa: E402

from greybox.devices import LASER_POWER  # noqa: E402
from greybox.io import (  # noqa: E402
    pulse_train_description,
    run_csv,
    run_table,
    waveform_from_description,  # noqa: E402
)
from greybox.parameters import get_value, set_values  # noqa: E402
from greybox.waveforms import CameraDefects, record  # noqa: E402

microrobot = greybox.device_module("microrobot")  # noqa: E402

SEED = 20240611
# true values (nominal: 0.448, 1.9e-7 J/K, 0.3 uN, 5 N/m, 1.0)
TRUE = {
    "absorptance_left": 0.40,
    "thermal.frame_capacitance_J_per_K": 2.4e-7,
    "locomotion.foot_forward_N": 0.35e-6,
    "locomotion.stiffness_N_per_m": 5.0,
    "locomotion.turn_gain": 0.6,
}
TRUTH_SUBSTEPS = 16  # reference resolution of the generating model (the fit uses the default)
CAMERA = {"fps": 30.0, "exposure_ms": 10.0, "um_per_px": 0.645}  # 6.45 um pixels at 10x
JITTER_S = 1e-3
NOISE_UM = 0.065  # tracking noise, 1 sd (0.1 px)
DROP_FRACTION = 0.05
START_SPREAD_UM = 3.0  # the image origin is the marked start centre, known to a few um
DELAY_MS, TAIL_MS = 100.0, 200.0  # laser off before the first and after the last pulse
PULSE_SPAN_S = 0.8  # each run holds about 0.8 s of pulses
# (name, power mW, period ms, spot x um, spot y um); 50 % duty. Powers and periods separate
# the thermal gain from the play width and the time constant; spot offsets drive turning.
ESTIMATION = [
    ("e1_15mW_16ms_y60", 15, 16, 0, 60),
    ("e2_25mW_16ms_y60", 25, 16, 0, 60),
    ("e3_20mW_40ms_y60", 20, 40, 0, 60),
    ("e4_20mW_16ms_y30", 20, 16, 0, 30),
    ("e5_20mW_24ms_x30y45", 20, 24, 30, 45),
]
VALIDATION = [("v1_22mW_20ms_y50", 22, 20, 0, 50)]
BURST_RUN = "e2_25mW_16ms_y60"  # two corrupted frames (a tracking glitch), 3-6 um off
COLUMNS = ("f1_x_px", "f1_y_px", "f2_x_px", "f2_y_px")


def _pulse(power_mW: float, period_ms: float) -> dict:
    n_pulses = int(round(PULSE_SPAN_S * 1e3 / period_ms))
    return pulse_train_description(
        power_mW, period_ms, n_pulses=n_pulses, delay_ms=DELAY_MS, tail_ms=TAIL_MS
    )


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent)
    out = ap.parse_args(argv).out
    out.mkdir(parents=True, exist_ok=True)

    m_per_px = CAMERA["um_per_px"] * 1e-6
    camera = dict(exposure_s=CAMERA["exposure_ms"] * 1e-3, m_per_px=m_per_px)
    nominal = greybox.devices.with_camera(microrobot.SPEC.model(), **camera)
    truth_model = set_values(
        greybox.devices.with_camera(microrobot.SPEC.model(substeps=TRUTH_SUBSTEPS), **camera),
        list(TRUE),
        list(TRUE.values()),
    )
    rng = np.random.default_rng(SEED)
    runs = [(*r, "estimation") for r in ESTIMATION] + [(*r, "validation") for r in VALIDATION]
    offsets_um, n_frames, motion_um, run_toml = {}, {}, {}, []
    for name, power, period, spot_x, spot_y, role in runs:
        desc = _pulse(power, period)
        wave = waveform_from_description(desc, LASER_POWER, lambda msg, *_: ValueError(msg))[0]
        offset = np.round(rng.uniform(-START_SPREAD_UM, START_SPREAD_UM, 2), 3)
        offsets_um[name] = offset.tolist()
        settings = {"spot.x_m": spot_x * 1e-6, "spot.y_m": spot_y * 1e-6}
        run_model = set_values(
            truth_model,
            [*settings, "image_offset_x_m", "image_offset_y_m"],
            [*settings.values(), *(offset * 1e-6)],
        )
        defects = CameraDefects(
            fps=CAMERA["fps"],
            jitter_s=JITTER_S,
            noise_m=NOISE_UM * 1e-6,
            drop_fraction=DROP_FRACTION,
            burst_length=2 if name == BURST_RUN else 0,
            burst_size_m=3e-6,
        )
        exp, clean = record(
            run_model, wave, name=name, defects=defects, seed=int(rng.integers(2**31)), role=role
        )
        motion_um[name] = float(np.hypot(*(clean[-1, :2] - clean[0, :2])) * 1e6)
        y_px = exp.y / m_per_px
        columns = {c: (y_px[:, j], 4) for j, c in enumerate(COLUMNS)}
        (out / f"{name}.csv").write_text(run_csv(exp.t_s, columns))
        n_frames[name] = exp.n_frames
        run_toml.append(run_table(name, role, desc, settings))

    n_est = sum(n_frames[r[0]] for r in ESTIMATION)
    n_val = sum(n_frames[r[0]] for r in VALIDATION)
    description = (
        f"Laser-steered stick-slip micro-robot, two body features tracked on a 30 fps "
        f"camera: {len(ESTIMATION)} estimation runs (15-25 mW, 16-40 ms periods, "
        f"spot at 30-60 um left of the start axis; {n_est} frames) and one "
        f"validation run ({n_val} frames). Synthetic data with known truth "
        "(truth.json)."
    )
    toml = f'''# Synthetic tracked-pose data set (made by generate.py, seed {SEED}).
# The file format is documented in experiments/README.md.

[experiment]
device = "microrobot"   # models/microrobot.py (play-operator contacts)
description = "{description}"

[camera]
fps = {CAMERA["fps"]:g}                  # nominal frame rate [frames/s]
exposure_ms = {CAMERA["exposure_ms"]:g}          # exposure time [ms]: frames average the motion
um_per_px = {CAMERA["um_per_px"]:g}         # image scale [um per pixel]: 6.45 um pixels at 10x

[fit]
loss = "huber"             # robust to the corrupted burst in {BURST_RUN}
# The device's standard list: thermal gain (left absorptance) and frame heat capacity (time
# constant), foot friction and leg stiffness with log-normal priors (the pose fixes only the
# play width W = (F_a + F_b)/k), the turning gain, and one image offset pair per run.
free = ["absorptance_left", "thermal.frame_capacitance_J_per_K", "locomotion.foot_forward_N",
        "locomotion.stiffness_N_per_m", "locomotion.turn_gain", "image_offset_x_m",
        "image_offset_y_m"]

# One [[runs]] table per CSV: waveform = the commanded laser (power in mW, times in ms);
# settings = the known spot centre for the run [m], in the start-body frame.
'''
    (out / "experiment.toml").write_text(toml + "\n" + "\n".join(run_toml))

    units = {p.path: p.unit for p in microrobot.PARAMETERS}
    truth = {
        "note": "True values used by generate.py; a fit of this folder should recover the "
        "identifiable free ones within their 95 % intervals.",
        "generator": "experiments/microrobot/generate.py",
        "seed": SEED,
        "device": microrobot.NAME,
        "truth_substeps": TRUTH_SUBSTEPS,
        "parameters": {
            p: {"value": v, "unit": units[p], "nominal": float(get_value(nominal, p))}
            for p, v in TRUE.items()
        },
        "play_width_m": {
            "value": float(
                set_values(nominal, list(TRUE), list(TRUE.values())).locomotion.play_width_m()
            ),
            "unit": "m",
            "nominal": float(nominal.locomotion.play_width_m()),
        },
        "image_offset_um": offsets_um,
        "motion_um": {k: round(v, 3) for k, v in motion_um.items()},
        "camera": {
            **CAMERA,
            "jitter_ms": JITTER_S * 1e3,
            "noise_um": NOISE_UM,
            "drop_fraction": DROP_FRACTION,
            "burst_run": BURST_RUN,
            "burst_frames": 2,
        },
        "frames": n_frames,
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    print(f"wrote {len(runs)} runs ({n_est} estimation + {n_val} validation frames) to {out}")


if __name__ == "__main__":
    main()
