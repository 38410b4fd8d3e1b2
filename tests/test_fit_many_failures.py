"""`greybox fit-many` survives its worst member (issue 27).

Four folders of one user device (the DEVELOPING.md mass-spring-damper), three with data from
scipy's `lsim` of known stiffness and damping and one whose copy of the device outputs NaN:
the three are written and recover their spring constants, the fourth is reported by
name, exit 1, and no figure is drawn from a NaN; a device whose `linear_dynamics` raises is
reported at its file and line while the others are written. Mixed free lists, bad Dask
settings and a missing ``distributed`` extra are refused before any fit (exit 2, nothing
written).
"""

import json
import re
import socket
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from scipy import signal

from greybox.cli import main

ROOT = Path(__file__).resolve().parents[1]
MASS, C_TRUE = 1.0, 2.0
STIFF = {"d1": 30.0, "d2": 40.0, "d3": 50.0}


def _example() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    return re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, re.S).group(1)


def _truth(t, k):
    sys_ = signal.lti([[0, 1], [-k / MASS, -C_TRUE / MASS]], [[0], [1 / MASS]], [[1, 0]], 0)
    grid = np.arange(0, t[-1] + 1e-3, 1e-3)
    _, y, _ = signal.lsim(sys_, np.ones_like(grid), grid, interp=False)
    return np.interp(t, grid, y)


def _folder(root: Path, name: str, y, free='["stiffness_N_per_m", "damping_N_s_per_m"]',
            device="../msd.py:SPEC"):
    d = root / name
    d.mkdir()
    t = np.arange(0.01, 2, 0.02)
    (d / "run0.csv").write_text(
        "t_s,x_m\n" + "".join(f"{a:.3f},{b:.9g}\n" for a, b in zip(t, y(t)))
    )
    (d / "experiment.toml").write_text(
        f'[experiment]\ndevice = "{device}"\n\n'
        f"[fit]\nfree = {free}\nn_starts = 1\nmax_steps = 60\n\n"
        '[[runs]]\nname = "run0"\nfile = "run0.csv"\nrole = "estimation"\n'
        'waveform = { type = "steps", times_s = [0.0], F_N = [1.0], end_s = 2.0 }\n'
    )
    return d


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    root = tmp_path_factory.mktemp("many")
    (root / "msd.py").write_text(_example())
    rng = np.random.default_rng(4)
    folders = [
        _folder(root, n, lambda t, k=k: _truth(t, k) + 1e-5 * rng.normal(size=t.size))
        for n, k in STIFF.items()
    ]
    # the same device, except that its output is NaN: its fit cannot give a number
    bad = _folder(root, "bad", lambda t: _truth(t, 40.0), device="msd.py:SPEC")
    (bad / "msd.py").write_text(_example().replace("return x[:1]", "return x[:1] * jnp.nan"))
    folders.insert(2, bad)
    return root, folders


@pytest.fixture(scope="module")
def batch(lab):
    root, folders = lab
    out = root / "result"
    rc = main(["fit-many", *map(str, folders), "--out", str(out), "--quiet",
               "--no-device-figures", "--no-validate"])  # fmt: skip
    return rc, out


def test_valid_devices_are_written_and_the_bad_one_reported(batch, capsys):
    rc, out = batch
    assert rc == 1
    assert sorted(p.name for p in (out / "devices").iterdir()) == sorted(STIFF)
    for name, k in STIFF.items():
        doc = json.loads((out / "devices" / name / "params.json").read_text())
        est = {p["name"]: p for p in doc["parameters"]}["stiffness_N_per_m"]
        assert abs(est["value"] - k) < max(4 * est["se"], 1e-3 * k), (name, est)
    md = (out / "batch.md").read_text()
    assert "Devices that failed (1)" in md and "- bad:" in md
    rows = (out / "batch.csv").read_text().splitlines()
    assert sum(r.startswith("bad,failed") for r in rows) == 1
    assert (out / "figures" / "histograms.png").is_file()


def _refused(argv, capsys, field, seconds=15):
    t0 = time.perf_counter()
    assert main(argv) == 2
    assert time.perf_counter() - t0 < seconds
    err = capsys.readouterr().err
    assert f"{field}:" in err, err
    return err


