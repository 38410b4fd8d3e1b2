"""Where a result folder's figures are drawn: in this process, or in processes beside it.

matplotlib holds the interpreter while it draws, so threads would take turns: figures are
drawn side by side only in other processes, and get the same bytes there (the jobs of
`greybox.io._results.figure_jobs` carry plain data only and Agg draws deterministically).
A drawing process is a plain Python process running `_serve` (`_DrawingProcess`): never a
fork (this process runs JAX's threads), and not multiprocessing's spawn, which imports the
caller's main script again in the child (a script without a `__main__` guard would run
twice). Three ways:

- `drawing_process`: one process started before a fit, so that its start (Python,
  matplotlib and greybox's plotting modules, ~0.35 s; not JAX) runs on a core the fit
  leaves idle; it shares the fit's figures with this process when they are drawn
  (`draw_figures`; the TCLab two-heater result: writing 1.4-1.6 -> 1.0 s), and draws the
  estimation's figures while the validation runs (`drawing_ahead`; writing 1.2 -> 0.65 s);
- `draw_many`: many result folders (`greybox fit-many`), shared out a folder at a time
  among processes started for them and this one;
- `drawing_beside`: inside `drawing_process`, figures drawn there while this process writes
  the rest of its result (`greybox simulate`).

The work is shared as it goes (`_share`): the other processes take items from the front,
each as it finishes one, and this process takes them from the back, until they meet, so a
slower side (a costly figure, this process's own matplotlib import, a busy core) draws
fewer. A job that cannot be sent to another process, and the jobs of a process that failed,
are drawn here, so a drawing error is raised here as without processes.
"""

from __future__ import annotations

import collections
import contextlib
import contextvars
import os
import pickle
import struct
import sys
import threading
from pathlib import Path

FIGURE_PROCESSES_MAX = 8  # processes drawing result folders' figures, this one included
# (each other one ~130 MB); from two folders on, as a process starts in ~0.35 s and a
# folder's figures take ~1 s or more
IDLE_CORE = 0.5  # the idle share of a core (by the 1-minute load) that a drawing process needs
IN_HAND = 2  # items a drawing process holds: it never waits on this process between two

# the `_DrawingProcess` of `drawing_process`, where one is open
_DRAWING = contextvars.ContextVar("greybox_drawing_process", default=None)


def draw_figures(folder, jobs) -> None:
    """Draw `figure_jobs` into `folder` (the folders of their paths made as they are drawn);
    inside `drawing_process` shared with that process."""
    folder = Path(folder)
    helper = _DRAWING.get()
    shared = helper is not None and len(jobs) >= 2
    payloads = [_payload(folder, [job]) for job in jobs] if shared else []
    if not payloads or None in payloads:
        _draw_here(folder, jobs)
        return
    from greybox.report import _plots as plots

    with plots.png_writes_in_background():
        failed = _share([helper], payloads, lambda k: _draw_one(plots, folder, jobs[k]))
    if failed:  # it failed or is gone: its jobs are drawn (or raise) here
        _draw_here(folder, [jobs[k] for k in failed])


@contextlib.contextmanager
def drawing_beside(folder, jobs):
    """Draw `jobs` into `folder` while the block runs (the caller's other writing): inside
    `drawing_process` they go to that process first and are waited for when the block ends;
    drawn here after the block where there is no such process, a job cannot be sent, or the
    process failed (a drawing error is then raised here). On an error in the block no job is
    handed out any more and those in hand are waited for (nothing is drawn into a folder its
    caller is about to remove). `greybox simulate`: its figure is drawn while its tables are
    written."""
    folder = Path(folder)
    helper = _DRAWING.get()
    payloads = [_payload(folder, [job]) for job in jobs] if helper is not None else []
    if not payloads or None in payloads:
        yield
        _draw_here(folder, jobs)
        return
    pending = _Pending(payloads)
    helper.start(pending.hand_out)
    try:
        yield
    except BaseException:
        pending.close()
        helper.answers()
        raise
    failed = _not_drawn([helper])
    if failed:  # it failed or is gone: its jobs are drawn (or raise) here
        _draw_here(folder, [jobs[k] for k in failed])


