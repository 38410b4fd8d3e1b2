"""Device code is the user's: it runs only with consent, and its failures are theirs.

- Trust: a params.json naming a device file outside its own folder imports nothing (exit 2,
  no marker written by the file's import) unless ``--trust-device`` names it; with consent the
  simulated response matches scipy's closed-form-equivalent `lsim` of the same ODE.
- Blame: a syntax error, a missing import, an exception or ``sys.exit`` at import, a
  ``build`` that raises for an option and a model method that raises are exit 2 naming the
  user's file and line; a device that hangs at import is stopped by the timeout.
"""

import json
import math
import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from greybox.cli import main

ROOT = Path(__file__).resolve().parents[1]
K, C, MASS = 55.0, 1.5, 2.0


def _example() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    m = re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, flags=re.S)
    return m.group(1)


def _params_doc(location: Path) -> dict:
    free = [
        {"path": p, "unit": u, "lower": 0.0, "upper": None, "per_experiment": False}
        for p, u in (("stiffness_N_per_m", "N/m"), ("damping_N_s_per_m", "N s/m"))
    ]
    return {
        "schema": "greybox.params/2",
        "device": {
            "name": "mass_spring_damper",
            "ref": "msd.py:SPEC",
            "source": "file",
            "location": str(location),
            "options": {"mass_kg": MASS},
        },
        "model": {
            "camera": {"m_per_px": None, "exposure_s": None, "fps": None},
            "fixed": {},
            "fitted": {"stiffness_N_per_m": K, "damping_N_s_per_m": C},
            "method": "zoh",
        },
        "free": free,
        "raw": [math.log(K), math.log(C)],
        "covariance_raw": [[1e-8, 0.0], [0.0, 1e-8]],
        "sigma": {"value": [2e-5]},
    }


@pytest.fixture()
def lab(tmp_path):
    """(params.json in result/, the device file in elsewhere/ that leaves a marker on import)."""
    marker = tmp_path / "imported.marker"
    device = tmp_path / "elsewhere" / "msd.py"
    device.parent.mkdir()
    device.write_text(_example() + f"\nopen({str(marker)!r}, 'w').write('ran')\n")
    result = tmp_path / "result"
    result.mkdir()
    params = result / "params.json"
    params.write_text(json.dumps(_params_doc(device)))
    return params, device, marker


WAVE = "pulse:F_N=2,period_ms=1000,duty=0.5,n=1"


def _truth(t):
    """Position [m] under a 2 N force on [0, 0.5) s, by scipy's lsim (an independent solver)."""
    sys_ = signal.lti([[0, 1], [-K / MASS, -C / MASS]], [[0], [1 / MASS]], [[1, 0]], 0)
    grid = np.arange(0, t[-1] + 1e-4, 1e-4)
    _, y, _ = signal.lsim(sys_, np.where(grid < 0.5 - 1e-9, 2.0, 0.0), grid, interp=False)
    return np.interp(t, grid, y)


