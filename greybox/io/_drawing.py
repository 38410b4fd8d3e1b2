"""Where a result folder's figures are drawn: in this process, or in processes beside it.

matplotlib holds the interpreter while it draws, so threads would take turns: figures are
drawn side by side only in other processes, and get the same bytes there (the jobs of
`greybox.io._results.figure_jobs` carry plain data only and Agg draws deterministically).
A drawing process is a plain Python process running `_serve` (`_DrawingProcess`): never a
fork (this process runs JAX's threads), and not multiprocessing's spawn, which imports the
caller's main script again in the child (a script without a `__main__` guard would run
twice). Two ways:

- `draw_many`: many result folders (`greybox fit-many`), a share of the folders per process.
- `drawing_process`: one process started before a fit, so that its start (Python,
  matplotlib and greybox's plotting modules, ~0.35 s; not JAX) runs on a core the fit
  leaves idle; when the fit's figures are drawn (`draw_figures`) it draws half of them
  while this process draws the other half (the TCLab two-heater result: writing 1.4-1.6 ->
  1.0 s).

Either way, a job that cannot be sent to another process, and the jobs of a process that
failed, are drawn here, so a drawing error is raised here as without processes.
"""

from __future__ import annotations

import contextlib
import contextvars
import os
import pickle
import struct
import sys
from pathlib import Path

FIGURE_PROCESSES_MAX = 8  # processes drawing result folders' figures (~130 MB each)
FIGURE_PROCESSES_FROM = 2  # folders below which `draw_many` draws here (a process starts in
# ~0.35 s, a folder's figures take ~1 s or more)
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
    if payload is None:
        _draw_here(folder, jobs)
        return
    helper.send(payload)
    try:
        _draw_here(folder, here)
    finally:  # its share finished either way: nothing is written into `folder` after this
        drawn = helper.drawn()
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
    helpers = _start(1) if start and spare_core() else []
    token = _DRAWING.set(helpers[0] if helpers else None)
    try:
        yield
    finally:
        _DRAWING.reset(token)
        for helper in helpers:
            helper.stop()


def draw_many(deferred) -> None:
    """Draw the figures of many result folders (`deferred`: the (folder, `figure_jobs`) pairs
    of `write_fit_files(defer=...)`), shared out among processes side by side on the cores
    this process may use (`greybox fit-many` of 8 chevrons: its writing was 86 % of the
    command's time). Drawn here instead: with one core or few folders, when a job cannot be
    sent to another process, and a folder whose process failed."""
    from greybox import _platform

    workers = min(_platform.usable_cores(), FIGURE_PROCESSES_MAX, len(deferred))
    payloads = []
    if workers >= 2 and len(deferred) >= FIGURE_PROCESSES_FROM:
        payloads = [_payload(Path(folder), jobs) for folder, jobs in deferred]
    helpers = _start(workers) if payloads and None not in payloads else []
    if not helpers:
        for folder, jobs in deferred:
            draw_figures(folder, jobs)
        return
    try:
        for k, payload in enumerate(payloads):  # in turn; each process answers in order
            helpers[k % len(helpers)].send(payload)
        for k, (folder, jobs) in enumerate(deferred):
            if not helpers[k % len(helpers)].drawn():
                draw_figures(folder, jobs)
    finally:  # an error or an interrupt: the folders not drawn yet are not drawn
        for helper in helpers:
            helper.stop()


def _start(n: int) -> list:
    """Up to `n` drawing processes (none where none can be started)."""
    helpers = []
    with contextlib.suppress(OSError, ValueError):  # no interpreter to run, no processes left
        for _ in range(n):
            helpers.append(_DrawingProcess())
    return helpers


def _payload(folder: Path, jobs) -> bytes | None:
    """A folder's jobs pickled for another process, or None when they cannot be."""
    try:
        return pickle.dumps((folder, jobs))
    except Exception:  # noqa: BLE001 (e.g. a waveform class defined inside a function)
        return None


# the drawing process's program (its argument: the folder this process imported greybox from)
_SERVE = (
    "import sys\n"
    "if sys.argv[1] not in sys.path: sys.path.insert(0, sys.argv[1])\n"
    "from greybox.io._drawing import _serve\n"
    "_serve()\n"
)


class _DrawingProcess:
    """A Python process running `_serve`, started now: it draws the payloads sent
    to it one after another and answers each, in order (`drawn`). Payloads are written by a
    thread, so that sending never waits on the process's imports."""

    def __init__(self):
        import queue
        import subprocess
        import threading

        import greybox

        # -P: no working folder on its path; this process's greybox, wherever it came from
        where = str(Path(greybox.__file__).parents[1])
        self._proc = subprocess.Popen(
            [sys.executable, "-P", "-c", _SERVE, where],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            stderr=subprocess.DEVNULL,  # a failure shows as a missing answer: drawn here
        )
        self._outbox = queue.SimpleQueue()
        self._writer = threading.Thread(target=self._write_all, daemon=True)
        self._writer.start()

    def send(self, payload: bytes) -> None:
        self._outbox.put(payload)

    def drawn(self) -> bool:
        """Whether the next payload sent was drawn (False: it failed, or the process died).
        Interrupted while waiting, the process is stopped first: it never writes on into a
        folder its caller is about to clean up."""
        try:
            return _read(self._proc.stdout) == b""
        except BaseException:
            self.stop()
            raise

    def stop(self) -> None:
        """End the process: idle, drawing, or still importing when the block ended early."""
        self._outbox.put(None)
        self._proc.kill()
        self._proc.wait()
        self._writer.join()
        self._proc.stdout.close()

    def _write_all(self) -> None:
        pipe = self._proc.stdin
        with contextlib.suppress(OSError):  # the process is gone: `drawn` reads its end
            while (payload := self._outbox.get()) is not None:
                _write(pipe, payload)
        with contextlib.suppress(OSError):
            pipe.close()


def _write(pipe, data: bytes) -> None:
    pipe.write(struct.pack(">Q", len(data)) + data)
    pipe.flush()


def _read(pipe) -> bytes | None:
    """The next message on `pipe`, None at its end."""
    head = pipe.read(8)
    if len(head) < 8:
        return None
    size = struct.unpack(">Q", head)[0]
    data = pipe.read(size)
    return data if len(data) == size else None


def _serve() -> None:
    """The drawing process: ignores Ctrl-C (the command that started it stops it), imports
    what drawing needs, then draws each payload read from stdin and answers on stdout (an
    empty message, or the error it met) until stdin ends. What drawing prints goes to
    stderr."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    from matplotlib.backends import backend_agg  # noqa: F401

    from greybox.report import _plots  # noqa: F401

    while (payload := _read(sys.stdin.buffer)) is not None:
        try:
            _draw_payload(payload)
        except Exception as e:  # noqa: BLE001 (answered; the jobs are drawn again there)
            _write(answers, repr(e).encode())
        else:
            _write(answers, b"")


def _draw_payload(payload: bytes) -> None:
    folder, jobs = pickle.loads(payload)
    (folder / "figures").mkdir(exist_ok=True)
    _draw_here(folder, jobs)
