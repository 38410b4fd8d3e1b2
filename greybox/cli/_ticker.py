"""A progress line at least every few seconds, whatever the phase (compiling, optimising,
writing, a batch): a wrapper around a command's `say` that, while nothing was said for
`every_s` seconds, says that the current phase is still running and for how long.

    with Ticker(Progress(args.quiet)) as say:
        say("compiling the model")      # passes through, and names the phase
        ...                             # silent for 20 s: four "still ..." lines
"""

from __future__ import annotations

import threading
import time

EVERY_S = 5.0  # the longest silence a user sees


def to_stderr(message: str) -> None:
    import sys

    print(message, file=sys.stderr, flush=True)


class Ticker:
    def __init__(self, say, every_s: float = EVERY_S, clock=time.monotonic, poll_s=None):
        self.say = say
        self.every_s = float(every_s)
        self.poll_s = min(0.5, self.every_s / 4) if poll_s is None else float(poll_s)
        self.clock = clock
        self.phase = "working"
        self.phase_start = self.last = clock()
        self.gaps: list = []  # the silences seen (s), for benchmarks
        self._stop = threading.Event()
        self._lock = threading.Lock()
        self._thread = None

    def __call__(self, message: str) -> None:
        with self._lock:
            now = self.clock()
            self.gaps.append(now - self.last)
            self.phase = str(message).rstrip(" .:")
            self.phase_start = self.last = now
            self.say(message)

    def phase_is(self, name: str) -> None:
        """Name the phase without saying anything (the ticker speaks only after silence)."""
        with self._lock:
            self.phase = name
            self.phase_start = self.clock()

    @property
    def elapsed(self) -> float:
        return getattr(self.say, "elapsed", self.clock() - self.phase_start)

    def __enter__(self):
        self._thread = threading.Thread(target=self._run, name="greybox-ticker", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        return False

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            with self._lock:
                now = self.clock()
                # one poll early, so that the silence a user sees stays under every_s
                if now - self.last >= self.every_s - self.poll_s:
                    self.gaps.append(now - self.last)
                    self.last = now
                    self.say(f"... still {self.phase} ({now - self.phase_start:.0f} s so far)")