def test_a_device_file_outside_the_params_folder_is_not_imported(lab, tmp_path, capsys):
    params, device, marker = lab
    out = tmp_path / "sim"
    rc = main(["simulate", "--params", str(params), "--waveform", WAVE, "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert not marker.exists() and not out.exists()
    assert str(params) in err and "--trust-device" in err and str(device) in err


def test_trust_device_runs_it_and_the_response_is_right(lab, tmp_path):
    params, device, marker = lab
    out = tmp_path / "sim"
    argv = ["simulate", "--params", str(params), "--waveform", WAVE, "--out", str(out)]
    assert main([*argv, "--trust-device", str(device)]) == 0
    assert marker.exists()
    table = np.genfromtxt(out / "simulation.csv", delimiter=",", names=True)
    col = next(n for n in table.dtype.names if n.startswith("x_") and n.count("_") == 1)
    t, y = table["t_s"], table[col] * {"m": 1.0, "mm": 1e-3, "um": 1e-6}[col[2:]]
    assert np.max(np.abs(y - _truth(t))) < 1e-3 * np.max(np.abs(y))


def test_a_device_file_beside_params_json_needs_no_consent(lab, tmp_path):
    params, device, marker = lab
    (params.parent / "msd.py").write_text(device.read_text())
    device.unlink()
    argv = ["simulate", "--params", str(params), "--waveform", WAVE, "--out", str(tmp_path / "s")]
    assert main(argv) == 0


def test_a_symlink_in_the_folder_to_code_elsewhere_is_refused(lab, tmp_path):
    params, device, marker = lab
    (params.parent / "msd.py").symlink_to(device)
    argv = ["simulate", "--params", str(params), "--waveform", WAVE, "--out", str(tmp_path / "s")]
    assert main(argv) == 2
    assert not marker.exists()


def test_design_refuses_the_same_params_json(lab, tmp_path):
    params, device, marker = lab
    rc = main(["design", "--params", str(params), "--power-max-mW", "10",
               "--run-duration-s", "1", "--out", str(tmp_path / "d")])  # fmt: skip
    assert rc == 2 and not marker.exists()


# -- the user's failures are reported as theirs ----------------------------------------------

GOOD_BUILD = "def build(*, mass_kg: float = 1.0):"


def _experiment(tmp_path, device_text: str, model: str = "") -> Path:
    exp = tmp_path / "exp"
    exp.mkdir()
    (exp / "msd.py").write_text(device_text)
    t = np.arange(0, 1, 0.01)
    (exp / "run0.csv").write_text("t_s,x_mm\n" + "".join(f"{a:.3f},{0.1 * a:.5f}\n" for a in t))
    (exp / "experiment.toml").write_text(
        f'[experiment]\ndevice = "msd.py:SPEC"\n\n[model]\n{model}\n'
        '[[runs]]\nname = "run0"\nfile = "run0.csv"\nrole = "estimation"\n'
        'waveform = { type = "steps", times_s = [0.0], F_N = [1.0], end_s = 1.0 }\n'
    )
    return exp


def _line_of(text: str, needle: str) -> int:
    return text.splitlines().index(needle) + 1


CASES = {
    "syntax error": (lambda s: s.replace("def output(self, x):", "def output(self, x)"),
                     "    def output(self, x)", "", "syntax error"),
    "missing import": (lambda s: s.replace("import equinox as eqx", "import no_such_package_xyz"),
                       "import no_such_package_xyz", "", "ModuleNotFoundError"),
    "raises at import": (lambda s: s + "raise RuntimeError('calibration file missing')\n",
                         "raise RuntimeError('calibration file missing')", "",
                         "calibration file missing"),
    "sys.exit at import": (lambda s: s + "import sys\nsys.exit(0)\n", "sys.exit(0)", "",
                           "sys.exit"),
    "build raises for an option": (
        lambda s: s.replace(GOOD_BUILD, GOOD_BUILD + "\n    if mass_kg > 2.5:\n"
                            "        raise ValueError('no such mass in this lab')"),
        "        raise ValueError('no such mass in this lab')", "mass_kg = 3.0\n",
        "no such mass in this lab"),
    "a method raises": (
        lambda s: s.replace("        m, k, c = self.mass_kg,",
                            "        raise ZeroDivisionError('bad dynamics')\n"
                            "        m, k, c = self.mass_kg,"),
        "        raise ZeroDivisionError('bad dynamics')", "", "bad dynamics"),
}  # fmt: skip


@pytest.mark.parametrize("case", list(CASES))
def test_a_failure_in_the_users_code_is_theirs(case, tmp_path, capsys):
    edit, line, model, words = CASES[case]
    text = edit(_example())
    exp = _experiment(tmp_path, text, model)
    out = tmp_path / "out"
    rc = main(["fit", str(exp), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert f"{exp / 'msd.py'}:{_line_of(text, line)}:" in err, err
    assert words in err and "Traceback" not in err and not out.exists()


def test_a_device_that_hangs_at_import_is_stopped(tmp_path):
    text = _example() + "while True:\n    pass\n"
    exp = _experiment(tmp_path, text)
    env = {**os.environ, "GREYBOX_DEVICE_TIMEOUT_S": "2", "PYTHONPATH": str(ROOT)}
    proc = subprocess.run(
        [sys.executable, "-m", "greybox", "describe", str(exp / "msd.py")],
        capture_output=True, text=True, timeout=120, env=env,
    )  # fmt: skip
    assert proc.returncode == 2, proc.stderr
    assert "did not finish in 2 s" in proc.stderr and str(exp / "msd.py") in proc.stderr


def test_describe_a_params_json_needs_the_same_consent(lab, capsys):
    params, device, marker = lab
    assert main(["describe", str(params)]) == 2 and not marker.exists()
    assert main(["describe", str(params), "--trust-device", str(device.parent)]) == 0
    out = capsys.readouterr().out
    assert "device mass_spring_damper" in out and marker.exists()


# a class whose creation is interrupted: Python wraps what a descriptor's `__set_name__`
# raises (here the signal handler's exception) in "RuntimeError: Error calling __set_name__"
_CLASS_CREATION = """
import signal, time


class _Field:
    def __set_name__(self, owner, name):
        {action}


class _Calibration:
    gain = _Field()
"""


@pytest.mark.parametrize(
    "action, code, words",
    [
        ("signal.raise_signal(signal.SIGINT)", 130, "interrupted; no result was written"),
        ("signal.raise_signal(signal.SIGTERM)", 143, "terminated (SIGTERM); no result was"),
        ("time.sleep(30)", 2, "did not finish in 1 s"),
    ],
    ids=["SIGINT", "SIGTERM", "time limit"],
)
def test_a_stop_while_the_users_class_is_created_is_the_stop(
    action, code, words, tmp_path, capsys, monkeypatch
):
    """A Ctrl-C, SIGTERM or the device time limit landing while the device file creates a
    class is that stop (exit 130/143, or the time limit's message), not "the device code
    raised RuntimeError: Error calling __set_name__" blamed on the user's line."""
    monkeypatch.setenv("GREYBOX_DEVICE_TIMEOUT_S", "1")
    exp = _experiment(tmp_path, _CLASS_CREATION.format(action=action) + _example())
    out = tmp_path / "out"
    rc = main(["fit", str(exp), "--out", str(out), "--quiet"])
    err = capsys.readouterr().err
    assert rc == code, err
    assert words in err and "RuntimeError" not in err and "Traceback" not in err, err
    assert not out.exists()
