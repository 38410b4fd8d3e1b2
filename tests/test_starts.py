"""A multi-start fit's starts run side by side on a CPU's cores (`greybox._estimate.starts`),
least squares and likelihood (process noise) alike.

Truth: the same fit with its starts one after another (one usable core): the same estimate
and the same cost from every start, bit for bit, since each start is the same compiled solve
of the same inputs; and the side-by-side fit really did hand its starts to worker threads.
"""

import numpy as np
import pytest

import greybox
from greybox._estimate import starts as _starts
from greybox._model.freeparams import FreeParameter
from tests.helpers import two_run_chevron


@pytest.fixture(scope="module")
def device():
    d = two_run_chevron(1)
    free = [
        FreeParameter("absorptance", "1", lower=0.0, upper=1.0),
        FreeParameter("thermal.tau_s", "s", lower=0.0),
        FreeParameter("thermal.resistance_K_per_W", "K/W", lower=0.0),
        FreeParameter("camera.offset_m", "m"),
    ]
    return d.model, d.experiments, free


def _alone_and_side_by_side(monkeypatch, fit, n_starts):
    """(`fit(progress)` with one usable core, the same with two, the starts the second
    handed to worker threads, its progress lines)."""
    monkeypatch.setattr(_starts, "usable_cores", lambda: 1)
    alone = fit(lambda _m: None)
    submitted = []

    class Recording(_starts.ThreadPoolExecutor):
        def submit(self, fn, *args, **kwargs):
            submitted.append(args)
            return super().submit(fn, *args, **kwargs)

    monkeypatch.setattr(_starts, "usable_cores", lambda: 2)
    monkeypatch.setattr(_starts, "ThreadPoolExecutor", Recording)
    said = []
    side = fit(said.append)
    assert len(submitted) == n_starts - 1  # every start but the first went to the threads
    assert side.multistart_costs == alone.multistart_costs
    np.testing.assert_array_equal(side.raw, alone.raw)
    ended = [line.split(":")[0] for line in said if "after" in line and "steps" in line]
    assert ended == [f"start {i}/{n_starts}" for i in range(1, n_starts + 1)]  # in order
    return alone, side


def test_starts_side_by_side_equal_one_after_another(device, monkeypatch):
    if _starts.on_accelerator():
        pytest.skip("an accelerator runs the starts one after another")
    model, runs, free = device
    _alone_and_side_by_side(
        monkeypatch, lambda say: greybox.fit(model, runs, free, n_starts=4, progress=say), 4
    )


def test_likelihood_starts_side_by_side_equal_one_after_another(monkeypatch):
    """A process-noise fit (the scalar OU device, 200 frames from the numpy simulator of
    tests/ou_reference.py, three starts): the same bit for bit, covariance included."""
    if _starts.on_accelerator():
        pytest.skip("an accelerator runs the starts one after another")
    from tests import ou_device as od
    from tests import ou_reference as ou

    start = {"Ci": 2.5e6, "Rea": 6.0e-3, "q": 3.0e-6, "sd": 0.06}  # as tests/test_process_batch
    runs = [od.experiment(ou.simulate(ou.TRUTH, 200, 10))]
    noise = greybox.ProcessNoise(od.STRUCTURE)

    def fit(say):
        return greybox.fit(od.model(start), runs, od.FREE, noise=noise, n_starts=3, progress=say)

    alone, side = _alone_and_side_by_side(monkeypatch, fit, 3)
    assert side.status == "converged"
    np.testing.assert_array_equal(side.covariance_raw, alone.covariance_raw)


@pytest.mark.parametrize(("solve_bytes", "workers"), [(0.6e9, 1), (0.4e9, 2), (0.1e9, 4)])
def test_side_by_side_starts_stay_within_their_memory(monkeypatch, solve_bytes, workers):
    """Beside the one solve `greybox fit`'s memory pre-check counts, the starts side by side
    take at most SIDE_BY_SIDE_BYTES (1 GB) more: 0.6 GB solves run one after another, 0.4 GB
    ones two at a time, 0.1 GB ones as many as there are starts left (4 of 5), on 8 cores."""
    if _starts.on_accelerator():
        pytest.skip("an accelerator runs the starts one after another")
    made = []

    class Counting(_starts.ThreadPoolExecutor):
        def __init__(self, max_workers, **kwargs):
            made.append(max_workers)
            super().__init__(max_workers, **kwargs)

    monkeypatch.setattr(_starts, "usable_cores", lambda: 8)
    monkeypatch.setattr(_starts, "ThreadPoolExecutor", Counting)
    noop = lambda *_: None  # noqa: E731
    out = _starts.run_starts(lambda s: 2.0 * s, [1.0, 2.0, 3.0, 4.0, 5.0], noop, noop, solve_bytes)
    assert out == [2.0, 4.0, 6.0, 8.0, 10.0]
    assert made == ([] if workers == 1 else [workers])
