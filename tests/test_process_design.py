"""Design with process noise: the information of a run is the expected Fisher information of
the Kalman-filter likelihood, against an independent truth.

Truth: tests/ou_reference.py, the scalar OU process (one-node RC building with a known heater
input), whose readings are Gaussian with a closed-form mean and covariance
(Cov(x_j, x_k) = a^|k-j| P_min(j,k)); its Fisher information dmu' S^-1 dmu +
0.5 tr(S^-1 dS S^-1 dS) by numpy central differences. greybox builds the covariance from the
filter's discretisation and autodiff (greybox/stochastic/_fisher.py).

Measured: information equal to 1e-8 relative; on a 600-frame record the Cramer-Rao standard
errors at the estimate are the process-noise fit's (inverse Hessian) to < 1 % (Ci 0.00997
vs 0.00998, Rea 0.00760 vs 0.00760, q 0.177 vs 0.178, sd 0.0392 vs 0.0393; raw log units).
"""

import dataclasses

import numpy as np
import pytest

import greybox
from greybox.design import design_problem, run_information
from greybox.design._design import design_score
from tests import ou_device as od
from tests import ou_reference as ou

N = 600


def _raw(p):
    return np.array([float(f.to_raw(p[k])) for f, k in zip(od.FREE, od.NAMES)])


@pytest.fixture(scope="module")
def problem():
    # a known initial state: the first reading is conditioned on, as the fit does
    model = dataclasses.replace(od.model(ou.TRUTH), score_first=False)
    return design_problem(model, od.FREE, ["Ci", "Rea"], raw=_raw(ou.TRUTH))


def test_run_information_is_the_gaussian_information(problem):
    t = ou.frames(N)
    info = run_information(problem, [od.inputs(float(t[-1]) + ou.DT)], t)[0, 0]
    truth = ou.information(ou.TRUTH, N)
    np.testing.assert_allclose(info, truth, rtol=1e-6, atol=1e-6 * np.abs(truth).max())


def test_d_criterion_uses_it(problem):
    t = ou.frames(N)
    info = run_information(problem, [od.inputs(float(t[-1]) + ou.DT)], t)
    truth = ou.information(ou.TRUTH, N)
    # q and sd are nuisance parameters of the design: marginalised (Schur complement)
    m = truth[:2, :2] - truth[:2, 2:] @ np.linalg.solve(truth[2:, 2:], truth[2:, :2])
    d = np.linalg.slogdet(m)[1] / 2
    assert design_score(problem, info.sum(axis=1), "D") == pytest.approx(d, rel=1e-6)
    assert problem.sigma == pytest.approx([ou.TRUTH["sd"]])  # the model's measurement sd


def test_inverse_information_is_the_fit_covariance():
    y = ou.simulate(ou.TRUTH, N, 3)
    e = od.experiment(y)
    fit = greybox.fit(
        od.model(ou.TRUTH), [e], od.FREE, noise=greybox.ProcessNoise(od.STRUCTURE), n_starts=1
    )
    assert fit.status == "converged"
    p = design_problem(fit.model, od.FREE, ["Ci"], raw=fit.raw)
    info = run_information(p, [e.inputs], e.t_s)[0, 0]
    se_design = np.sqrt(np.diag(np.linalg.inv(info)))
    se_fit = np.sqrt(np.diag(fit.covariance_raw))
    np.testing.assert_allclose(se_design, se_fit, rtol=0.03)


def test_multilevel_design_refuses_process_noise(problem):
    c = greybox.design.LabConstraints.__new__(greybox.design.LabConstraints)
    with pytest.raises(ValueError, match="pulse_train"):
        greybox.design.design_experiment(problem, c, family="multilevel")
