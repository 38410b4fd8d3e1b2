"""A device's model code is tried at load: one simulation traced abstractly, bounded in time.

A device file whose `linear_dynamics` loops forever when traced, or whose `build` loops for
one option, stops at load with exit 2 naming the file and the looping line
(GREYBOX_DEVICE_TIMEOUT_S = 2 s), nothing written; a
device whose model method raises for one candidate's option stops `compare` at load, naming
the raising line, before any candidate is fitted (no "start" progress line).
"""

import os
import subprocess
import sys
from pathlib import Path

import pytest

from greybox.cli import main
from tests.test_user_code import _example, _experiment, _line_of

ROOT = Path(__file__).resolve().parents[1]
DYNAMICS = "        m, k, c = self.mass_kg, self.stiffness_N_per_m, self.damping_N_s_per_m"


GOOD_BUILD = "def build(*, mass_kg: float = 1.0):"
# where the device's code never returns: (edit of the example, the looping lines, [model])
HANGS = {
    "dynamics when traced": (
        lambda s: s.replace(DYNAMICS, "        while True:\n            pass\n" + DYNAMICS),
        "trial simulation", ""),
    "build for an option": (
        lambda s: s.replace(GOOD_BUILD, GOOD_BUILD + "\n    while mass_kg > 2.5:\n"
                            "            pass"),
        "building device", "mass_kg = 3.0\n"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(HANGS))
def test_device_code_that_never_returns_stops_at_load(tmp_path, case):
    edit, what, model = HANGS[case]
    text = edit(_example())
    exp, out = _experiment(tmp_path, text, model), tmp_path / "out"
    env = {**os.environ, "GREYBOX_DEVICE_TIMEOUT_S": "2", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(  # a subprocess: without the bound the test fails, never hangs
        [sys.executable, "-m", "greybox", "fit", str(exp), "--out", str(out), "--quiet"],
        capture_output=True, text=True, timeout=90, env=env,
    )  # fmt: skip
    err = proc.stderr
    assert proc.returncode == 2, err
    looping = [i + 1 for i, line in enumerate(text.splitlines()) if "while " in line or
               line.strip() == "pass"]  # fmt: skip
    assert any(f"{exp / 'msd.py'}:{n}:" in err for n in looping), err
    assert what in err and "did not finish in 2 s" in err, err
    assert "Traceback" not in err and not out.exists()


BROKEN = '''

class HeavyMassSpringDamper(MassSpringDamper):
    def linear_dynamics(self):
        raise ArithmeticError("no model for heavy masses")


def build_any(*, mass_kg: float = 1.0):
    model = build(mass_kg=mass_kg)
    if mass_kg > 2.5:
        return HeavyMassSpringDamper(**{f: getattr(model, f) for f in model.__dataclass_fields__})
    return model
'''


def test_compare_blames_a_raising_method_at_load_before_any_fit(tmp_path, capsys):
    text = _example().replace("    build=build,", "    build=build_any,")
    text = text.replace("\nSPEC = ", BROKEN + "\n\nSPEC = ")
    candidates = (
        '\n[[candidates]]\nname = "light"\nmodel = { mass_kg = 1.0 }\n\n'
        '[[candidates]]\nname = "heavy"\nmodel = { mass_kg = 3.0 }\n'
    )
    exp, out = _experiment(tmp_path, text, candidates), tmp_path / "out"
    rc = main(["compare", str(exp), "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2, err
    raising = _line_of(text, '        raise ArithmeticError("no model for heavy masses")')
    assert f"{exp / 'msd.py'}:{raising}:" in err and "no model for heavy masses" in err, err
    assert "trial simulation" in err and "Traceback" not in err, err
    assert "start 1/" not in err and not out.exists(), err  # nothing was fitted
