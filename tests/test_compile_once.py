"""A new device of a known structure reuses the compiled solver (issue 24, item 1).

A parameter's starting value (`FreeParameter.initial`, e.g. per-run camera offsets started at
each device's rest reading) is read on the host only, to build the raw start vector; it takes
no part in a problem's identity, so a second device with other starting values must compile
nothing for its solve. Truth: JAX's own record of backend compilations during the second fit,
and the second fit's estimates against a fit of that device alone.
"""

import pytest

import greybox
from greybox._model.freeparams import FreeParameter
from tests.helpers import backend_compiles, two_run_chevron


@pytest.fixture(scope="module")
def compiles():
    with backend_compiles() as names:
        yield names


def test_second_device_compiles_no_solver(compiles):
    a, b = two_run_chevron(1), two_run_chevron(2)
    starts = {p.path: p.initial for p in a.free if p.initial is not None}
    assert starts and any(
        q.initial != starts.get(q.path) for q in b.free if q.initial is not None
    )  # the two devices really start from different values
    greybox.fit(a.model, a.experiments, a.free)
    first = [n for n in compiles if "_solve" in n]
    assert first  # the first device compiled the solver
    before = len(compiles)
    res = greybox.fit(b.model, b.experiments, b.free)
    assert [n for n in compiles[before:] if "_solve" in n] == []
    assert res.valid


def test_initial_is_not_part_of_the_identity():
    p = FreeParameter("x", "m", lower=0.0, initial=1.0)
    q = FreeParameter("x", "m", lower=0.0, initial=2.0)
    assert p == q and hash(p) == hash(q)
    assert p != FreeParameter("x", "m", lower=0.5, initial=1.0)  # bounds still count
    assert FreeParameter("y", scale=1.0) != FreeParameter("y", scale=2.0)  # and the scale


def test_a_new_structure_traces_its_simulation_once_and_its_derivative_once(monkeypatch):
    """Compiling a solver traces the model's simulation twice: once as it is (the residuals the
    solver evaluates) and once with its tangents (their derivative); the end point's
    Jacobian and predictions reuse that trace rather than tracing the model a third time
    (which was a quarter of an adaptive model's compile). Truth: the simulation's own
    Python code, counted each time JAX runs it to trace it."""
    import greybox._estimate.fit as fit_module

    traced = []
    simulate = fit_module.observe_schedule

    def counted(*args, **kwargs):
        traced.append(1)
        return simulate(*args, **kwargs)

    monkeypatch.setattr(fit_module, "observe_schedule", counted)
    d = two_run_chevron(3)
    # a Huber constant no other test uses: a structure compiled here, not found in a cache
    res = greybox.fit(d.model, d.experiments, d.free, loss="huber", huber_c=1.2345)
    assert res.converged
    assert len(traced) == 2
