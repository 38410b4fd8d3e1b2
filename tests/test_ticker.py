"""The progress ticker: a line at least every `every_s` seconds of silence, naming the
phase; messages pass through unchanged. Timed with a fake clock (no sleeping on a clock
that may stall on a loaded machine beyond a short real wait for the thread)."""

import threading
import time

from greybox.cli._ticker import Ticker


def test_silence_is_filled_and_messages_pass_through():
    said, now = [], [0.0]
    done = threading.Event()

    def say(message):
        said.append(message)
        if len(said) >= 4:
            done.set()

    with Ticker(say, every_s=5.0, clock=lambda: now[0], poll_s=0.002) as tick:
        tick("compiling the model")
        for step in range(1, 40):  # 19.5 s of fake silence, in 0.5 s steps
            now[0] = 0.5 * step
            time.sleep(0.05)
            if done.is_set():
                break
        done.wait(5.0)
    assert said[0] == "compiling the model"
    assert said[1].startswith("... still compiling the model (5 s")
    assert all(m.startswith("... still compiling the model") for m in said[1:])
    assert max(tick.gaps) <= 5.0  # never longer than the limit


def test_no_tick_while_messages_keep_coming():
    said, now = [], [0.0]
    with Ticker(said.append, every_s=5.0, clock=lambda: now[0]) as tick:
        for k in range(10):
            now[0] = 2.0 * k
            tick(f"step {k}")
            time.sleep(0.01)
    assert said == [f"step {k}" for k in range(10)]
