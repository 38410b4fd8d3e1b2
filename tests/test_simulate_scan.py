"""The ZOH path's two scans (sequential and associative) give the same readings.

Truth: the sequential scan x+ = Phi x + Gamma u, stepped one interval after another, which
tests/test_simulate.py checks against closed forms; the associative scan composes the same
interval maps in a different order (log depth), so the two may differ only by rounding.
Every built-in linear device (an `AbstractLinearDevice` for some structural option) is
simulated on irregular frame times with input switches between and on frames.
"""

import itertools

import numpy as np
import pytest

import greybox
from greybox._model.device import AbstractLinearDevice
from greybox._model.waveforms import PiecewiseConstant
from greybox._simulate.schedules import schedule_for
from greybox._simulate.simulate import (
    ASSOCIATIVE_MIN_INTERVALS,
    simulate,
    zoh_scan_kind,
)

# options tried per device (every combination); only the linear builds are kept
OPTION_GRID = {
    "thermal_nodes": (1, 3),
    "elongation_lag": (False, True),
    "radiation": (False, True),
    "shared_sensor_lag": (False, True),
}


def linear_builds():
    out = []
    for name in greybox.available_devices():
        spec = greybox.get_device(name)
        keys = [o.name for o in spec.options if o.name in OPTION_GRID]
        for values in itertools.product(*(OPTION_GRID[k] for k in keys)):
            options = dict(zip(keys, values))
            model = spec.model(options)
            if isinstance(model, AbstractLinearDevice):
                out.append(pytest.param(model, id=f"{name}-{options}"))
    return out


BUILDS = linear_builds()


def test_the_linear_devices_are_found():
    ids = " ".join(p.id for p in BUILDS)
    assert "chevron_laser" in ids and "tclab" in ids
    assert len(BUILDS) >= 6


def irregular_record(model, seed=0):
    """(inputs, frame times): random levels switching at random instants, some on a frame,
    and jittered frames with gaps, over ~4 time constants of the slowest device."""
    rng = np.random.default_rng(seed)
    span = 40.0 if model.n_inputs == 2 else 0.4  # TCLab (minutes) vs chevron (tens of ms)
    t = np.sort(rng.uniform(0.01 * span, span, 300))
    t = t[np.concatenate([[True], np.diff(t) > 1e-6 * span])]
    switches = np.sort(np.concatenate([rng.uniform(0, span, 12), t[[10, 50, 200]]]))
    scale = 50.0 if model.n_inputs == 2 else 0.02  # % heater, W laser
    levels = scale * rng.uniform(0, 1, (switches.size, model.n_inputs))
    return PiecewiseConstant(switches, levels.reshape(switches.size, -1), span), t


@pytest.mark.parametrize("model", BUILDS)
def test_associative_scan_equals_sequential(model):
    inputs, t = irregular_record(model)
    dt = np.asarray(schedule_for(model, inputs, t)["dt"][0])
    assert np.count_nonzero(dt) > t.size  # input switches between frames add intervals
    seq = simulate(model, inputs, t, method="zoh", zoh_scan="sequential")
    par = simulate(model, inputs, t, method="zoh", zoh_scan="associative")
    assert np.all(np.isfinite(seq)) and np.ptp(seq) > 0
    scale = np.max(np.abs(seq), axis=0)
    np.testing.assert_allclose(par, seq, rtol=1e-12, atol=0)
    assert np.max(np.abs(par - seq) / scale) < 1e-12


def test_auto_scan_choice():
    assert zoh_scan_kind(10, "sequential") == "sequential"
    assert zoh_scan_kind(10, "associative") == "associative"
    on_cpu = greybox._simulate.simulate.jax.default_backend() == "cpu"
    assert zoh_scan_kind(10) == ("sequential" if on_cpu else "associative")
    assert zoh_scan_kind(ASSOCIATIVE_MIN_INTERVALS) == "associative"
    with pytest.raises(ValueError, match="zoh_scan"):
        zoh_scan_kind(10, "parallel")
