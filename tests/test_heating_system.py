"""experiments/heating_system: a real record (DaISy) with a user-written device in its folder.

The fits take ~40 s (results.md gives the commands); here the folder's contract is checked
cheaply: it loads as a process-noise fit of its own device, the readings are in kelvin, every
candidate loads, and the ARX rows of results.md are what `arx.py` prints now.
"""

import subprocess
import sys
from pathlib import Path

import numpy as np

from greybox.io._experiment_set import candidate_names, load_experiment_set

FOLDER = Path(__file__).resolve().parents[1] / "experiments" / "heating_system"


def test_folder_loads_its_own_device_with_process_noise():
    fs = load_experiment_set(FOLDER)
    assert fs.device_name == "lamp_plate" and fs.noise is not None
    assert [e.n_frames for e in fs.estimation] == [400]
    assert [e.n_frames for e in fs.validation] == [401]
    first = fs.estimation[0]
    assert np.isclose(first.y[0], 129.32 + 273.15)  # degC in the file, K inside
    assert fs.estimation[0].settings["initial_T_K"] == first.y[0]  # run_settings hook
    # the lamp at rest at the drive before each run: the file's settings
    assert [e.settings["initial_lamp_V"] for e in (*fs.estimation, *fs.validation)] == [6.0, 4.0]
    names = candidate_names(FOLDER)
    assert names[1] == "plate + thermocouple lag"
    for i in range(len(names)):
        assert load_experiment_set(FOLDER, candidate=i).candidate == names[i]


def test_results_hold_what_arx_py_prints():
    out = subprocess.run(
        [sys.executable, str(FOLDER / "arx.py")], capture_output=True, text=True, check=True
    ).stdout
    results = (FOLDER / "results.md").read_text()
    rows = [line for line in out.splitlines() if line.startswith("| [")]
    assert len(rows) == 3
    for row in rows:
        order, k, est, val = [c.strip() for c in row.strip("|").split("|")]
        assert f"| ARX {order} + offset | {k} | {est} | {val} |" in results, row
