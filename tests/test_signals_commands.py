"""SIGINT and SIGTERM end `track`, `design` and `fit-many` as they end `fit` and `compare`.

Each command runs in a child process; the signal is sent once the command's own handlers are
installed (read from /proc/PID/status: SIGTERM is caught only from then on), 0.5 s later
(while the command imports and reads its inputs) or 1-1.5 s later (decoding and tracking,
building the design's information matrix, loading and compiling the batch: well inside the
work, which lasts ~2.0 s after the handlers for `design` and ~2.6 s for `fit-many` on a
2-core machine with the suite's fast-compile XLA options, so the signal cannot come after
the command has finished). Every time the exit status is 130
(SIGINT) or 143 (SIGTERM), the message says nothing was written, and neither --out nor any
``.partial-*`` leftover exists. (`tests/test_signals.py` covers `compare` at five moments.)

A signal that lands while Python runs a garbage-collector callback (JAX's `_xla_gc_callback`
runs at every collection), a ``__del__`` or a weakref callback -- where an exception is
printed as "Exception ignored" and lost, and the command ran on for seconds -- stops the
command just after.
"""

import gc
import os
import re
import signal
import subprocess
import sys
import time
import weakref
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.skipif(not Path("/proc/self/status").is_file(), reason="needs /proc")


def _catches_sigterm(pid: int) -> bool:
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return False
    caught = int(re.search(r"^SigCgt:\s*([0-9a-f]+)", text, re.M).group(1), 16)
    return bool(caught >> (signal.SIGTERM - 1) & 1)


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    from greybox.io._video import write_video

    base = tmp_path_factory.mktemp("sig")
    frames = (np.random.default_rng(0).random((6000, 64, 64)) * 255).astype(np.uint8)
    video = write_video(base / "v.avi", frames, fps=30.0)
    text = (ROOT / "DEVELOPING.md").read_text()
    dev = re.search(r"<!-- device example: msd.py -->\n```python\n(.*?)```", text, re.S).group(1)
    (base / "msd.py").write_text(dev)
    t = np.arange(0.01, 2, 0.02)
    for name in ("a", "b"):
        d = base / name
        d.mkdir()
        (d / "run0.csv").write_text("t_s,x_m\n" + "".join(f"{a:.3f},{0.01 * a:.6g}\n" for a in t))
        (d / "experiment.toml").write_text(
            '[experiment]\ndevice = "../msd.py:SPEC"\n\n[fit]\nn_starts = 1\n\n[[runs]]\n'
            'name = "run0"\nfile = "run0.csv"\nrole = "estimation"\n'
            'waveform = { type = "steps", times_s = [0.0], F_N = [1.0], end_s = 2.0 }\n'
        )
    return {
        "track": ["track", str(video), "--roi", "8,8,40,40", "--search-px", "4"],
        "design": ["design", "--device", "chevron_laser", "--power-max-mW", "30",
                   "--run-duration-s", "3", "--runs", "2"],
        "fit-many": ["fit-many", str(base / "a"), str(base / "b"), "--no-device-figures",
                     "--no-validate"],
    }  # fmt: skip


# (command, delay after its handlers are installed [s], signal)
CASES = [
    ("track", 0.5, signal.SIGINT),
    ("track", 1.5, signal.SIGTERM),
    ("design", 0.5, signal.SIGTERM),
    ("design", 1.0, signal.SIGINT),
    ("fit-many", 0.5, signal.SIGINT),
    ("fit-many", 1.5, signal.SIGTERM),
]


@pytest.mark.parametrize("command, delay, sig", CASES, ids=[f"{c}+{d}" for c, d, _ in CASES])
def test_a_signal_during_the_work_exits_cleanly(inputs, tmp_path, command, delay, sig):
    out = tmp_path / ("track.csv" if command == "track" else "result")
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    proc = subprocess.Popen(
        [sys.executable, "-m", "greybox", *inputs[command], "--out", str(out)],
        stderr=subprocess.PIPE, stdout=subprocess.DEVNULL, text=True, env=env,
    )  # fmt: skip
    try:
        deadline = time.monotonic() + 60
        while not _catches_sigterm(proc.pid) and proc.poll() is None:
            assert time.monotonic() < deadline, "the command never installed its handlers"
            time.sleep(0.02)
        time.sleep(delay)
        assert proc.poll() is None, proc.stderr.read()  # still working when the signal lands
        proc.send_signal(sig)
        err = proc.stderr.read()
        rc = proc.wait(timeout=120)
    finally:
        proc.kill()
    assert rc == (130 if sig == signal.SIGINT else 143), err
    assert "no result was written" in err and "Traceback" not in err, err
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if ".partial-" in p.name or ".old-" in p.name]


