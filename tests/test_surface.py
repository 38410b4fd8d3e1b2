"""Polynomial surfaces and curves (thesis ch. 5 fits), grid checks, information criteria, CV."""

import numpy as np
import pytest

import greybox

SURFACE = greybox.device_module("electrothermal_chevron").surface  # noqa: E402


# Thesis eq. 5.1 coefficients as printed (poly32 in amplitude x [V] and frequency y [Hz]); the OCR
# lost the last monomial, taken here as the ninth poly32 term x*y^2.
THESIS_POLY32 = np.array(
    [267.9, 4.359, -0.01172, -0.5892, 0.003353, 0.000032, 0.04129, -0.000359, -0.001318]
)


def _thesis_grid():
    a, f = np.meshgrid(np.arange(0.0, 25.0, 2.0), np.arange(0.0, 401.0, 10.0), indexing="ij")
    return a.ravel(), f.ravel()


def test_matlab_poly32_term_order():
    assert SURFACE.polynomial_terms((3, 2)).tolist() == [
        [0, 0],
        [1, 0],
        [0, 1],
        [2, 0],
        [1, 1],
        [0, 2],
        [3, 0],
        [2, 1],
        [1, 2],
    ]
    assert len(SURFACE.polynomial_terms(3)) == 4 and len(SURFACE.polynomial_terms((3, 3))) == 10


def test_surface_fit_reproduces_known_coefficients_on_noise_free_data():
    a, f = _thesis_grid()
    x = np.column_stack([a, f])
    z = SURFACE.design_matrix(x, SURFACE.polynomial_terms((3, 2))) @ THESIS_POLY32
    fit = SURFACE.fit_polynomial(x, z, (3, 2))
    np.testing.assert_allclose(fit.coefficients, THESIS_POLY32, rtol=1e-9)
    assert fit.r_squared == pytest.approx(1.0, abs=1e-12) and fit.rmse < 1e-9
    xs, ys, zz = SURFACE.grid(fit, (0, 25), (0, 400), dx=0.1, dy=1.0)
    assert zz.shape == (251, 401)
    i, j = 123, 257  # 12.3 V, 257 Hz
    by_hand = sum(
        c * xs[i] ** p * ys[j] ** q
        for c, (p, q) in zip(THESIS_POLY32, SURFACE.polynomial_terms((3, 2)))
    )
    assert zz[i, j] == pytest.approx(by_hand, rel=1e-10)


def test_r_squared_rmse_and_criteria_by_hand():
    # line through (0,0), (1,1), (2,1), (3,2): slope 0.6, intercept 0.1, residuals -.1 .3 -.3 .1
    fit = SURFACE.fit_polynomial([0, 1, 2, 3], [0, 1, 1, 2], 1)
    np.testing.assert_allclose(fit.coefficients, [0.1, 0.6], atol=1e-12)
    assert fit.r_squared == pytest.approx(1 - 0.2 / 2.0)
    assert fit.rmse == pytest.approx(np.sqrt(0.2 / 4)) and fit.rmse_dof == pytest.approx(
        np.sqrt(0.1)
    )
    assert fit.criteria["aic"] == pytest.approx(4 * np.log(0.05) + 4)
    assert fit.criteria["bic"] == pytest.approx(4 * np.log(0.05) + 2 * np.log(4))
    assert fit.criteria["aicc"] == pytest.approx(4 * np.log(0.05) + 4 + 12)


def test_cross_validation_is_exact_for_the_true_degree_and_not_for_too_low():
    x = np.linspace(0, 20, 11)
    z = 2.0 + 0.5 * x + 0.03 * x**2
    right = SURFACE.cross_validate(SURFACE.polynomial_predictor(2), x, z)
    wrong = SURFACE.cross_validate(SURFACE.polynomial_predictor(1), x, z)
    assert right.rmse < 1e-9 and wrong.rmse > 0.1


def test_grid_check_rejects_bad_tables():
    a, f = _thesis_grid()
    z = np.zeros_like(a)
    amps, freqs, table = SURFACE.check_grid(a, f, z)
    assert table.shape == (13, 41) and amps[-1] == 24 and freqs[-1] == 400
    with pytest.raises(ValueError, match="ragged"):
        SURFACE.check_grid(a[1:], f[1:], z[1:])
    with pytest.raises(ValueError, match="negative voltage"):
        SURFACE.check_grid(a - 2.0, f, z)
    with pytest.raises(ValueError, match="more than once"):
        SURFACE.check_grid(np.append(a, a[0]), np.append(f, f[0]), np.append(z, 0.0))
    with pytest.raises(ValueError, match="different lengths"):
        SURFACE.check_grid(a, f, z[:-1])
    with pytest.raises(ValueError, match="cannot be determined"):
        SURFACE.fit_polynomial([0.0, 1.0, 2.0], [1.0, 2.0, 3.0], 8)