@contextlib.contextmanager
def drawing_ahead(jobs):
    """Inside `drawing_process`, `jobs` are drawn by that process into a temporary folder
    while the block runs (`greybox fit`: the estimation's figures while the validation runs,
    before the result folder exists); yields the `Ahead` whose `take` moves them into the
    result folder, or None where there is no such process or a job cannot be sent (then
    nothing is drawn ahead). On leaving the block no job is handed out any more, those in
    hand are waited for, and the temporary folder is removed."""
    helper = _DRAWING.get()
    if helper is None or not jobs:
        yield None
        return
    import tempfile

    with tempfile.TemporaryDirectory(prefix="greybox-figures-") as tmp:
        folder = Path(tmp)
        payloads = [_payload(folder, [job]) for job in jobs]
        if None in payloads:
            yield None
            return
        ahead = Ahead(helper, folder, jobs, payloads)
        try:
            yield ahead
        finally:
            ahead.stop()


class Ahead:
    """Figures that the drawing process draws into `folder` (`drawing_ahead`), taken from
    the front of `jobs`; this process draws the rest from the back once it needs them."""

    def __init__(self, helper, folder: Path, jobs, payloads):
        self.helper, self.folder, self.jobs, self.payloads = helper, folder, jobs, payloads
        self._pending, self._finished = _Pending(payloads), False
        helper.start(self._pending.hand_out)

    def take(self, folder, jobs) -> list:
        """Every job drawn ahead (this process drawing those still left), those among `jobs`
        (the same path and the same data) moved into `folder`; returns the jobs left to
        draw, in their order."""
        import shutil

        self._finish()
        ahead = dict(zip((job[0] for job in self.jobs), self.payloads, strict=True))
        left = []
        for job in jobs:
            rel = job[0]
            if ahead.get(rel) is not None and ahead[rel] == _payload(self.folder, [job]):
                (Path(folder) / rel).parent.mkdir(parents=True, exist_ok=True)
                shutil.move(self.folder / rel, Path(folder) / rel)
            else:  # not drawn ahead, or its data changed since
                left.append(job)
        return left

    def stop(self) -> None:
        """Nothing handed out any more; what the drawing process holds is waited for."""
        self._pending.close()
        self.helper.answers()

    def _finish(self) -> None:
        if self._finished:
            return
        self._finished = True
        from greybox.report import _plots as plots

        with plots.png_writes_in_background():
            failed = _drawn_from_the_back(
                self._pending, [self.helper], lambda k: _draw_one(plots, self.folder, self.jobs[k])
            )
        if failed:  # it failed or is gone: its jobs are drawn (or raise) here
            _draw_here(self.folder, [self.jobs[k] for k in failed])


def draw_many(deferred) -> None:
    """Draw the figures of many result folders (`deferred`: the (folder, `figure_jobs`) pairs
    of `write_fit_files(defer=...)`), shared out a folder at a time among this process and
    processes started beside it on the cores it may use (`greybox fit-many` of 8 chevrons:
    its writing was 86 % of the command's time). All drawn here with one core or few
    folders, or when a job cannot be sent to another process."""
    from greybox import _platform

    workers = min(_platform.usable_cores(), FIGURE_PROCESSES_MAX, len(deferred))
    payloads = []
    if workers >= 2:
        payloads = [_payload(Path(folder), jobs) for folder, jobs in deferred]
    helpers = _start(workers - 1) if payloads and None not in payloads else []
    token = _DRAWING.set(None)  # a folder drawn here is drawn here whole
    try:
        failed = _share(helpers, payloads, lambda k: draw_figures(*deferred[k]))
        for k in failed if helpers else range(len(deferred)):
            draw_figures(*deferred[k])
    finally:
        _DRAWING.reset(token)
        for helper in helpers:
            helper.stop()


class _Pending:
    """The indices of `payloads` not yet handed out: drawing processes take them from the
    front (`hand_out`, the function their `start` is given), this process from the back
    (`take_back`); `close` hands out nothing more."""

    def __init__(self, payloads):
        self._payloads = payloads
        self._left, self._lock = collections.deque(range(len(payloads))), threading.Lock()

    def _take(self, pop):
        with self._lock:
            return pop() if self._left else None

    def hand_out(self):
        k = self._take(self._left.popleft)
        return None if k is None else (k, self._payloads[k])

    def take_back(self):
        return self._take(self._left.pop)

    def close(self) -> None:
        with self._lock:
            self._left.clear()


def _not_drawn(helpers) -> list:
    """The indices the `helpers` took and did not draw (one failed, or died), once every
    item they took has finished."""
    return sorted(k for helper in helpers for k, drawn in helper.answers() if not drawn)


def _share(helpers, payloads, draw_here) -> list:
    """Draw the items `payloads` (by index): `helpers` take them from the front, each as it
    finishes one, while this process draws them from the back (`draw_here(index)`) until
    none is left. Returns the indices a helper did not draw (it failed, or died). On an
    error here no item is handed out any more, and the helpers' items are waited for."""
    if not helpers:
        return []
    pending = _Pending(payloads)
    for helper in helpers:
        helper.start(pending.hand_out)
    return _drawn_from_the_back(pending, helpers, draw_here)


