"""Each physics block alone, against closed forms, quadrature and PHYSICS.md's derived tables."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy import integrate

from greybox.blocks._mechanics import (
    ChevronExact,
    ChevronLinear,
    ThermalElongation,
    chevron_blocked_force_N,
    chevron_stiffness_N_per_m,
    okada_tokumaru_cte,
)
from greybox.blocks._optics import material_absorptance
from greybox.blocks._spot import GaussianSpot, Rectangle, RectangularFrame
from greybox.blocks._thermal import FirstOrderThermal, ThermalNetwork

UM = 1e-6


def _quad_fraction(spot, x1, x2, y1, y2):
    w = spot.waist_m

    def intensity(y, x):
        return 2 / (np.pi * w**2) * np.exp(-2 * ((x - spot.x_m) ** 2 + (y - spot.y_m) ** 2) / w**2)

    return integrate.dblquad(intensity, x1, x2, y1, y2, epsabs=1e-13, epsrel=1e-11)[0]


@pytest.mark.parametrize("x0", [0.0, -50 * UM, 70 * UM])
def test_erf_spot_fraction_matches_quadrature(x0):
    spot = GaussianSpot(waist_m=100 * UM, x_m=x0, y_m=20 * UM)
    rect = Rectangle(-40 * UM, 110 * UM, -60 * UM, 30 * UM)
    expected = _quad_fraction(spot, -40 * UM, 110 * UM, -60 * UM, 30 * UM)
    assert float(rect.fraction(spot)) == pytest.approx(expected, rel=1e-9)


def test_frame_is_outer_minus_hole_and_matches_physics_table():
    # PHYSICS.md §3: frames 150 um outer / 90 um hole at x = -110 um; w = 100 um, x0 = -110 um
    frame = RectangularFrame.square(-110 * UM, 0.0, 150 * UM, 90 * UM)
    spot = GaussianSpot(100 * UM, -110 * UM, 0.0)
    outer = _quad_fraction(spot, -185 * UM, -35 * UM, -75 * UM, 75 * UM)
    hole = _quad_fraction(spot, -155 * UM, -65 * UM, -45 * UM, 45 * UM)
    assert float(frame.fraction(spot)) == pytest.approx(outer - hole, rel=1e-9)
    assert float(frame.fraction(spot)) == pytest.approx(0.351, abs=5e-4)


def test_optics_absorptance_matches_physics_table():
    assert float(material_absorptance("Si", 800e-9, 10e-6)) == pytest.approx(0.448, abs=1e-3)
    assert float(material_absorptance("Si", 800e-9, 1e-3)) == pytest.approx(0.673, abs=1e-3)
    assert float(material_absorptance("Au", 800e-9)) == pytest.approx(0.024, abs=1e-3)
    with pytest.raises(ValueError, match="no optical constants"):
        material_absorptance("Ge", 800e-9)


def test_exact_chevron_matches_physics_table_and_linear_limit():
    # PHYSICS.md §6, thesis geometry: a = 2 deg, L = 3.5 mm, dL = 91.3 nm -> 2.59 um exact,
    # 2.62 um linearised
    exact = ChevronExact(3.5e-3, np.deg2rad(2.0))
    linear = ChevronLinear(np.deg2rad(2.0))
    assert float(exact(0.0)) == 0.0
    assert float(exact(91.3e-9)) / UM == pytest.approx(2.59, abs=0.01)
    assert float(linear(91.3e-9)) / UM == pytest.approx(2.62, abs=0.01)
    # small-elongation limit: relative difference -> dL cos^2 a / (2 L sin^2 a), i.e. -> 0
    for dl in [1e-12, 1e-11, 1e-10]:
        rel = 1 - float(exact(dl)) / float(linear(dl))
        expected = dl * np.cos(np.deg2rad(2)) ** 2 / (2 * 3.5e-3 * np.sin(np.deg2rad(2)) ** 2)
        assert rel == pytest.approx(expected, rel=1e-3)
    # slope at zero equals the linear gain exactly
    assert float(jax.grad(exact)(0.0)) == pytest.approx(1 / np.sin(np.deg2rad(2.0)), rel=1e-12)


def test_elongation_and_cte():
    assert float(okada_tokumaru_cte(300.0)) == pytest.approx(2.57e-6, abs=0.01e-6)
    assert float(okada_tokumaru_cte(400.0)) == pytest.approx(3.21e-6, abs=0.01e-6)
    el = ThermalElongation(cte_per_K=2.6e-6, length_m=3.5e-3, beam_fraction=0.5)
    assert float(el(20.0)) == pytest.approx(2.6e-6 * 3.5e-3 * 10.0, rel=1e-12)


def test_stiffness_and_blocked_force_match_physics_numbers():
    a = np.deg2rad(2.0)
    k = chevron_stiffness_N_per_m(169e9, 20e-6, 100e-6, 3.5e-3, a)
    f = chevron_blocked_force_N(169e9, 20e-6, 100e-6, 2.6e-6, 20.0, a)
    assert float(k) == pytest.approx(241.5, rel=0.01)
    assert float(f) * 1e3 == pytest.approx(1.25, rel=0.03)


def test_one_node_network_equals_first_order_block():
    tau, r = 0.05, 800.0
    net = ThermalNetwork(jnp.array([tau / r]), jnp.array([1 / r]), jnp.zeros(0))
    a1, b1 = FirstOrderThermal(tau, r).linear_matrices()
    a2, b2 = net.linear_matrices()
    np.testing.assert_allclose(a1, a2, rtol=1e-12)
    np.testing.assert_allclose(b1, b2, rtol=1e-12)


def test_network_derivative_matches_its_matrices_and_radiation_linearisation():
    net = ThermalNetwork(
        capacitance_J_per_K=jnp.array([2e-3, 1e-3]),
        ground_conductance_W_per_K=jnp.array([5e-3, 4e-3]),
        coupling_conductance_W_per_K=jnp.array([2e-3]),
        couplings=((0, 1),),
        input_nodes=(0, 1),
        sensor_nodes=(1,),
        sensor_tau_s=jnp.array([3.0]),
    )
    x, q = jnp.array([3.0, 1.0, 0.5]), jnp.array([0.02, 0.01])
    a, b = net.linear_matrices()
    np.testing.assert_allclose(net.derivative(x, q), a @ x + b @ q, rtol=1e-12)
    # hand-computed node 0: (0.02 - 5e-3*3 - 2e-3*(3-1)) / 2e-3
    assert float(net.derivative(x, q)[0]) == pytest.approx((0.02 - 0.015 - 0.004) / 2e-3)
    # sensor lag: (node1 - s) / tau
    assert float(net.derivative(x, q)[2]) == pytest.approx((1.0 - 0.5) / 3.0)
    rad = ThermalNetwork(
        jnp.array([2e-3]),
        jnp.array([5e-3]),
        jnp.zeros(0),
        radiation_ground_W_per_K4=jnp.array([0.9 * 5.67e-8 * 1e-3]),
    )
    small = jnp.array([1e-4])
    a_lin, _ = rad.linearised_matrices()
    np.testing.assert_allclose(rad.derivative(small, jnp.zeros(1)), a_lin @ small, rtol=1e-3)
    with pytest.raises(ValueError, match="adaptive"):
        rad.linear_matrices()
