"""SIGINT and SIGTERM end every command the same way: exit 130 / 143, nothing partial.

`greybox compare` (two candidates of a small linear device, so each run is short) is sent a
signal at several moments, found from its own progress lines: while loading, while compiling,
while solving, between candidates and while writing. Every time the exit status is 130
(SIGINT) or 143 (SIGTERM) -- never a swallowed signal or a crash -- and the output
folder is either absent or a complete result, with no ``.partial-*`` folder beside it. (At
the last moment the run may have ended before the signal is sent: exit 0, complete result.)
"""

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]


def _example() -> str:
    text = (ROOT / "DEVELOPING.md").read_text()
    return re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, re.S).group(1)


@pytest.fixture(scope="module")
def folder(tmp_path_factory):
    exp = tmp_path_factory.mktemp("cmp")
    (exp / "msd.py").write_text(_example())
    t = np.arange(0, 2, 0.02)
    y = 0.02 * (1 - np.exp(-2 * t)) + 1e-4 * np.random.default_rng(0).normal(size=t.size)
    (exp / "run0.csv").write_text("t_s,x_m\n" + "".join(f"{a:.3f},{b:.6g}\n" for a, b in zip(t, y)))
    (exp / "experiment.toml").write_text(
        '[experiment]\ndevice = "msd.py:SPEC"\n\n[fit]\nfree = ["stiffness_N_per_m", '
        '"damping_N_s_per_m"]\n\n[[runs]]\nname = "run0"\nfile = "run0.csv"\n'
        'role = "estimation"\nwaveform = { type = "steps", times_s = [0.0], F_N = [1.0], '
        "end_s = 2.0 }\n\n"
        '[[candidates]]\nname = "light"\nmodel = { mass_kg = 1.0 }\n\n'
        '[[candidates]]\nname = "heavy"\nmodel = { mass_kg = 2.0 }\n'
    )
    return exp


@pytest.fixture(scope="module")
def cache(tmp_path_factory):
    """A JAX compilation cache shared by the runs (the later moments then cost seconds)."""
    return {
        "JAX_COMPILATION_CACHE_DIR": str(tmp_path_factory.mktemp("jax-cache")),
        "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS": "0",
        "JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES": "0",
    }


# (line of stderr to wait for, extra delay [s], signal)
MOMENTS = [
    ("candidate 1/2", 0.0, signal.SIGINT),  # loading the folder
    ("start 1/1", 0.0, signal.SIGTERM),  # compiling the first fit
    ("start 1/1", 1.0, signal.SIGINT),  # solving
    ("candidate 'light': AIC", 0.0, signal.SIGTERM),  # between candidates
    ("candidate 'heavy': AIC", 0.0, signal.SIGINT),  # writing the result
]


@pytest.mark.parametrize("line, delay, sig", MOMENTS, ids=[f"{m[0]}+{m[1]}" for m in MOMENTS])
def test_a_signal_at_any_moment_exits_cleanly(folder, cache, tmp_path, line, delay, sig):
    out = tmp_path / "result"
    env = {**os.environ, "PYTHONPATH": str(ROOT), **cache}
    proc = subprocess.Popen(
        [sys.executable, "-m", "greybox", "compare", str(folder), "--out", str(out)],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env,
    )  # fmt: skip
    seen = []
    try:
        for text in proc.stderr:
            seen.append(text)
            if line in text:
                time.sleep(delay)
                proc.send_signal(sig)
                break
        rest = proc.stderr.read()
        rc = proc.wait(timeout=120)
    finally:
        proc.kill()
    assert any(line in s for s in seen), "".join(seen)
    if rc == 0:  # only when the run had ended before the signal could land (the last moment)
        assert line.startswith("candidate 'heavy'") and (out / "compare.json").is_file()
    else:
        assert rc == (130 if sig == signal.SIGINT else 143), "".join(seen) + rest
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name or ".old-" in p.name]
    if out.exists():  # the signal came after the result was swapped in: it is complete
        assert {"compare.md", "compare.json", ".greybox-result"} <= {p.name for p in out.iterdir()}


def test_fit_started_with_sigint_ignored_still_stops_on_sigint(folder, cache, tmp_path):
    """A background job of a non-interactive shell starts with SIGINT ignored; once the
    command runs, SIGINT stops it like Ctrl-C (it was swallowed: exit 0 after the fit)."""
    out = tmp_path / "fit"
    env = {**os.environ, "PYTHONPATH": str(ROOT), **cache}
    proc = subprocess.Popen(
        [sys.executable, "-m", "greybox", "fit", str(folder), "--out", str(out)],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env,
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_IGN),
    )  # fmt: skip
    try:
        for text in proc.stderr:
            if "start 1/1" in text:
                proc.send_signal(signal.SIGINT)
                break
        rest = proc.stderr.read()
        rc = proc.wait(timeout=120)
    finally:
        proc.kill()
    assert rc == 130, rest
    assert not out.exists() and not [p for p in tmp_path.iterdir() if ".partial-" in p.name]