def _drawn_from_the_back(pending, helpers, draw_here) -> list:
    """The items `pending` still holds drawn here from the back (`draw_here(index)`) while
    the `helpers` it was given to take them from the front; returns the indices a helper did
    not draw. On an error here no item is handed out any more, and the helpers' items are
    waited for."""
    try:
        while (k := pending.take_back()) is not None:
            draw_here(k)
    finally:  # nothing is handed out any more; their items finished before this returns
        pending.close()
        failed = _not_drawn(helpers)
    return failed


def _draw_here(folder: Path, jobs) -> None:
    from greybox.report import _plots as plots

    with plots.png_writes_in_background():
        for job in jobs:
            _draw_one(plots, folder, job)


def _draw_one(plots, folder: Path, job) -> None:
    rel, function, args, kwargs = job
    (folder / rel).parent.mkdir(parents=True, exist_ok=True)  # figures/ of a fit's result
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
def drawing_process():
    """Within this block, `draw_figures` shares its jobs with one process started here
    (where `spare_core()`), which imports what drawing needs at once, while the block's fit
    runs. The process ends with the block, also on an error or an interrupt."""
    helpers = _start(1) if spare_core() else []
    token = _DRAWING.set(helpers[0] if helpers else None)
    try:
        yield
    finally:
        _DRAWING.reset(token)
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
    """A Python process running `_serve`, started now. Given work (`start`: a function that
    hands out (index, payload) items, None when there are none), it holds `IN_HAND` items at
    a time and takes the next as it answers each, from its reader thread, so it never waits
    on this process; `answers` waits for the (index, drawn) of every item it took. Payloads
    are written by a thread too, so that handing one out never waits on its imports."""

    def __init__(self):
        import queue
        import subprocess

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
        self._lock, self._finished = threading.Lock(), threading.Event()
        self._hand_out, self._held, self._answers = None, collections.deque(), []
        self._gone = False
        self._threads = [
            threading.Thread(target=self._write_all, daemon=True),
            threading.Thread(target=self._read_all, daemon=True),
        ]
        for thread in self._threads:
            thread.start()

    def start(self, hand_out) -> None:
        with self._lock:
            self._hand_out, self._answers = hand_out, []
            self._finished.clear()
            for _ in range(0 if self._gone else IN_HAND):
                self._take()
            if not self._held:
                self._finished.set()

    def answers(self) -> list:
        """(index, drawn) of every item it took. Interrupted while waiting, the process is
        stopped first: it never writes on into a folder its caller is about to clean up."""
        try:
            self._finished.wait()
        except BaseException:
            self.stop()
            raise
        return self._answers

    def stop(self) -> None:
        """End the process: idle, drawing, or still importing when the block ended early."""
        self._outbox.put(None)
        self._proc.kill()
        self._proc.wait()
        for thread in self._threads:
            thread.join()
        self._proc.stdout.close()

    def _take(self) -> None:  # with self._lock held
        item = self._hand_out()
        if item is not None:
            self._held.append(item[0])
            self._outbox.put(item[1])

    def _read_all(self) -> None:
        with contextlib.suppress(OSError, ValueError):  # its end, or this side closed
            while (answer := _read(self._proc.stdout)) is not None:
                with self._lock:
                    self._answers.append((self._held.popleft(), answer == b""))
                    self._take()
                    if not self._held:
                        self._finished.set()
        with self._lock:  # its end: the items it held are not drawn
            self._gone = True
            self._answers.extend((k, False) for k in self._held)
            self._held.clear()
            self._finished.set()

    def _write_all(self) -> None:
        pipe = self._proc.stdin
        with contextlib.suppress(OSError):  # the process is gone: its reader says so
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
    what drawing needs and draws a first figure (its fonts), then draws each payload read
    from stdin and answers on stdout (an empty message, or the error it met) until stdin
    ends. What drawing prints goes to stderr."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    answers = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    from greybox.report import _plots

    _plots.warm_up()
    while (payload := _read(sys.stdin.buffer)) is not None:
        try:
            _draw_payload(payload)
        except Exception as e:  # noqa: BLE001 (answered; the jobs are drawn again there)
            _write(answers, repr(e).encode())
        else:
            _write(answers, b"")


def _draw_payload(payload: bytes) -> None:
    draw_figures(*pickle.loads(payload))  # no drawing process of its own: drawn here