def test_mixed_free_lists_are_refused_before_any_fit(lab, tmp_path, capsys):
    root, folders = lab
    other = _folder(tmp_path, "d4", lambda t: _truth(t, 45.0), free='["stiffness_N_per_m"]')
    (tmp_path / "msd.py").write_text(_example())
    out = tmp_path / "out"
    err = _refused(["fit-many", str(folders[0]), str(other), "--out", str(out)], capsys, "FOLDER")
    assert "d1" in err and "d4" in err and "Nothing was fitted" in err and not out.exists()


@pytest.mark.parametrize(
    "extra, field",
    [(["--workers", "0"], "--workers"), (["--memory-budget-mb", "0"], "--memory-budget-mb"),
     (["--memory-budget-mb", "-5"], "--memory-budget-mb"),
     (["--memory-budget-mb", "nan"], "--memory-budget-mb"),
     (["--scheduler", "not an address"], "--scheduler")],
)  # fmt: skip
def test_bad_settings_are_refused_before_the_work(lab, tmp_path, capsys, extra, field):
    root, folders = lab
    out = tmp_path / "out"
    _refused(["fit-many", str(folders[0]), "--out", str(out), *extra], capsys, field)
    assert not out.exists()


def test_an_unreachable_scheduler_is_refused_quickly(lab, tmp_path, capsys):
    root, folders = lab
    with socket.socket() as s:  # a port nobody listens on
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    argv = ["fit-many", str(folders[0]), "--out", str(tmp_path / "o"),
            "--scheduler", f"tcp://127.0.0.1:{port}"]  # fmt: skip
    err = _refused(argv, capsys, "--scheduler", seconds=10)
    assert "cannot reach" in err


def test_a_missing_extra_names_the_pip_install(lab, tmp_path, capsys, monkeypatch):
    root, folders = lab
    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    argv = ["fit-many", str(folders[0]), "--out", str(tmp_path / "o"), "--scheduler", "local"]
    err = _refused(argv, capsys, "--scheduler")
    assert 'pip install "greybox[distributed]"' in err


def test_a_device_whose_code_raises_does_not_lose_the_batch(lab, tmp_path, capsys):
    root, folders = lab
    raiser = _folder(tmp_path, "raiser", lambda t: _truth(t, 40.0), device="msd.py:SPEC")
    text = _example().replace(
        "        m, k, c = self.mass_kg,", "        raise RuntimeError('no dynamics today')\n"
        "        m, k, c = self.mass_kg,"
    )  # fmt: skip
    (raiser / "msd.py").write_text(text)
    out = tmp_path / "out"
    argv = ["fit-many", str(folders[0]), str(raiser), str(folders[1]), "--out", str(out),
            "--quiet", "--no-device-figures", "--no-validate"]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    line = text.splitlines().index("        raise RuntimeError('no dynamics today')") + 1
    assert "device raiser failed" in err and f"{raiser / 'msd.py'}:{line}" in err, err
    assert sorted(p.name for p in (out / "devices").iterdir()) == ["d1", "d2"]


def test_a_device_refused_by_name_is_left_out_and_the_rest_batched(lab, tmp_path, capsys):
    """A device whose data cannot determine its parameters (two readings, two parameters)
    loads, but the batch refuses it by name before solving any device: it is reported with
    that reason and the others are fitted together in one batch, not one by one."""
    root, folders = lab
    few = _folder(tmp_path, "few", lambda t: np.where(t < 0.04, _truth(t, 40.0), np.nan))
    (tmp_path / "msd.py").write_text(_example())
    out = tmp_path / "out"
    argv = ["fit-many", str(folders[0]), str(few), str(folders[1]), "--out", str(out),
            "--no-device-figures", "--no-validate"]  # fmt: skip
    assert main(argv) == 1
    err = capsys.readouterr().err
    assert "device few: experiments: 2 valid frames cannot determine 2 parameters" in err, err
    assert "fitting the other 2 together" in err and "one by one" not in err, err
    assert sorted(p.name for p in (out / "devices").iterdir()) == ["d1", "d2"]
    assert "- few: experiments: 2 valid frames cannot determine 2 parameters" in (
        out / "batch.md"
    ).read_text()
    for name in ("d1", "d2"):
        doc = json.loads((out / "devices" / name / "params.json").read_text())
        est = {p["name"]: p for p in doc["parameters"]}["stiffness_N_per_m"]
        assert abs(est["value"] - STIFF[name]) < max(4 * est["se"], 1e-3 * STIFF[name])
