"""Python's cyclic garbage collector paused around work that creates many long-lived objects.

A batch of fits creates results (~135 objects a chevron `FitResult`) that nothing frees, and
every so many new objects the collector walks every object the process holds, a number the
results themselves keep raising: a warm `fit_batch` of 512 chevrons spent 0.2-0.5 s of its
2.5-3 s in the collector, more the more results the session already held. The work paused
here creates next to no cyclic garbage (a cold 512-device batch: 10 unreachable objects, a
warm one none; the same peak memory), so nothing waits long to be freed.

Paused is not free: every object made meanwhile stays in the youngest generation, and the
first collection after the pause examines all of them at once (a warm 512-device batch:
0.05-0.07 s, after its last result). `collect_young` examines them in pieces instead, where
the work's caller chooses: a batch's host thread after each wave it assembles, beside the
compiled solves of the next."""

from __future__ import annotations

import contextlib
import gc
import threading

_LOCK = threading.Lock()
_STATE = {"depth": 0, "was_on": False}  # blocks open now; whether it was on at the first


@contextlib.contextmanager
def collector_paused():
    """The cyclic collector off inside; back on when the last open block ends, if it was on
    when the first began (blocks nest and may overlap across threads)."""
    with _LOCK:
        if _STATE["depth"] == 0:
            _STATE["was_on"] = gc.isenabled()
            gc.disable()
        _STATE["depth"] += 1
    try:
        yield
    finally:
        with _LOCK:
            _STATE["depth"] -= 1
            if _STATE["depth"] == 0 and _STATE["was_on"]:
                gc.enable()


def collect_young() -> None:
    """Examine the objects made since the last call (generations 0 and 1; the survivors move
    to the oldest, which only a full collection walks), in the calling thread, paused or not."""
    gc.collect(1)