_RAISED_AT: list[float] = []  # when each test signal was raised (a loaded machine can take
# seconds to reach that point: a full collection of a worker's heap)


def _raise(sig):
    _RAISED_AT.append(time.monotonic())
    signal.raise_signal(sig)


class _SignalsOnDelete:
    def __init__(self, sig):
        self.sig = sig

    def __del__(self):
        if self.sig is not None:
            _raise(self.sig)


@pytest.mark.parametrize("sig, stop", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, None)])
@pytest.mark.parametrize("where", ["gc callback", "__del__", "weakref callback"])
def test_a_signal_inside_a_callback_that_swallows_it_still_stops(where, sig, stop):
    from greybox.io._atomic import Terminated, received_signal, signal_handlers

    stop = stop or Terminated
    seen = []

    def callback(phase, info):  # what JAX's gc callback is to the interpreter
        if phase == "start" and not seen:
            seen.append(phase)
            _raise(sig)

    with pytest.raises(stop), signal_handlers():
        if where == "gc callback":
            gc.callbacks.append(callback)
            try:
                gc.collect()
            finally:
                gc.callbacks.remove(callback)
        elif where == "__del__":
            _SignalsOnDelete(sig)  # deleted at once: __del__ raises the signal
        else:  # a weakref callback (what the collector runs for a WeakKeyDictionary entry)
            target = _SignalsOnDelete(None)
            ref = weakref.ref(target, lambda _: _raise(sig))  # noqa: F841
            del target
        time.sleep(5)  # the command's work goes on: the signal must stop it here
    assert time.monotonic() - _RAISED_AT[-1] < 2 and received_signal() == sig


@pytest.mark.parametrize("sig, stop", [(signal.SIGINT, KeyboardInterrupt), (signal.SIGTERM, None)])
def test_a_signal_landing_inside_the_unraisable_hook_still_stops(sig, stop, monkeypatch):
    """The hook that delivers a swallowed signal again starts a thread, and starting one waits:
    on a loaded machine a signal (the user's second Ctrl-C, or the re-delivery itself) can
    land in that wait. Raised there it would be lost for good ("Exception ignored in
    sys.unraisablehook"); it must stop the command once the hook has returned."""
    import threading

    from greybox.io._atomic import Terminated, received_signal, signal_handlers

    stop = stop or Terminated
    start = threading.Thread.start

    def start_with_a_signal(self):  # the signal arrives while the hook starts its thread
        _raise(sig)
        start(self)

    with pytest.raises(stop), signal_handlers():
        monkeypatch.setattr(threading.Thread, "start", start_with_a_signal)
        _SignalsOnDelete(sig)  # __del__ raises the first signal; the hook gets the second
        monkeypatch.setattr(threading.Thread, "start", start)
        time.sleep(5)
    assert time.monotonic() - _RAISED_AT[-1] < 2 and received_signal() == sig


class _RaisesOnSetName:
    def __init__(self, sig):
        self.sig = sig

    def __set_name__(self, owner, name):
        _raise(self.sig)


@pytest.mark.parametrize("sig, code", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_during_class_creation_is_an_interrupt_not_a_bug(sig, code, capsys):
    """Python wraps what a descriptor's `__set_name__` raises in "RuntimeError: Error calling
    __set_name__": a signal landing while greybox imports a module that defines an
    `eqx.Module` (fit-many at +0.5 s) must still read as the user's interrupt (exit 130/143,
    "no result was written", no traceback), not as an internal error (exit 3)."""
    from types import SimpleNamespace

    from greybox.cli import _run

    def command(args):
        type("Defined", (), {"field": _RaisesOnSetName(sig)})
        time.sleep(5)  # not reached: the class creation raised

    rc = _run(SimpleNamespace(func=command, command="fit-many"))
    err = capsys.readouterr().err
    assert rc == code, err
    assert "no result was written" in err and "Traceback" not in err, err
