"""Make `experiments/chevron_process/` (synthetic, fixed seed): a chevron whose temperature
carries process noise, for the process-noise (stochastic) fit.

One thermal node, tau dtheta/dt = R A F P(t) - theta, plus white noise of intensity
`Q_K2_PER_S` on theta, simulated exactly (the scalar Ornstein-Uhlenbeck step, ZOH laser on a
1 ms grid) with numpy; the shuttle's stroke from the mean beam rise 0.5 theta by the exact
rigid-link kinematics and the thesis geometry of tests/test_chevron_structures.py (not
greybox); a 30 fps camera with no exposure averaging (the Kalman filter models none) and
0.05 um tracking noise. Truth: truth.json. The temperature is in K and the reading in m, so
the noise intensity is in K^2/s, 1e14 x the output's m^2/s scale.

Usage (from the repository root):
    .venv/bin/python experiments/chevron_process/generate.py
"""

import json
import math
import sys
from pathlib import Path

import numpy as np
from scipy.special import erf

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))
from tests.test_chevron_structures import PAD, RHO_CP, WAIST, H, L, W, stroke_m  # noqa: E402

SEED = 20261128
TRUE = {"absorptance": 0.62, "thermal.tau_s": 0.045}
Q_K2_PER_S = 50.0  # process noise on the temperature
NOISE_UM, UM_PER_PX, FPS = 0.05, 0.645, 30.0
R_K_PER_W = 0.040 / (RHO_CP * (2 * L * W * H + PAD**2 * H))  # nominal (tau 40 ms), held
DT = 1e-3  # the simulator's grid [s]
DELAY_MS, TAIL_MS, SPAN_MS = 300, 700, 10_000
# (name, power mW, period ms, role); 50 % duty
RUNS = [
    ("e1_5mW_200ms", 5, 200, "estimation"),
    ("e2_10mW_200ms", 10, 200, "estimation"),
    ("e3_10mW_300ms", 10, 300, "estimation"),
    ("e4_15mW_400ms", 15, 400, "estimation"),
    ("e5_20mW_600ms", 20, 600, "estimation"),
    ("e6_30mW_1000ms", 30, 1000, "estimation"),
    ("v1_8mW_250ms", 8, 250, "validation"),
    ("v2_25mW_800ms", 25, 800, "validation"),
]


def simulate_run(power_mW, period_ms, offset_px, rng):
    """(frame times [s], readings [px]) of one run."""
    n_pulses = round(SPAN_MS / period_ms)
    spot = erf(math.sqrt(2) * (PAD / 2) / WAIST) ** 2  # Gaussian spot on the square pad
    drive = R_K_PER_W * TRUE["absorptance"] * spot * power_mW * 1e-3  # rise when on [K]
    tau = TRUE["thermal.tau_s"]
    n = round((DELAY_MS + n_pulses * period_ms + TAIL_MS) * 1e-3 / DT)
    ms = np.arange(n) * DT * 1e3 + 1e-6
    on = (ms >= DELAY_MS) & (ms < DELAY_MS + n_pulses * period_ms)
    on &= ((ms - DELAY_MS) % period_ms) < 0.5 * period_ms
    a = math.exp(-DT / tau)
    sd = math.sqrt(Q_K2_PER_S * tau * (1 - a * a) / 2)  # exact OU step
    theta = np.zeros(n + 1)
    for k in range(n):
        theta[k + 1] = a * theta[k] + (1 - a) * drive * on[k] + sd * rng.standard_normal()
    every = round(1 / FPS / DT)  # 33 ms
    frames = np.arange(0, n + 1, every)
    px = stroke_m(0.5 * theta[frames]) / (UM_PER_PX * 1e-6) + offset_px
    px = px + NOISE_UM / UM_PER_PX * rng.standard_normal(frames.size)
    return frames * DT, px, n_pulses


DESCRIPTION = (
    f"Laser-heated chevron whose temperature carries process noise ({Q_K2_PER_S:g} K^2/s), "
    "30 fps camera without exposure averaging: six estimation and two validation runs. "
    "Synthetic (generate.py, numpy), truth in truth.json."
)


# `greybox compare`: where the noise enters (the truth: on the temperature)
CANDIDATES = """
[[candidates]]
name = "thermal noise"
noise = { process = "all" }

[[candidates]]
name = "offset walk"
noise = { disturbances = ["ambient_random_walk"] }

[[candidates]]
name = "both"
noise = { process = "all", disturbances = ["ambient_random_walk"] }
nests = ["thermal noise", "offset walk"]
"""


def main(out=Path(__file__).resolve().parent):
    rng = np.random.default_rng(SEED)
    tables, offsets = [], {}
    for name, p, period, role in RUNS:
        offsets[name] = round(310.0 + rng.uniform(-4, 4), 2)
        t, px, n_pulses = simulate_run(p, period, offsets[name], rng)
        (out / f"{name}.csv").write_text(
            "t_s,y_px\n" + "".join(f"{a:.6f},{b:.5f}\n" for a, b in zip(t, px))
        )
        tables.append(
            f'[[runs]]\nname = "{name}"\nfile = "{name}.csv"\nrole = "{role}"\nwaveform = '
            f'{{ type = "pulse_train", power_mW = {p}, period_ms = {period}, duty = 0.5, '
            f"n_pulses = {n_pulses}, delay_ms = {DELAY_MS}, tail_ms = {TAIL_MS} }}\n"
        )
    head = f"""# Synthetic, made by generate.py (seed {SEED}): temperature with process noise.

[experiment]
device = "chevron_laser"
description = "{DESCRIPTION}"

[camera]
fps = {FPS:g}
exposure_ms = 0
um_per_px = {UM_PER_PX:g}

[fit]
noise_model = "process"    # Kalman-filter maximum likelihood
free = ["absorptance", "thermal.tau_s", "camera.offset_m"]

[noise]
process = "all"            # one intensity on the thermal state [K^2/s]

"""
    (out / "experiment.toml").write_text(head + "\n".join(tables) + CANDIDATES)
    truth = {
        "generator": "experiments/chevron_process/generate.py",
        "seed": SEED,
        "parameters": TRUE,
        "process.states_K2_per_s": Q_K2_PER_S,
        "measurement.y_m": NOISE_UM * 1e-6,
        "camera_offset_m": {k: round(v * UM_PER_PX * 1e-6, 12) for k, v in offsets.items()},
    }
    (out / "truth.json").write_text(json.dumps(truth, indent=2) + "\n")


if __name__ == "__main__":
    main()
