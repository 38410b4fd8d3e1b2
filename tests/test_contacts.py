"""Stick-slip contact blocks against closed forms (PHYSICS.md §5, §8, §14)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from greybox.blocks._contacts import (
    FrictionContacts,
    FrictionLaw,
    PlayContacts,
    directional_friction_N,
    play_step_per_cycle_m,
    smooth_clip,
    soft_min_force,
)

H = 1e-3  # s
PERIOD = 0.5  # s
TAU = 0.05  # s
NOMINAL = dict(
    foot_forward_N=0.3e-6,
    foot_backward_N=1.5e-6,
    dimple_forward_N=0.8e-6,
    dimple_backward_N=0.8e-6,
    stiffness_N_per_m=5.0,
)


def stroke_series(amplitude_m, n_cycles=3):
    """Free stroke of a first-order thermal node under a 50 % square wave, sampled at h."""
    n = int(round(n_cycles * PERIOD / H))
    on = (np.mod(np.arange(n) * H, PERIOD) < PERIOD / 2).astype(float)
    theta = np.zeros(n + 1)
    decay = np.exp(-H / TAU)
    for i in range(n):
        theta[i + 1] = decay * theta[i] + (1 - decay) * on[i]
    return jnp.asarray(amplitude_m * theta[1:])


@eqx.filter_jit
def run_play(contacts, strokes):
    def f(c, s):
        u, x = contacts.step(c[0], c[1], s)
        return (u, x), x

    return jax.lax.scan(f, (0.0, 0.0), strokes)[1]


@eqx.filter_jit
def run_friction(contacts, strokes):
    def f(c, s):
        u, x, v = contacts.step(c[0], c[1], s, H, c[2])
        return (u, x, v), x

    return jax.lax.scan(f, (0.0, 0.0, jnp.zeros(2)), strokes)[1]


def last_cycle_advance(x):
    per = int(round(PERIOD / H))
    return float(x[-1] - x[-1 - per])


def test_smooth_helpers_match_exact_functions():
    x = jnp.linspace(-3.0, 3.0, 61)
    np.testing.assert_allclose(smooth_clip(x, -1.0, 1.0, 1e-4), np.clip(x, -1, 1), atol=1e-4)
    assert float(soft_min_force(0.3e-6, 0.8e-6)) == pytest.approx(0.3e-6, rel=1e-6)
    # directional law: f(0) = 0, saturates at +F+ and -F- (plus the viscous term)
    v = jnp.array([0.0, 1e-3, -1e-3])
    f = directional_friction_N(v, 0.3e-6, 1.5e-6, 1e-8, 0.1, 1e-5)
    np.testing.assert_allclose(f, [0.0, 0.3e-6 + 1e-8, -1.5e-6 - 1e-8], rtol=1e-9, atol=1e-20)


def test_play_width_is_the_physics_anchor():
    # PHYSICS.md §14: W = (F_a + F_b)/k = (0.3 + 0.8) uN / 5 N/m = 0.220 um
    assert float(PlayContacts(**NOMINAL).play_width_m()) == pytest.approx(0.220e-6, rel=1e-4)


@pytest.mark.parametrize("amplitude_um", [0.384, 0.30, 0.15])
def test_step_per_cycle_closed_form_play_and_detailed(amplitude_um):
    strokes = stroke_series(amplitude_um * 1e-6)
    per = int(round(PERIOD / H))
    s_pp = float(strokes[-per:].max() - strokes[-per:].min())
    play = PlayContacts(**NOMINAL)
    expected = float(play_step_per_cycle_m(s_pp, play.play_width_m()))
    step_play = last_cycle_advance(run_play(play, strokes))
    # detailed solver with v_eps = 0.1 nm/s: creep is negligible, so it meets the play operator
    detailed = FrictionContacts(**NOMINAL, law=FrictionLaw(v_eps_m_per_s=1e-10))
    step_detailed = last_cycle_advance(run_friction(detailed, strokes))
    assert step_play == pytest.approx(expected, abs=2e-9)
    assert step_detailed == pytest.approx(expected, abs=4e-9)
    if amplitude_um == 0.15:  # below threshold S_pp < W: no motion at all
        assert expected == 0.0 and abs(step_detailed) < 4e-9


def test_no_net_motion_without_friction_asymmetry():
    # isotropic feet (F_f+ = F_f- = 0.3 uN < F_d): the feet slip both ways, the body only creeps
    iso = dict(NOMINAL, foot_backward_N=0.3e-6)
    strokes = stroke_series(0.384e-6)
    assert abs(float(run_play(PlayContacts(**iso), strokes)[-1])) < 1e-12
    detailed = FrictionContacts(**iso, law=FrictionLaw(v_eps_m_per_s=1e-10))
    assert abs(float(run_friction(detailed, strokes)[-1])) < 1e-9
    # while the anisotropic nominal contacts walk ~0.16 um per cycle
    assert float(run_play(PlayContacts(**NOMINAL), strokes)[-1]) > 0.3e-6


def test_gradients_forward_equal_reverse_through_detailed_solver():
    strokes = stroke_series(0.384e-6, n_cycles=1)

    def final(values):
        c = FrictionContacts(values[0], 1.5e-6, values[1], 0.8e-6, values[2])
        return run_friction(c, strokes)[-1]

    x0 = jnp.array([0.3e-6, 0.8e-6, 5.0])
    rev = jax.grad(final)(x0)
    fwd = jax.jacfwd(final)(x0)
    assert np.all(np.isfinite(rev))
    np.testing.assert_allclose(rev, fwd, rtol=1e-8)
    # independent check of one entry by central differences
    d = 1e-9
    fd = (final(x0.at[0].add(d * 0.3e-6)) - final(x0.at[0].add(-d * 0.3e-6))) / (2 * d * 0.3e-6)
    assert float(rev[0]) == pytest.approx(float(fd), rel=1e-3)
