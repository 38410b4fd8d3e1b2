"""A device written by a user, outside the repository, works end to end with no greybox edit.

The device file is the example in DEVELOPING.md ("Adding a device"), extracted verbatim, so the
documentation cannot drift from what runs. Its data come from scipy.signal.lsim (an
independent simulator of m x'' + c x' + k x = F with zero-order-hold input), and the fit must
recover the spring and damper within 3 standard errors; `greybox simulate --params` must then
rebuild the same model (mass option included) from params.json alone, once the user trusts the
device file (it lives outside the result folder).
"""

import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from greybox.cli import main

ROOT = Path(__file__).resolve().parents[1]
MASS, K_TRUE, C_TRUE, NOISE_M = 2.0, 55.0, 1.5, 2e-5
STEPS = ([0.0, 0.5, 1.5, 2.2], [0.0, 3.0, -1.0, 2.0], 3.0)  # times [s], force [N], end [s]


def _example() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    m = re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, flags=re.S)
    assert m, "DEVELOPING.md lost its device example"
    return m.group(1)


def _truth(t, times, levels):
    """Position [m] at `t` under the piecewise-constant force (scipy lsim, ZOH between edges)."""
    sys = signal.lti([[0, 1], [-K_TRUE / MASS, -C_TRUE / MASS]], [[0], [1 / MASS]], [[1, 0]], 0)
    grid = np.arange(int(round(max(t[-1], times[-1]) / 1e-4)) + 2) * 1e-4  # holds every edge
    force = np.asarray(levels)[np.searchsorted(times, grid + 1e-9, side="right") - 1]
    _, y, _ = signal.lsim(sys, force, grid, interp=False)
    return np.interp(t, grid, y)


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp("lab")
    (root / "my_devices").mkdir()
    (root / "my_devices" / "msd.py").write_text(_example())
    exp = root / "exp"
    exp.mkdir()
    times, levels, end = STEPS
    rng = np.random.default_rng(3)
    runs = []
    for i, scale in enumerate((1.0, 0.6)):
        t = np.arange(0.01, end, 0.01) + rng.uniform(-2e-3, 2e-3, size=299)
        t.sort()
        y = _truth(t, times, np.asarray(levels) * scale) + 0.004 + rng.normal(0, NOISE_M, t.size)
        y[[40, 41, 200]] = np.nan  # dropped frames
        rows = ["t_s,x_mm"] + [f"{a:.6f},{b * 1e3:.6f}" for a, b in zip(t, y)]
        (exp / f"run{i}.csv").write_text("\n".join(rows).replace("nan", "") + "\n")
        f = ", ".join(f"{v * scale:g}" for v in levels)
        runs.append(
            f'[[runs]]\nname = "run{i}"\nfile = "run{i}.csv"\nrole = "estimation"\n'
            f'waveform = {{ type = "steps", times_s = {times}, F_N = [{f}], end_s = {end} }}\n'
        )
    (exp / "experiment.toml").write_text(
        '[experiment]\ndevice = "../my_devices/msd.py:SPEC"\n\n[model]\nmass_kg = 2.0\n\n'
        "[fit]\nfree = [\n"
        '  "stiffness_N_per_m",\n  "damping_N_s_per_m",\n'
        '  { path = "readout.offset", per_run = true, scale = 1e-3 },\n]\n\n' + "\n".join(runs)
    )
    out = root / "result"
    assert main(["fit", str(exp), "--out", str(out), "--quiet", "--no-figures"]) == 0
    return root, exp, out


def test_user_device_is_fitted_from_its_own_file(lab):
    _, _, out = lab
    params = json.loads((out / "params.json").read_text())
    assert params["device"]["source"] == "file"
    assert params["device"]["name"] == "mass_spring_damper"
    assert params["device"]["options"] == {"mass_kg": 2.0}
    est = {p["name"]: p for p in params["parameters"]}
    for name, truth in (("stiffness_N_per_m", K_TRUE), ("damping_N_s_per_m", C_TRUE)):
        p = est[name]
        assert p["verdict"] == "identifiable"
        assert abs(p["value"] - truth) < 3 * p["se"], (name, p["value"], p["se"])


def test_simulate_rebuilds_the_fitted_user_model(lab, tmp_path):
    root, _, out = lab
    times, levels, end = STEPS
    t = np.arange(0.0, end, 0.005)
    force = np.asarray(levels)[np.searchsorted(times, t, side="right") - 1]
    wave = tmp_path / "force.csv"
    wave.write_text("t_s,F_N\n" + "\n".join(f"{a:.4f},{b:g}" for a, b in zip(t, force)) + "\n")
    sim = tmp_path / "sim"
    argv = ["simulate", "--params", str(out / "params.json"), "--waveform", str(wave),
            "--out", str(sim), "--dt-ms", "5"]  # fmt: skip
    # greybox fit copied the user's device file beside params.json: its own result runs as is
    assert len(list(out.glob("*.py"))) == 1
    assert main(argv) == 0
    # a result without that copy names a device file outside its folder: that needs consent
    bare = tmp_path / "result"
    shutil.copytree(out, bare)
    for p in bare.glob("*.py"):
        p.unlink()
    sim2 = tmp_path / "sim2"
    argv_bare = [*argv[:2], str(bare / "params.json"), *argv[3:-3], str(sim2), *argv[-2:]]
    assert main(argv_bare) == 2 and not sim2.exists()
    assert main([*argv_bare, "--trust-device", str(root / "my_devices")]) == 0
    table = np.genfromtxt(sim / "simulation.csv", delimiter=",", names=True)
    y_mm = table[table.dtype.names[1]]
    truth_mm = _truth(table["t_s"], times, levels) * 1e3
    # the fitted model (k, c within a few SE of the truth) reproduces the independent simulator
    assert np.max(np.abs(y_mm - truth_mm)) < 0.02 * np.max(np.abs(truth_mm))
