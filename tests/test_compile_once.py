"""A new device of a known structure reuses the compiled solver (issue 24, item 1).

A parameter's starting value (`FreeParameter.initial`, e.g. per-run camera offsets started at
each device's rest reading) is read on the host only, to build the raw start vector; it takes
no part in a problem's identity, so a second device with other starting values must compile
nothing for its solve. Its bounds, scale and prior are inputs of the compiled solver, so
they take no part either. The same holds for what follows a fit: its bands and the delta
method and draws of a function of its parameters. Truth: JAX's own record of backend
compilations during the second device's calls, and what its own numbers must do to its
estimates, bands and intervals.
"""

import dataclasses

import numpy as np
import pytest

import greybox
from greybox._model.freeparams import FreeParameter
from greybox.waveforms import PulseTrain
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


def _with(free, path, **change):
    return [dataclasses.replace(p, **change) if p.path == path else p for p in free]


def test_other_bounds_scales_and_priors_compile_no_solver(compiles):
    """A parameter's bounds, its scale (derived from each device's own start when not given)
    and its prior's numbers are inputs of the compiled solver, not part of its identity: a
    device that differs from the last only in them compiles nothing. Truth that the new
    numbers are the ones used (not those the solver was compiled with): an upper bound below
    the device's true tau (45 ms) caps the estimate at that bound, and a prior with a 0.1 %
    log-sd holds the absorptance at its median, 0.5 (the data say ~0.6)."""
    first, second = two_run_chevron(4), two_run_chevron(5)
    base = _with(first.free, "camera.offset_m", scale=None)  # scale from each device's start
    base = _with(base, "absorptance", prior_median=0.6, prior_log_sd=0.5)
    greybox.fit(first.model, first.experiments, base)
    before = len(compiles)
    free = _with(second.free, "camera.offset_m", scale=None)
    free = _with(free, "thermal.tau_s", upper=0.03, initial=0.02)
    free = _with(free, "absorptance", prior_median=0.5, prior_log_sd=1e-3)
    res = greybox.fit(second.model, second.experiments, free)
    assert [n for n in compiles[before:] if "_solve" in n] == []
    tau, absorptance = res.estimate("thermal.tau_s"), res.estimate("absorptance")
    assert tau.verdict == "at bound" and tau.bound == "upper"
    assert 0.0299 < tau.value <= 0.03
    assert absorptance.value == pytest.approx(0.5, rel=3e-3)
    scales = [p.scale for p in res.free if p.path == "camera.offset_m"]
    assert scales and scales != [q.scale for q in first.free if q.path == "camera.offset_m"]


def test_other_step_budgets_and_tolerances_compile_no_solver(compiles):
    """The optimiser's step budget and tolerances are inputs of the compiled solver too (every
    budget up to `MIN_STEP_BOUND` shares one program). Truth that they are the ones used: a
    budget of 2 steps ends after exactly 2 ("ran out of steps"), and tolerances 1e5 times
    looser stop the solve in fewer steps than the defaults."""
    d = two_run_chevron(8)
    default = greybox.fit(d.model, d.experiments, d.free, n_starts=1)
    before = len(compiles)
    short = greybox.fit(d.model, d.experiments, d.free, n_starts=1, max_steps=2)
    loose = greybox.fit(d.model, d.experiments, d.free, n_starts=1, rtol=0.1, atol=0.1)
    assert [n for n in compiles[before:] if "_solve" in n] == []
    assert short.status == "ran out of steps" and short.n_steps == 2 + 2  # and the re-fit's
    assert default.converged and loose.n_steps < default.n_steps


def test_a_batch_of_other_bounds_is_one_structure():
    """`fit_batch` groups devices by structure: devices whose free parameters differ only
    in their numbers (here tau's upper bound and the offsets' derived scales) are one group,
    one compiled solver, and each device is fitted with its own numbers (truth: the capped
    device ends at its bound, 30 ms; the other recovers tau = 45 ms within 3 sd)."""
    a, b = two_run_chevron(6), two_run_chevron(7)
    a = dataclasses.replace(a, free=tuple(_with(a.free, "camera.offset_m", scale=None)))
    capped = _with(b.free, "thermal.tau_s", upper=0.03, initial=0.02)
    b = dataclasses.replace(b, free=tuple(_with(capped, "camera.offset_m", scale=None)))
    batch = greybox.fit_batch([a, b], a.free)  # each device's own `free` overrides it
    assert batch.groups == 1
    tau_a = batch.results[a.name].estimate("thermal.tau_s")
    tau_b = batch.results[b.name].estimate("thermal.tau_s")
    assert abs(tau_a.value - 0.045) < 3 * tau_a.se
    assert tau_b.verdict == "at bound" and 0.0299 < tau_b.value <= 0.03


