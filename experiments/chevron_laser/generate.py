"""Make the embedded camera data set `experiments/chevron_laser/` (synthetic, fixed seed).

It mirrors the thesis's laser-chevron experiments (Yelike 2012, §3.1: 5-30 mW, 200-1000 ms
periods, 50 % duty, shuttle displacement tracked on video): six estimation runs and a
separate validation set, recorded by a simulated 30 fps camera with timestamp jitter,
tracking noise, dropped frames and one burst of corrupted frames. The true parameters
differ from the model's nominal values, so a fit has something to recover; they are written
to `truth.json` together with the seed.

Usage (from the repository root):
    .venv/bin/python experiments/chevron_laser/generate.py [--out DIR]

Re-running it reproduces the committed files (tests/test_experiment_files.py checks this).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import jax

import greybox

jax.config.update("jax_enable_x64", True)

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

chevron_laser = greybox.device_module("chevron_laser")  # noqa: E402

SEED = 20120815
TRUE = {"absorptance": 0.62, "thermal.tau_s": 0.045}  # nominal: 0.67 and 0.040 s
CAMERA = {"fps": 30.0, "exposure_ms": 10.0, "um_per_px": 0.645}  # 6.45 um pixels at 10x
JITTER_S = 2e-3
NOISE_UM = 0.05  # tracking noise, 1 sd (~0.08 px)
DROP_FRACTION = 0.05
REST_PX = 312.0  # shuttle position in the image, px (each run adds a few px of re-focusing)
REST_SPREAD_PX = 4.0
DELAY_MS, TAIL_MS = 300.0, 700.0  # laser off before the first and after the last pulse
PULSE_SPAN_S = 10.0  # each run holds about 10 s of pulses
# (name, power mW, period ms); the thesis's six estimation runs, then new settings
ESTIMATION = [
    ("e1_5mW_200ms", 5, 200),
    ("e2_10mW_200ms", 10, 200),
    ("e3_10mW_300ms", 10, 300),
    ("e4_15mW_400ms", 15, 400),
    ("e5_20mW_600ms", 20, 600),
    ("e6_30mW_1000ms", 30, 1000),
]
VALIDATION = [("v1_8mW_250ms", 8, 250), ("v2_12mW_500ms", 12, 500), ("v3_25mW_800ms", 25, 800)]
BURST_RUN = "e4_15mW_400ms"  # eight corrupted frames (a tracking glitch), 2-4 um off
LOGGED_RUN = "v2_12mW_500ms"  # also logs laser_mW (checked against its description)


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
    model = greybox.devices.with_camera(
        chevron_laser.SPEC.model(), exposure_s=CAMERA["exposure_ms"] * 1e-3, m_per_px=m_per_px
    )
    truth_model = set_values(model, list(TRUE), list(TRUE.values()))
    rng = np.random.default_rng(SEED)
    runs = [(*r, "estimation") for r in ESTIMATION] + [(*r, "validation") for r in VALIDATION]
    offsets_px, n_frames, run_toml = {}, {}, []
    for name, power, period, role in runs:
        desc = _pulse(power, period)
        wave = waveform_from_description(desc, LASER_POWER, lambda msg, *_: ValueError(msg))[0]
        rest_px = round(REST_PX + rng.uniform(-REST_SPREAD_PX, REST_SPREAD_PX), 2)
        offsets_px[name] = rest_px
        run_model = set_values(truth_model, ["camera.offset_m"], [rest_px * m_per_px])
        defects = CameraDefects(
            fps=CAMERA["fps"],
            jitter_s=JITTER_S,
            noise_m=NOISE_UM * 1e-6,
            drop_fraction=DROP_FRACTION,
            burst_length=8 if name == BURST_RUN else 0,
            burst_size_m=2e-6,
        )
        exp, _ = record(
            run_model, wave, name=name, defects=defects, seed=int(rng.integers(2**31)), role=role
        )
        y_px = exp.y[:, 0] / m_per_px
        logged = name == LOGGED_RUN
        laser_mW = np.asarray(wave(exp.t_s)) * 1e3
        columns = {"y_px": (y_px, 4), **({"laser_mW": (laser_mW, None)} if logged else {})}
        (out / f"{name}.csv").write_text(run_csv(exp.t_s, columns))
        n_frames[name] = exp.n_frames
        run_toml.append(run_table(name, role, desc))

    n_est = sum(n_frames[r[0]] for r in ESTIMATION)
    n_val = sum(n_frames[r[0]] for r in VALIDATION)
    description = (
        f"Laser-heated chevron actuator, shuttle tracked on a 30 fps camera: six "
        f"estimation runs (5-30 mW, 200-1000 ms, 50 % duty; {n_est} frames) and "
        f"three validation runs ({n_val} frames). Synthetic data with known truth "
        "(truth.json)."
    )
    toml = f'''# Embedded default experiment set (synthetic; made by generate.py, seed {SEED}).
# The file format is documented in experiments/README.md.

[experiment]
device = "chevron_laser"   # models/chevron_laser.py
description = "{description}"

[camera]
fps = {CAMERA["fps"]:g}                  # nominal frame rate [frames/s]
exposure_ms = {CAMERA["exposure_ms"]:g}          # exposure time [ms]: frames average the motion
um_per_px = {CAMERA["um_per_px"]:g}         # image scale [um per pixel]: 6.45 um pixels at 10x

[fit]
loss = "huber"             # robust to the corrupted burst in {BURST_RUN}
# Fitted: absorptance and the thermal time constant (shared by all runs) and one camera
# offset per run (the shuttle's rest position in the image); everything else stays at the
# device's nominal value. This is the device's standard list, written out.
free = ["absorptance", "thermal.tau_s", "camera.offset_m"]

# One [[runs]] table per CSV; waveform = the commanded laser (power in mW, times in ms).
'''
    (out / "experiment.toml").write_text(toml + "\n" + "\n".join(run_toml))

    units = {p.path: p.unit for p in chevron_laser.PARAMETERS}
    truth = {
        "note": "True values used by generate.py; a fit of this folder should recover the "
        "free ones within their 95 % intervals.",
        "generator": "experiments/chevron_laser/generate.py",
        "seed": SEED,
        "device": chevron_laser.NAME,
        "parameters": {
            p: {"value": v, "unit": units[p], "nominal": float(get_value(model, p))}
            for p, v in TRUE.items()
        },
        "fixed_at_nominal": {
            p: {"value": float(get_value(model, p)), "unit": units[p]}
            for p in (
                "thermal.resistance_K_per_W",
                "spot.waist_m",
                "elongation.beam_fraction",
                "kinematics.angle_rad",
            )
        },
        "camera_offset_m": {n: round(px * m_per_px, 12) for n, px in offsets_px.items()},
        "camera_offset_px": offsets_px,
        "camera": {
            **CAMERA,
            "jitter_ms": JITTER_S * 1e3,
            "noise_um": NOISE_UM,
            "drop_fraction": DROP_FRACTION,
            "burst_run": BURST_RUN,
            "burst_frames": 8,
        },
        "frames": n_frames,
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")
    print(f"wrote {len(runs)} runs ({n_est} estimation + {n_val} validation frames) to {out}")


if __name__ == "__main__":
    main()
