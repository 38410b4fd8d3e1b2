"""Gait analysis of the micro-robot (pure functions, PHYSICS.md §5, §9): pose under a pulse
train on a uniform, edge-aligned grid, step per cycle and speed against period and duty, and
turning rate against the left/right absorbed-power ratio.

Every laser cycle is cut into `steps_per_cycle` equal intervals (each split again into the
model's `substeps`), so the array shapes depend only on the cycle count: a sweep over periods,
duties or spot positions is one `jax.vmap` and one compilation. The laser is on in an
interval when its mid-phase is below the duty, so duties are resolved to 1/steps_per_cycle.
SI units: s, W, m, rad.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from greybox.parameters import set_values


def pulse_schedule(period_s, duty, power_W, n_cycles: int, steps_per_cycle: int):
    """(interval lengths dt (n,) [s], laser power per interval (n,) [W]) of a pulse train."""
    n = n_cycles * steps_per_cycle
    k = jnp.arange(n)
    phase = (jnp.mod(k, steps_per_cycle) + 0.5) / steps_per_cycle
    power = jnp.where(phase < duty, power_W, 0.0) * jnp.ones(n)
    return jnp.full(n, period_s / steps_per_cycle), power


def pose_history(model, period_s, duty, power_W, n_cycles: int, steps_per_cycle: int = 20):
    """States (n + 1, 14) at the interval ends of a pulse train started cold at pose 0."""
    dt, power = pulse_schedule(period_s, duty, power_W, n_cycles, steps_per_cycle)
    return model.grid_states(model.initial_state(), dt, power)


def cycle_summary(model, states, steps_per_cycle: int):
    """Per-cycle body advance along the start heading [m], heading change [rad] and per-side
    stroke swing max - min (n_cycles, 2) [m] from `pose_history` states."""
    ends = states[::steps_per_cycle]
    pose = ends[:, 4:7]
    advance = jnp.diff(pose[:, 0])
    turn = jnp.diff(pose[:, 2])
    strokes = jax.vmap(model.strokes_m)(states[1:, :4]).reshape(-1, steps_per_cycle, 2)
    swing = strokes.max(axis=1) - strokes.min(axis=1)
    return advance, turn, swing


def speed_vs_period(model, periods_s, duty, power_W, n_cycles: int = 8, steps_per_cycle: int = 20):
    """Last-cycle step [m], speed = step/period [m/s] and stroke swing (left) [m] per period."""

    def one(period):
        states = pose_history(model, period, duty, power_W, n_cycles, steps_per_cycle)
        advance, _, swing = cycle_summary(model, states, steps_per_cycle)
        return advance[-1], advance[-1] / period, swing[-1, 0]

    step, speed, swing = jax.vmap(one)(jnp.asarray(periods_s, dtype=float))
    return {
        "period_s": jnp.asarray(periods_s),
        "step_m": step,
        "speed_m_per_s": speed,
        "stroke_swing_m": swing,
    }


def speed_vs_duty(model, duties, period_s, power_W, n_cycles: int = 8, steps_per_cycle: int = 20):
    """Last-cycle step [m] and speed [m/s] for each duty at a fixed period and on-power."""

    def one(duty):
        states = pose_history(model, period_s, duty, power_W, n_cycles, steps_per_cycle)
        advance, _, _ = cycle_summary(model, states, steps_per_cycle)
        return advance[-1], advance[-1] / period_s

    step, speed = jax.vmap(one)(jnp.asarray(duties, dtype=float))
    return {"duty": jnp.asarray(duties), "step_m": step, "speed_m_per_s": speed}


def turning_vs_power_ratio(
    model, spot_y_m, period_s, duty, power_W, n_cycles: int = 8, steps_per_cycle: int = 20
):
    """For each lateral spot position [m]: the absorbed left/right power ratio at the start
    pose and the mean turning rate d(psi)/dt [rad/s] and speed [m/s] over the run (psi > 0 is
    counter-clockwise, i.e. towards the left)."""

    def one(y):
        m = set_values(model, ["spot.y_m"], [y])
        fractions = m.absorbed_fractions(jnp.zeros(3))
        states = pose_history(m, period_s, duty, power_W, n_cycles, steps_per_cycle)
        duration = n_cycles * period_s
        return fractions[0] / fractions[1], states[-1, 6] / duration, states[-1, 4] / duration

    ratio, rate, speed = jax.vmap(one)(jnp.asarray(spot_y_m, dtype=float))
    return {
        "spot_y_m": jnp.asarray(spot_y_m),
        "power_ratio_left_right": ratio,
        "turn_rate_rad_per_s": rate,
        "speed_m_per_s": speed,
    }
