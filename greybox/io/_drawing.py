"""Where a result folder's figures are drawn: in this process, or in processes beside it.

matplotlib holds the interpreter while it draws, so threads would take turns: figures are
drawn side by side only in other processes, spawned (never forked: this process runs JAX's
threads), and get the same bytes there (the jobs of `greybox.io._results.figure_jobs` carry
plain data only and Agg draws deterministically). Two ways:

- `draw_many`: many result folders (`greybox fit-many`), a folder per process.
- `drawing_process`: one process started before a fit, so that its start (Python,
  matplotlib and greybox's imports, ~1.3 s of CPU) runs on a core the fit leaves idle; when
  the fit's figures are drawn (`draw_figures`) it draws half of them while this process
  draws the other half (the TCLab two-heater folder: writing 1.8-1.9 -> 1.1-1.2 s).

Either way, a job that cannot be sent to another process, and the jobs of a process that
failed, are drawn here, so a drawing error is raised here as without processes.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import pickle
from pathlib import Path

FIGURE_PROCESSES_MAX = 8  # processes drawing result folders' figures (~250 MB each)
FIGURE_PROCESSES_FROM = 3  # folders below which `draw_many` draws here: a process's start
# (its imports, ~1-2 s) would cost more than it saves
IDLE_CORE = 0.5  # the idle share of a core (by the 1-minute load) that a drawing process needs

# the `_DrawingProcess` of `drawing_process`, where one is open
_DRAWING = contextvars.ContextVar("greybox_drawing_process", default=None)


def draw_figures(folder, jobs) -> None:
    """Draw `figure_jobs` into `folder` (its figures/ made here); inside `drawing_process`
    every other job is drawn by that process while this one draws the rest."""
    folder = Path(folder)
    (folder / "figures").mkdir(exist_ok=True)
    helper = _DRAWING.get()
    there, here = jobs[::2], jobs[1::2]
    payload = None if helper is None or not here else _payload(folder, there)
    if payload is None or not helper.send(payload):
        _draw_here(folder, jobs)
        return
    try:
        _draw_here(folder, here)
    finally:  # its share finished either way: nothing is written into `folder` after this
        drawn = helper.done()
    if not drawn:  # it failed or is gone: its jobs are drawn (or raise) here
        _draw_here(folder, there)


def _draw_here(folder: Path, jobs) -> None:
    from greybox.report import _plots as plots

    with plots.png_writes_in_background():
        for rel, function, args, kwargs in jobs:
            getattr(plots, function)(folder / rel, *args, **kwargs)


def spare_core() -> bool:
    """Whether a process beside this one would run on an idle core: two or more usable
    cores, and the 1-minute load average leaving at least `IDLE_CORE` of one idle (on a busy
    machine, a test suite's workers say, the process's start would only take CPU from
    others)."""
    from greybox import _platform

    cores = _platform.usable_cores()
    try:
        load = os.getloadavg()[0]
    except (AttributeError, OSError):  # no load average here: the cores alone decide
        load = 0.0
    return cores >= 2 and cores - load >= IDLE_CORE


@contextlib.contextmanager
def drawing_process(start: bool = True):
    """Within this block, `draw_figures` shares its jobs with one process started here
    (when `start` and `spare_core()`), which imports what drawing needs at once, while the
    block's fit runs. The process ends with the block, also on an error or an interrupt."""
    helper = None
    if start and spare_core():
        try:
            helper = _DrawingProcess()
        except Exception:  # noqa: BLE001 (no process could be started: everything drawn here)
            helper = None
    token = _DRAWING.set(helper)
    try:
        yield
    finally:
        _DRAWING.reset(token)
        if helper is not None:
            helper.stop()


class _DrawingProcess:
    """A spawned process (daemonic: it never outlives this one) that draws the payloads
    sent to it, one at a time, answering each with None or the error it met."""

    def __init__(self):
        import multiprocessing

        context = multiprocessing.get_context("spawn")
        self._conn, theirs = context.Pipe()
        self._process = context.Process(target=_serve, args=(theirs,), daemon=True)
        self._process.start()
        theirs.close()

    def send(self, payload: bytes) -> bool:
        try:
            self._conn.send_bytes(payload)
        except OSError:  # the process is gone
            return False
        return True

    def done(self) -> bool:
        """Whether the payload sent was drawn (False: it failed, or the process died)."""
        try:
            return self._conn.recv() is None
        except (EOFError, OSError):
            return False

    def stop(self) -> None:
        """End the process: idle, or still importing when the block ended early."""
        self._conn.close()
        self._process.terminate()


def _serve(conn) -> None:
    """The drawing process: ignores Ctrl-C (the command that started it stops it), reads
    payloads from the start (a thread, so a sender never waits on the imports), imports what
    drawing needs, and draws each payload in turn until its pipe closes."""
    import queue
    import signal
    import threading

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    payloads = queue.SimpleQueue()

    def read():
        while True:
            try:
                payloads.put(conn.recv_bytes())
            except (EOFError, OSError):
                payloads.put(None)
                return

    threading.Thread(target=read, daemon=True).start()
    from matplotlib.backends import backend_agg  # noqa: F401

    from greybox.report import _plots  # noqa: F401

    while (payload := payloads.get()) is not None:
        try:
            _draw_payload(payload)
        except Exception as e:  # noqa: BLE001 (answered; the jobs are drawn again there)
            conn.send(repr(e))
        else:
            conn.send(None)


def draw_many(deferred) -> None:
    """Draw the figures of many result folders (`deferred`: the (folder, `figure_jobs`) pairs
    of `write_fit_files(defer=...)`), a folder per task, in processes side by side on the
    cores this process may use (`greybox fit-many` of 8 chevrons: its writing was 86 % of the
    command's time). Drawn here instead: with one core or few folders, when a job cannot be
    sent to another process, and a folder whose process failed."""
    from greybox import _platform

    workers = min(_platform.usable_cores(), FIGURE_PROCESSES_MAX, len(deferred))
    payloads = None
    if workers >= 2 and len(deferred) >= FIGURE_PROCESSES_FROM:
        payloads = [_payload(Path(folder), jobs) for folder, jobs in deferred]
        if any(p is None for p in payloads):
            payloads = None
    if payloads is None:
        for folder, jobs in deferred:
            draw_figures(folder, jobs)
        return
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor

    pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        futures = [pool.submit(_draw_payload, p) for p in payloads]
        for (folder, jobs), future in zip(deferred, futures):
            if future.exception() is not None:
                draw_figures(folder, jobs)
    finally:  # an error or an interrupt: the folders not started are not drawn
        pool.shutdown(wait=True, cancel_futures=True)


def _payload(folder: Path, jobs) -> bytes | None:
    """A folder's jobs pickled for another process, or None when they cannot be."""
    try:
        return pickle.dumps((folder, jobs))
    except Exception:  # noqa: BLE001 (e.g. a waveform class defined inside a function)
        return None


def _draw_payload(payload: bytes) -> None:
    folder, jobs = pickle.loads(payload)
    (folder / "figures").mkdir(exist_ok=True)
    _draw_here(folder, jobs)
