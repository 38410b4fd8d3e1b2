"""Laser waveforms: exact edges, levels, stitching and input validation."""

import numpy as np
import pytest

from greybox._model.waveforms import (
    PiecewiseConstant,
    PulseTrain,
    concatenate,
    from_samples,
    multilevel_prbs,
    stack_channels,
)


def test_pulse_train_edges_and_mean_power():
    w = PulseTrain(power_W=0.02, period_s=0.4, duty=0.25, n_pulses=5, delay_s=0.1, tail_s=0.3)
    edges = w.switch_times()
    rises = 0.1 + 0.4 * np.arange(5)
    np.testing.assert_allclose(edges, np.column_stack([rises, rises + 0.1]).ravel(), atol=1e-15)
    assert w.duration_s == pytest.approx(0.1 + 2.0 + 0.3)
    # on for 5 x 0.1 s at 20 mW over 2.4 s
    assert w.to_piecewise().mean() == pytest.approx(0.02 * 0.5 / 2.4)
    assert w(0.05) == 0.0 and w(0.1) == 0.02 and w(0.199999) == 0.02 and w(0.2) == 0.0


def test_concatenate_shifts_and_inserts_gaps():
    a = PulseTrain(0.01, 0.2, 0.5, 2)
    b = PulseTrain(0.03, 1.0, 0.5, 1)
    c = concatenate([a, b], gaps_s=0.5)
    # a lasts 0.4 s, then 0.5 s off, then b starts at 0.9 s
    assert c.end_s == pytest.approx(0.4 + 0.5 + 1.0)
    np.testing.assert_allclose(c.switch_times(), [0.0, 0.1, 0.2, 0.3, 0.9, 1.4], atol=1e-12)
    assert c(1.0) == 0.03 and c(0.5) == 0.0


def test_prbs_is_deterministic_and_uses_only_given_levels():
    levels = [0.0, 0.01, 0.025]
    a = multilevel_prbs(levels, hold_s=0.1, n_holds=200, seed=3)
    b = multilevel_prbs(levels, hold_s=0.1, n_holds=200, seed=3)
    np.testing.assert_array_equal(a.times_s, b.times_s)
    assert set(np.unique(a.values)) <= set(levels) and len(np.unique(a.values)) == 3
    # holds are multiples of hold_s and consecutive levels differ (repeats merged)
    np.testing.assert_allclose(np.round(a.times_s / 0.1), a.times_s / 0.1, atol=1e-9)
    assert np.all(np.diff(a.values) != 0)


def test_stack_channels_merges_breakpoints():
    s = stack_channels([PulseTrain(1.0, 1.0, 0.5, 2), PulseTrain(2.0, 0.6, 0.5, 2)])
    assert s.n_channels == 2
    np.testing.assert_allclose(s(np.array([0.2, 0.4, 0.7, 1.1])), [[1, 2], [1, 0], [0, 2], [1, 0]])


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(power_W=-0.01, period_s=0.2), "power_W"),
        (dict(power_W=0.01, period_s=0.0), "period_s"),
        (dict(power_W=0.01, period_s=0.2, duty=1.5), "duty"),
        (dict(power_W=0.01, period_s=0.2, n_pulses=0), "n_pulses"),
    ],
)
def test_pulse_train_rejects_bad_values(kwargs, field):
    with pytest.raises(ValueError, match=field):
        PulseTrain(**kwargs)


def test_logged_trace_rejects_bad_samples():
    # the sign of a level is the input channel's business (a force may be negative; a laser
    # power may not, which the loader checks against the channel's declared range)
    wave = from_samples([0, 1, 2], [0.0, -1e-3, 0.0], name="force_N")
    assert float(wave(1.5)) == -1e-3
    with pytest.raises(ValueError, match="NaN"):
        from_samples([0, 1, 2], [0.0, np.nan, 0.0], name="laser_mW")
    with pytest.raises(ValueError, match="strictly increasing"):
        from_samples([0, 2, 1], [0.0, 1e-3, 0.0])
    with pytest.raises(ValueError, match="lengths must match"):
        from_samples([0, 1], [0.0, 1e-3, 0.0])
    with pytest.raises(ValueError, match="strictly increasing"):
        PiecewiseConstant(np.array([0.0, 0.0]), np.array([1.0, 2.0]), 1.0)
