"""Experiment folders of the three-state stochastic RC building data (tests/rc3_reference.py),
written as a user writes them: the device file beside the folder, one run CSV, and an
experiment.toml asking for a process-noise fit.

The inputs are logged every 30 min and the temperatures read at irregular frames: the run CSV
holds a row at every frame and at every input change (readings empty where there was none), the
inputs held from their row on (zero-order hold), so the folder describes the reference's
continuous-time experiment exactly.
"""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np

DEVICE = Path(__file__).with_name("rc_building_device.py")

THREE_STATE_NOISE = """\
[noise]
process = { air = [0], envelope = [1], heater = [2] }
"""


def run_csv(data: dict, outputs=("Ti", "Te")) -> str:
    """The run's CSV: t_s, the inputs (held from their row on) and the readings (K)."""
    t_frames, u_t, u = data["t_s"], data["u_times_s"], data["u_levels"]
    rows_t = np.unique(np.concatenate([t_frames, u_t[u_t <= t_frames[-1]]]))
    level = u[np.searchsorted(u_t, rows_t, side="right") - 1]
    frame = {float(t): k for k, t in enumerate(t_frames)}
    cols = {"Ti": 0, "Te": 1}
    head = ["t_s", "Ta_K", "Ph_W", "Ps_Wpm2"] + [f"{o}_K" for o in outputs]
    lines = [",".join(head)]
    for t, lv in zip(rows_t, level):
        k = frame.get(float(t))
        ys = [
            ""
            if k is None or not np.isfinite(data["y"][k, cols[o]])
            else f"{data['y'][k, cols[o]]:.9f}"
            for o in outputs
        ]
        lines.append(",".join([f"{t:.1f}", f"{lv[0]:.9f}", f"{lv[1]:.6f}", f"{lv[2]:.6f}", *ys]))
    return "\n".join(lines) + "\n"


def write_folder(root: Path, data: dict, *, spec="SPEC", outputs=("Ti", "Te"), extra="",
                 noise=THREE_STATE_NOISE, name="rc", validation: dict | None = None) -> Path:
    """root/devices/rc_building_device.py and root/<name>/ (experiment.toml + run.csv, and
    val.csv as a validation run when `validation` data are given)."""
    (root / "devices").mkdir(parents=True, exist_ok=True)
    shutil.copy(DEVICE, root / "devices" / DEVICE.name)
    folder = root / name
    folder.mkdir()
    (folder / "run.csv").write_text(run_csv(data, outputs))
    x0 = data["x0"]
    toml = f"""\
[experiment]
device = "../devices/{DEVICE.name}:{spec}"
description = "three-state stochastic RC building, numpy/scipy simulator (tests/rc3_reference.py)"
settings = {{ Ti0 = {float(x0[0])!r}, Te0 = {float(x0[1])!r}, Th0 = {float(x0[2])!r} }}

[fit]
noise_model = "process"
n_starts = 1

{noise}
{extra}
[[runs]]
name = "rc3"
file = "run.csv"
role = "estimation"
waveform = {{ type = "logged" }}
"""
    if validation is not None:
        (folder / "val.csv").write_text(run_csv(validation, outputs))
        toml += """
[[runs]]
name = "val"
file = "val.csv"
role = "validation"
waveform = { type = "logged" }
"""
    (folder / "experiment.toml").write_text(toml)
    return folder


def _free(**starts) -> str:
    """A candidate's free list with starting values (SI; bounds from the device table)."""
    cells = [f'{{ path = "{k}", lower = {lo!r}, upper = {hi!r}, initial = {v!r} }}'
             for k, (v, lo, hi) in starts.items()]
    return "free = [\n  " + ",\n  ".join(cells) + ",\n]"


_C, _R = (1e4, 1e9), (1e-5, 1.0)
CANDIDATES = f"""\
[[candidates]]
name = "one state"
model = {{ nodes = 1 }}
noise = {{ process = {{ air = [0] }} }}

[[candidates]]
name = "two states"
model = {{ nodes = 2 }}
nests = ["one state"]
{_free(Ci=(2e6, *_C), Ce=(1e7, *_C), Rie=(5e-3, *_R), Rea=(7e-3, *_R), Aw=(2.5, 1e-2, 100.0))}
noise = {{ process = {{ air = [0], envelope = [1] }} }}

[[candidates]]
name = "three states"
model = {{ nodes = 3 }}
nests = ["two states"]
{_free(Ci=(2e6, *_C), Ce=(1e7, *_C), Ch=(5e5, 1e3, 1e9), Rie=(5e-3, *_R), Rea=(7e-3, *_R),
       Rih=(2.5e-3, *_R), Aw=(2.5, 1e-2, 100.0))}
noise = {{ process = {{ air = [0], envelope = [1], heater = [2] }} }}
"""


def write_candidates_folder(root: Path, data: dict, candidates: str = CANDIDATES, name="cands"):
    """The air temperature alone (CTSM-R's classic case) with one-, two- and three-state
    candidates, each with its own noise table."""
    return write_folder(
        root, data, spec="SPEC_AIR", outputs=("Ti",), noise="", extra=candidates, name=name
    )
