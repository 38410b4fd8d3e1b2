"""Generate the synthetic electro-thermal chevron data of this folder (fixed seed).

Writes, next to this script:
- `table.csv` (`amplitude_V,frequency_Hz,y_pp_um`): periodic steady-state peak-to-peak shuttle
  displacement under a 0-to-amplitude square wave (50 % duty), on the thesis grid (0-24 V in
  2 V steps x 0-400 Hz in 10 Hz steps; 0 Hz = DC limit), with Gaussian interferometer noise;
- `force_readings.csv` (`voltage_V,repeat,sensor_mV`): piezoresistive sensor bridge output at DC
  voltages 0-20 V in 2 V steps, 5 repeats each, with repeat-to-repeat scatter;
- `truth.json`: every generating value (model, sensor, noise, seed).

Run: .venv/bin/python experiments/electrothermal/generate.py
"""

from __future__ import annotations

import json
import pathlib
import sys

import jax

import greybox

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

from greybox.io import atomic_output_file  # noqa: E402

ec = greybox.device_module("electrothermal_chevron")  # noqa: E402

HERE = pathlib.Path(__file__).resolve().parent
SEED = 2012
AMPLITUDES_V = np.arange(0.0, 25.0, 2.0)
FREQUENCIES_HZ = np.arange(0.0, 401.0, 10.0)
NOISE_UM = 0.1  # interferometer repeatability [assumed], the size of the thesis RMSE (0.13 um)
FORCE_VOLTAGES_V = np.arange(0.0, 21.0, 2.0)
N_REPEATS = 5
SENSOR_NOISE_MV = 2.0  # repeat scatter of the sensor reading ("wide deviations", thesis §5.5)
SENSOR = ec.ForceSensor(
    length_m=1e-3, thickness_m=50e-6, gauge_factor=100.0, bridge_V=5.0, stiffness_N_per_m=1000.0
)  # [assumed]: the thesis gives no AE801 constants
N_STEPS = 64


def main() -> None:
    rng = np.random.default_rng(SEED)
    truth = ec.SPEC.model()
    a, f = (g.ravel() for g in np.meshgrid(AMPLITUDES_V, FREQUENCIES_HZ, indexing="ij"))
    _, pp = greybox.waveforms.square_wave_response(truth, a, f, n_steps=N_STEPS)
    y_um = pp * 1e6 + rng.normal(0.0, NOISE_UM, pp.shape)
    with atomic_output_file(HERE / "table.csv") as tmp:
        np.savetxt(
            tmp,
            np.column_stack([a, f, y_um]),
            delimiter=",",
            fmt=["%.1f", "%.1f", "%.5f"],
            header="amplitude_V,frequency_Hz,y_pp_um",
            comments="",
        )

    volts = np.repeat(FORCE_VOLTAGES_V, N_REPEATS)
    repeat = np.tile(np.arange(1, N_REPEATS + 1), FORCE_VOLTAGES_V.size)
    force = np.asarray(ec.force_predictor(SENSOR.stiffness_N_per_m)(truth, volts))
    mv = SENSOR.sensor_V(force) * 1e3 + rng.normal(0.0, SENSOR_NOISE_MV, volts.size)
    with atomic_output_file(HERE / "force_readings.csv") as tmp:
        np.savetxt(
            tmp,
            np.column_stack([volts, repeat, mv]),
            delimiter=",",
            fmt=["%.1f", "%d", "%.5f"],
            header="voltage_V,repeat,sensor_mV",
            comments="",
        )

    info = {
        "seed": SEED,
        "device": ec.NAME,
        "model": {
            "thermal.tau_s": ec.NOMINAL_TAU_S,
            "thermal.resistance_K_per_W": ec.NOMINAL_RESISTANCE_K_PER_W,
            "joule.resistance_ohm": ec.NOMINAL_R0_OHM,
            "joule.tcr_per_K": ec.NOMINAL_TCR_PER_K,
            "beam_length_m": ec.BEAM_LENGTH_M,
            "angle_rad": ec.ANGLE_RAD,
            "beam_width_m": ec.BEAM_WIDTH_M,
            "beam_thickness_m": ec.BEAM_THICKNESS_M,
            "cte_per_K": ec.CTE_SI_PER_K,
            "youngs_Pa": ec.YOUNGS_SI_PA,
            "beam_fraction": 1.0,
        },
        "table": {
            "duty": 0.5,
            "noise_um": NOISE_UM,
            "n_steps_per_phase": N_STEPS,
            "amplitudes_V": AMPLITUDES_V.tolist(),
            "frequencies_Hz": FREQUENCIES_HZ.tolist(),
        },
        "force": {
            "voltages_V": FORCE_VOLTAGES_V.tolist(),
            "n_repeats": N_REPEATS,
            "sensor_noise_mV": SENSOR_NOISE_MV,
            "sensor": {
                "length_m": SENSOR.length_m,
                "thickness_m": SENSOR.thickness_m,
                "gauge_factor": SENSOR.gauge_factor,
                "bridge_V": SENSOR.bridge_V,
                "resistor_position": SENSOR.resistor_position,
                "stiffness_N_per_m": SENSOR.stiffness_N_per_m,
            },
        },
    }
    with atomic_output_file(HERE / "truth.json") as tmp:
        tmp.write(json.dumps(info, indent=2) + "\n")
    print(f"wrote table.csv ({a.size} rows), force_readings.csv ({volts.size} rows), truth.json")


if __name__ == "__main__":
    main()
