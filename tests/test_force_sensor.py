"""Force-sensor conversion (thesis eqs. 5.2-5.3), repeat averaging, and force-model selection."""

import numpy as np
import pytest

import greybox
from greybox import fit_table

ec = greybox.device_module("electrothermal_chevron")
SURFACE = ec.surface
ForceSensor, average_repeats = ec.ForceSensor, ec.average_repeats

SENSOR = ForceSensor(
    length_m=1e-3, thickness_m=50e-6, gauge_factor=100.0, bridge_V=5.0, stiffness_N_per_m=1000.0
)


def test_sensor_conversion_by_hand():
    # dU = 0.75 U gamma (1 - 0.5) h d / l^2 = 0.75*5*100*0.5*50e-6/1e-6 = 9375 V/m
    assert SENSOR.volts_per_m == pytest.approx(9375.0)
    assert float(SENSOR.deflection_m(10e-3)) == pytest.approx(10e-3 / 9375.0)
    assert float(SENSOR.force_N(10e-3)) == pytest.approx(1000.0 * 10e-3 / 9375.0)
    assert float(SENSOR.sensor_V(SENSOR.force_N(7e-3))) == pytest.approx(7e-3)
    with pytest.raises(ValueError, match="stiffness_N_per_m"):
        ForceSensor(1e-3, 50e-6, 100.0, 5.0, stiffness_N_per_m=0.0)


def test_average_repeats_and_bad_input():
    v = [0, 0, 0, 2, 2, 2]
    avg = average_repeats(v, [1.0, 2.0, 3.0, 4.0, 6.0, np.nan])
    np.testing.assert_allclose(avg.voltage_V, [0, 2])
    np.testing.assert_allclose(avg.mean, [2.0, 5.0])
    np.testing.assert_allclose(avg.se, [1.0 / np.sqrt(3), np.sqrt(2) / np.sqrt(2)])
    np.testing.assert_array_equal(avg.n, [3, 2])
    pooled_sd = np.sqrt((2 * 1.0 + 1 * 2.0) / 3)  # sds 1 and sqrt(2) with 2 and 1 dof
    np.testing.assert_allclose(avg.pooled_se, pooled_sd / np.sqrt([3, 2]))
    with pytest.raises(ValueError, match="zero repeats"):
        average_repeats(v, [1.0, 2.0, 3.0, np.nan, np.nan, np.nan])
    with pytest.raises(ValueError, match="zero repeats"):
        average_repeats(v, np.ones(6), expected_repeats=0)
    with pytest.raises(ValueError, match="negative voltage"):
        average_repeats([-2, -2, 0, 0], np.ones(4))


@pytest.fixture(scope="module")
def force_data():
    """Five repeats at 0, 2, ..., 20 V with 'wide deviations' (thesis §5.4), from the device."""
    truth = ec.SPEC.model()
    volts = np.repeat(np.arange(0.0, 21.0, 2.0), 5)
    force = np.asarray(ec.force_predictor(SENSOR.stiffness_N_per_m)(truth, volts))
    readings = SENSOR.sensor_V(force) + np.random.default_rng(3).normal(0.0, 2e-3, volts.size)
    avg = average_repeats(volts, SENSOR.force_N(readings), expected_repeats=5)
    return avg


def test_eighth_order_overfits_held_out_voltages(force_data):
    v, f, se = force_data.voltage_V, force_data.mean, force_data.pooled_se
    cv2 = SURFACE.cross_validate(SURFACE.polynomial_predictor(2), v, f)
    cv8 = SURFACE.cross_validate(SURFACE.polynomial_predictor(8), v, f)
    fit2, fit8 = SURFACE.fit_polynomial(v, f, 2), SURFACE.fit_polynomial(v, f, 8)
    assert fit8.rmse < fit2.rmse  # closer to the training points ...
    assert cv8.rmse > 3 * cv2.rmse  # ... far worse on held-out voltages
    assert fit2.criteria["aicc"] < fit8.criteria["aicc"]

    start = ec.SPEC.model(thermal__resistance_K_per_W=150.0, joule__tcr_per_K=0.0)
    predict = ec.force_predictor(SENSOR.stiffness_N_per_m)
    free = ec.force_free_parameters()

    def greybox(train, x, z):
        res = fit_table(start, predict, x, z, free, sigma=se, weights=train.astype(float))
        return np.asarray(predict(res.model, x))

    cvg = SURFACE.cross_validate(greybox, v, f)
    # no over-fit: comparable to order 2 (0.9-1.6x over seeds 0-7), far below order 8
    assert cvg.rmse < 2 * cv2.rmse and cvg.rmse < cv8.rmse / 3
    full = fit_table(start, predict, v, f, free, sigma=se)
    r_th = full.estimate("thermal.resistance_K_per_W")
    assert r_th.ci95[0] < ec.NOMINAL_RESISTANCE_K_PER_W < r_th.ci95[1]
