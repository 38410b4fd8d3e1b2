"""Verdicts on noise levels that fall towards zero (greybox/_estimate/likelihood.py), against
the numpy OU reference of tests/ou_reference.py: an intensity far below its start but whose
zero the data reject is interior; a measurement sd where the likelihood levels off at zero is
"not needed"; one where it rises without bound (a reading fitted exactly) is a collapse."""

import dataclasses

import numpy as np
import pytest

import greybox
from greybox._estimate import likelihood as lik
from tests import ou_device as od
from tests import ou_reference as ou


def test_an_intensity_far_below_a_given_start_is_inside_its_range():
    """Started by the user 1e4 x above the truth, the intensity ends ~1e4 x below its start.
    The data reject zero (likelihood ratio), so it is an interior estimate with an interval
    covering the truth, not "at bound (lower)" with the whole fit invalid (before: status "at
    bound", as the TCLab board's heater noise started at 10 K^2/s)."""
    truth = dict(ou.TRUTH)
    run = od.experiment(ou.simulate(truth, 400, seed=5))
    free = [
        dataclasses.replace(p, initial=1e4 * truth["q"]) if p.path == "process.air" else p
        for p in od.FREE
    ]
    res = greybox.fit(od.model(truth), [run], free, noise=greybox.ProcessNoise(od.STRUCTURE))
    assert res.status == "converged", res.message
    q = {p.path: p for p in res.parameters}["process.air"]
    print("q", q.value, q.ci95, q.verdict)
    assert q.value < 1e-3 * 1e4 * truth["q"]  # the generic rule's "at bound" territory
    assert q.verdict == "identifiable"
    assert q.ci95[0] < truth["q"] < q.ci95[1]


def test_readings_without_measurement_noise_make_its_sd_not_needed_not_a_bound():
    """OU readings with no measurement noise (the numpy reference at sd = 0): the likelihood
    levels off as the sd goes to zero, so the sd is "not needed" and the fit valid, with the
    physical intervals covering the truth (before: status "at bound", "widen the bound")."""
    truth = dict(ou.TRUTH, sd=0.0)
    run = od.experiment(ou.simulate(truth, 400, seed=5))
    res = greybox.fit(od.model(ou.TRUTH), [run], od.FREE, noise=greybox.ProcessNoise(od.STRUCTURE))
    assert res.status == "converged", res.message
    est = {p.path: p for p in res.parameters}
    assert est["measurement.Ti"].verdict == "not needed"
    for path, key in (("Ci", "Ci"), ("Rea", "Rea"), ("process.air", "q")):
        assert est[path].ci95[0] < truth[key] < est[path].ci95[1], path


def test_a_reading_fitted_exactly_makes_the_likelihood_unbounded_at_zero_sd():
    """The first reading scored and the initial state set to it: that reading's term is
    -log N(0; 0, sd^2) = log sd + const, so taking the sd 1e3 x closer to zero lowers -log L
    by ln 1000 (the other readings' variances are the process noise's, ~1e10 x larger): the
    likelihood has no upper bound there. With the first reading conditioned on, none is
    fitted exactly and the likelihood levels off."""
    y = ou.simulate(ou.TRUTH, 200, seed=5)
    free = [*od.FREE, greybox.FreeParameter("Ti0", "K", per_experiment=True)]
    scored = greybox.ProcessNoise(
        od.STRUCTURE, initial_state=greybox.InitialState(score_first=True)
    )
    k, start = 3, 0.05
    for noise, unbounded in ((scored, True), (greybox.ProcessNoise(od.STRUCTURE), False)):
        su = lik.setup(od.model(ou.TRUTH), [od.experiment(y)], free, noise, n_starts=1)
        values = [ou.TRUTH[n] for n in od.NAMES] + [float(y[0])]
        raw = np.array([float(p.to_raw(v)) for p, v in zip(su.flat, values)])
        far = lik._nll_at_zero(su.obj, raw, k, start)
        near = lik._nll_at_zero(su.obj, raw, k, start, 1e-3)
        print(noise.initial_state, near - far)
        assert lik._unbounded_at_zero(su.obj, raw, k, start) is unbounded
        if unbounded:
            assert near - far == pytest.approx(-np.log(1e3), abs=1e-6)
        else:
            assert abs(near - far) < 1e-6
