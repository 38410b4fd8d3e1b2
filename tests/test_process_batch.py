"""`fit_batch(..., noise=ProcessNoise(...))`: each device's result is `greybox.fit`'s on that
device alone, and both are the maximum of an independent numpy Kalman filter's likelihood.

Three scalar OU devices (tests/ou_reference.py) of 200 frames with different parameters, all
started at the same values, two starts each. Measured (2-core machine shared by 5 agents):
estimates and log-likelihoods of the batch and of `fit` agree to ~1e-13 relative; 55 s wall,
26 s CPU (most of it compiling the vmapped and the single solver).
"""

import dataclasses

import numpy as np
import pytest

import greybox
from tests import ou_device as od
from tests import ou_reference as ou

TRUTHS = (
    dict(ou.TRUTH),
    dict(ou.TRUTH, Ci=3.0e6, q=5.0e-6),
    dict(ou.TRUTH, Rea=8.0e-3, sd=0.03),
)
START = {"Ci": 2.5e6, "Rea": 6.0e-3, "q": 3.0e-6, "sd": 0.06}
NOISE = greybox.ProcessNoise(od.STRUCTURE)


@pytest.fixture(scope="module")
def devices():
    return [
        greybox.population.Device(
            f"d{k}", od.model(START), [od.experiment(ou.simulate(p, 200, 10 + k))]
        )
        for k, p in enumerate(TRUTHS)
    ]


@pytest.fixture(scope="module")
def batch(devices):
    return greybox.fit_batch(devices, od.FREE, noise=NOISE, n_starts=2)


def test_batch_equals_fit_device_by_device(devices, batch):
    assert batch.groups == 1 and batch.n_calls == 1  # one vmapped call for all six starts
    for d in devices:
        alone = greybox.fit(d.model, d.experiments, od.FREE, noise=NOISE, n_starts=2)
        got = batch[d.name]
        assert got.status == alone.status == "converged"
        assert got.log_likelihood == pytest.approx(alone.log_likelihood, rel=1e-10, abs=1e-8)
        for a, b in zip(alone.parameters, got.parameters):
            assert b.value == pytest.approx(a.value, rel=1e-6), a.name
            assert b.se == pytest.approx(a.se, rel=1e-4), a.name


def test_batch_reaches_the_numpy_likelihood_maximum(devices, batch):
    for d in devices:
        r = batch[d.name]
        est = dict(zip(od.NAMES, (p.value for p in r.parameters)))
        y = d.experiments[0].y[:, 0]
        # greybox's log L is the numpy filter's at the estimate ...
        assert r.log_likelihood == pytest.approx(ou.loglik(est, y), abs=1e-6)
        # ... and no nearby point of the numpy likelihood is higher (a maximum)
        for k in od.NAMES:
            for f in (0.99, 1.01):
                assert ou.loglik(dict(est, **{k: est[k] * f}), y) < r.log_likelihood


def test_a_device_with_a_vanished_intensity_is_assembled_last_and_as_fit_alone(devices, batch):
    """The middle device has no process noise (q = 0): its intensity vanishes, so the batch
    holds it back for the revival check (`likelihood_batch._Assembler`) while the others are
    assembled; it still comes back in its place and as `fit` gives it alone: "not needed",
    the others' estimates those of the first batch."""
    quiet = greybox.population.Device(
        "quiet", od.model(START), [od.experiment(ou.simulate(dict(ou.TRUTH, q=0.0), 200, 40))]
    )
    mixed = [devices[0], quiet, devices[2]]
    said = []
    got = greybox.fit_batch(mixed, od.FREE, noise=NOISE, n_starts=2, progress=said.append)
    assert list(got.results) == ["d0", "quiet", "d2"]
    alone = greybox.fit(quiet.model, quiet.experiments, od.FREE, noise=NOISE, n_starts=2)
    assert got["quiet"].status == alone.status == "converged"
    assert "not needed" in got["quiet"].message and "process.air" in got["quiet"].message
    assert got["quiet"].message == alone.message
    assert got["quiet"].estimate("process.air").value < 1e-3 * START["q"]
    for a, b in zip(alone.parameters, got["quiet"].parameters):
        assert b.value == pytest.approx(a.value, rel=1e-6, abs=1e-12), a.name
    for name in ("d0", "d2"):
        assert np.array_equal(got[name].raw, batch[name].raw)
    assert said[-1] == "3 devices assembled"


def test_batch_refuses_a_sigma_with_process_noise(devices):
    with pytest.raises(ValueError, match="sigma"):
        greybox.fit_batch(devices[:1], od.FREE, noise=NOISE, sigma=0.1)


def test_a_device_with_its_own_bound_rides_in_the_same_group(devices, batch):
    """A device whose free parameters differ only in their numbers is in the batch's one
    group (the bounds are inputs of the compiled filter's solver, not its structure), and it
    is fitted with its own: a lower bound on Ci above d0's truth (2.0e6 J/K) holds its
    estimate at that bound; the other devices' results are the batch's without it."""
    bound = 2.4e6
    own = tuple(dataclasses.replace(p, lower=bound) if p.path == "Ci" else p for p in od.FREE)
    mixed = [dataclasses.replace(devices[0], free=own), *devices[1:]]
    again = greybox.fit_batch(mixed, od.FREE, noise=NOISE, n_starts=2)
    assert again.groups == 1
    ci = again[devices[0].name].estimate("Ci")
    assert bound < ci.value < 1.01 * bound
    for d in devices[1:]:
        log_l = batch[d.name].log_likelihood
        assert again[d.name].log_likelihood == pytest.approx(log_l, rel=1e-10)


def test_records_of_other_lengths_ride_in_the_same_group(devices, batch):
    """Records of similar lengths are padded to one bucketed length (frames unread, steps
    exact identities), so devices whose records are a few frames longer or shorter are one
    group, one compiled solver (they were one group each), and each is fitted on its own
    record. Truth: a 205-frame device's log L is the independent numpy filter's at its
    estimate and no nearby point is higher; the 200-frame devices' results are unchanged."""
    longer = greybox.population.Device(
        "long", od.model(START), [od.experiment(ou.simulate(TRUTHS[1], 205, 41))]
    )
    again = greybox.fit_batch([*devices, longer], od.FREE, noise=NOISE, n_starts=2)
    assert again.groups == 1
    r = again["long"]
    est = dict(zip(od.NAMES, (p.value for p in r.parameters)))
    y = longer.experiments[0].y[:, 0]
    assert y.size == 205 and r.status == "converged"
    assert r.log_likelihood == pytest.approx(ou.loglik(est, y), abs=1e-6)
    for k in od.NAMES:
        for f in (0.99, 1.01):
            assert ou.loglik(dict(est, **{k: est[k] * f}), y) < r.log_likelihood
    for d in devices:
        log_l = batch[d.name].log_likelihood
        assert again[d.name].log_likelihood == pytest.approx(log_l, rel=1e-10)


def test_a_bad_device_is_refused_by_name_before_any_solve(devices):
    """Every device is set up (and so checked) before the batch solves any, and the error
    says which device failed: here the last one names a parameter its model lacks."""
    from greybox.parameters import FreeParameter

    bad = dataclasses.replace(devices[-1], free=(*od.FREE, FreeParameter("no_such_K")))
    progress = []
    with pytest.raises(ValueError, match="no_such_K") as err:
        greybox.fit_batch([*devices[:-1], bad], od.FREE, noise=NOISE, progress=progress.append)
    assert str(err.value).startswith(f"{bad.name}: ")
    assert not progress