def _finite_difference_sd(result, wave, t, h=1e-5):
    """The delta method's sd of the response to `wave` at `t` from central differences of
    `greybox.simulate` (no forward-mode derivative) over the shared raw coordinates."""
    shared = [p for p in result.free if not p.per_experiment]
    raw = np.asarray(result.raw[: len(shared)], dtype=float)
    cov = np.asarray(result.posterior.covariance_raw)[: len(shared), : len(shared)]

    def response(r):
        model = greybox.parameters.with_shared(result.posterior.model, shared, r)
        return np.asarray(greybox.simulate(model, wave, t))

    cols = [
        (response(raw + h * e) - response(raw - h * e)).reshape(t.size) / (2 * h)
        for e in np.eye(raw.size)
    ]
    g = np.stack(cols, axis=-1)  # (N, P)
    return np.sqrt(np.einsum("np,pq,nq->n", g, cov, g))


def test_bands_of_other_runs_and_devices_compile_nothing(compiles):
    """A band (`Posterior.band`: the response to a waveform with its delta-method band) is one
    compiled function per structure: the model's values, the parameters' numbers and the
    waveform are its inputs. After the first band, the bands of the fit's other run and of
    another device of the structure compile nothing (they compiled the band's function
    again at every call: ~0.2-0.3 s each against a 0.02 s fit). Truth that each band is its
    own device's: the band's sd against central differences of `greybox.simulate`."""
    first, second = two_run_chevron(8), two_run_chevron(9)
    fits = [greybox.fit(d.model, d.experiments, d.free) for d in (first, second)]
    e0 = first.experiments[0]
    fits[0].posterior.band(e0.inputs, e0.t_s)
    before = len(compiles)
    wave = PulseTrain(0.015, 0.25, n_pulses=2, delay_s=0.05, tail_s=0.2)
    t = np.linspace(0.0, 0.6, 37)
    bands = [r.posterior.band(wave, t) for r in fits]
    e1 = first.experiments[1]
    fits[0].posterior.band(e1.inputs, e1.t_s)
    assert [n for n in compiles[before:] if "response_and_jacobian" in n] == []
    for r, b in zip(fits, bands):
        sd = np.asarray(b.sd_model).reshape(t.size)
        assert sd.max() > 0
        np.testing.assert_allclose(sd, _finite_difference_sd(r, wave, t), rtol=1e-4, atol=1e-12)
    assert not np.allclose(bands[0].sd_model, bands[1].sd_model, rtol=1e-3, atol=0.0)


def _tau(model):
    return model.thermal.tau_s


def test_the_same_function_propagated_through_another_fit_compiles_nothing(compiles):
    """`delta_method` and `propagate` compile once per function object and structure: the
    same `fn` through another device's fit compiles nothing, and gives that fit's numbers.
    Truth: the delta method's sd of tau is the fit's own reported standard error (from its
    covariance and the transform's derivative), and 4,000 draws spread as it says."""
    from greybox.uncertainty import delta_method, propagate

    fits = [greybox.fit(d.model, d.experiments, d.free) for d in map(two_run_chevron, (10, 11))]
    args = [(r.model, r.free, r.raw, r.covariance_raw) for r in fits]
    delta_method(_tau, *args[0])
    propagate(_tau, *args[0], 4000)
    before = len(compiles)
    value, cov = delta_method(_tau, *args[1])
    draws = propagate(_tau, *args[1], 4000, seed=1)
    assert compiles[before:] == []
    est = fits[1].estimate("thermal.tau_s")
    assert value[0] == pytest.approx(est.value, rel=1e-12)
    assert np.sqrt(cov[0, 0]) == pytest.approx(est.se, rel=1e-9)
    assert np.std(draws) == pytest.approx(est.se, rel=0.1)
    assert fits[0].estimate("thermal.tau_s").value != pytest.approx(est.value, rel=1e-6)
    # a callable that cannot be hashed (a dataclass with __call__) still works, compiled anew
    _, cov2 = delta_method(_Scaled(2.0), *args[1])
    assert np.sqrt(cov2[0, 0]) == pytest.approx(2.0 * est.se, rel=1e-9)


@dataclasses.dataclass
class _Scaled:
    factor: float

    def __call__(self, model):
        return self.factor * model.thermal.tau_s
