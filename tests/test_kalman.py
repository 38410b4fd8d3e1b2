"""Continuous-discrete Kalman filter and stochastic ML fit, against independent references.

References: closed forms and quadrature for Van Loan's discretisation; the dense joint Gaussian
of a whole record (moments from the stationary Lyapunov solution and `scipy.linalg.expm`) for the
likelihood, the filtered and the smoothed states; a numpy extended Kalman filter for nonlinear
outputs; central finite differences for gradients; a closed-form stochastic simulator (not the
filter) for the RC parameter-recovery test, with a scipy least-squares baseline.
"""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla
import scipy.optimize
import scipy.stats
from scipy.integrate import quad_vec
from threadpoolctl import threadpool_limits

from greybox._estimate.stochastic_fit import fit_stochastic, ljung_box
from greybox.stochastic._kalman import (
    FilterGrid,
    LinearGaussianSDE,
    discretise,
    discretise_steps,
    free_run,
    kalman_filter,
    log_likelihood,
    rts_smoother,
    with_output_random_walks,
)


@pytest.fixture(autouse=True, scope="module")
def single_threaded_blas():
    """The numpy references multiply 2x2 matrices thousands of times: multithreaded BLAS made
    them 60x slower on the 2-core test machine (0.64 s vs 0.01 s for one dense reference)."""
    with threadpool_limits(1):
        yield


# ---------------------------------------------------------------------------------------------
# A small LTI case: 2 states, 1 input switching between frames, 2 correlated outputs
# ---------------------------------------------------------------------------------------------

A2 = np.array([[-0.5, 0.3], [-0.2, -1.1]])
B2 = np.array([[1.0], [0.5]])
QC2 = np.array([[0.3, 0.1], [0.1, 0.2]])
C2 = np.array([[1.0, 0.0], [0.5, 1.0]])
R2 = np.array([[0.1, 0.02], [0.02, 0.05]])
D2 = np.array([[0.2], [0.0]])
OFFSET2 = np.array([0.3, -0.1])
X02 = np.array([0.5, -1.0])
P02 = np.array([[0.4, 0.1], [0.1, 0.3]])
# the same with a noise-free second state (deterministic x2, P0 and Qc rank 1): P is singular
# at every step, which the RTS smoother must handle (pseudo-inverse)
A2_SINGULAR = np.array([[-0.5, 0.3], [0.0, -1.1]])
QC2_SINGULAR = np.array([[0.3, 0.0], [0.0, 0.0]])
P02_SINGULAR = np.array([[0.4, 0.0], [0.0, 0.0]])
NOISE = {"full": (A2, QC2, P02), "singular": (A2_SINGULAR, QC2_SINGULAR, P02_SINGULAR)}
U_TIMES = np.array([2.0, 3.3, 5.5, 9.0])  # all after the first frame: both t0 cases share shapes
U_LEVELS = np.array([[1.0], [-0.5], [2.0], [0.0]])


def lti_model(**overrides):
    kw = dict(A=A2, B=B2, Qc=QC2, C=C2, R=R2, x0=X02, P0=P02, D=D2, d=OFFSET2) | overrides
    return LinearGaussianSDE(**kw)


def lti_record(pattern=0):
    """12 irregular frames of 2 outputs with dropped values (two NaN patterns)."""
    rng = np.random.default_rng(0)
    t = 0.4 + np.cumsum(rng.uniform(0.3, 1.5, 12))
    y = rng.normal(size=(12, 2))
    if pattern == 0:
        y[3, 1] = np.nan  # one output dropped
        y[6] = np.nan  # whole frame dropped
    else:
        y[0] = np.nan  # the first frame, then
        y[[5, 11], [0, 1]] = np.nan  # single outputs, including in the last frame
    return t, y


def u_at(t):
    i = np.searchsorted(U_TIMES, t, side="right") - 1
    return U_LEVELS[i] if i >= 0 else np.zeros(1)


@functools.cache
def dense_reference(t0, pattern=0, noise="full"):
    """Joint Gaussian of (x(t_1..t_N), y_1..y_N) from closed forms, without Van Loan.

    On each constant-input piece, with m_inf = -A^{-1} B u and P_inf the solution of
    A P + P A^T + Qc = 0 (A is stable): m(t+h) = m_inf + e^{Ah} (m - m_inf) and
    P(t+h) = P_inf + e^{Ah} (P - P_inf) e^{A^T h}; Cov(x_j, x_k) = P_j e^{A^T (t_k - t_j)}.
    Returns the log-density of the finite data and a function conditioning on a subset.
    """
    t, y = lti_record(pattern)
    A, Qc, P0 = NOISE[noise]
    n, N = 2, t.size
    P_inf = sla.solve_continuous_lyapunov(A, -Qc)
    pts = np.unique(np.concatenate([[t0], U_TIMES[(U_TIMES > t0) & (U_TIMES < t[-1])], t]))
    m, P = X02.copy(), P0.copy()
    at = {t0: (m, P)}
    for a, b in zip(pts[:-1], pts[1:]):
        E = sla.expm(A * (b - a))
        m_inf = -np.linalg.solve(A, B2 @ u_at(a))
        m = m_inf + E @ (m - m_inf)
        P = P_inf + E @ (P - P_inf) @ E.T
        at[b] = (m, P)
    mx = np.array([at[tk][0] for tk in t])
    Px = np.array([at[tk][1] for tk in t])
    Sx = np.zeros((N * n, N * n))
    for j in range(N):
        for k in range(j, N):
            c = Px[j] @ sla.expm(A * (t[k] - t[j])).T
            Sx[j * n : (j + 1) * n, k * n : (k + 1) * n] = c
            Sx[k * n : (k + 1) * n, j * n : (j + 1) * n] = c.T
    Cb = np.kron(np.eye(N), C2)
    my = (mx @ C2.T + np.array([u_at(tk) for tk in t]) @ D2.T + OFFSET2).ravel()
    Sy = Cb @ Sx @ Cb.T + np.kron(np.eye(N), R2)
    Sxy = Sx @ Cb.T
    yv = y.ravel()
    ok = np.isfinite(yv)
    loglik = scipy.stats.multivariate_normal(my[ok], Sy[np.ix_(ok, ok)]).logpdf(yv[ok])

    def condition(keep):
        gain = np.linalg.solve(Sy[np.ix_(keep, keep)], Sxy[:, keep].T).T
        return mx.ravel() + gain @ (yv[keep] - my[keep]), Sx - gain @ Sxy[:, keep].T

    return loglik, condition, ok


@pytest.fixture(
    params=[
        ("t0_before_first_frame", "full"),
        ("t0_at_first_frame", "full"),
        ("t0_before_first_frame", "singular"),
    ],
    ids="-".join,
)
def lti_case(request):
    """(t0, noise, t, y, grid, model); every case has the same array shapes (one compile)."""
    start, noise = request.param
    t, y = lti_record()
    t0 = 0.0 if start == "t0_before_first_frame" else float(t[0])
    A, Qc, P0 = NOISE[noise]
    model = lti_model(A=A, Qc=Qc, P0=P0)
    return t0, noise, t, y, FilterGrid(t, U_TIMES, U_LEVELS, t0_s=t0), model


# ---------------------------------------------------------------------------------------------
# Van Loan discretisation and the grid
# ---------------------------------------------------------------------------------------------


def quadrature(h, A=A2):
    """int_0^h e^{As} B ds and int_0^h e^{As} Qc e^{A^T s} ds by adaptive quadrature."""

    def integrand(s):
        E = sla.expm(A * s)
        return np.concatenate([(E @ B2).ravel(), (E @ QC2 @ E.T).ravel()])

    out = quad_vec(integrand, 0.0, h, epsabs=1e-15, epsrel=1e-13, norm="max", limit=2000)[0]
    return out[:2].reshape(2, 1), out[2:].reshape(2, 2)


def test_van_loan_scalar_ou_equals_closed_form():
    a, b, q = 0.7, 2.0, 0.3
    for h in (1e-3, 0.1, 1.0, 7.5, 100.0):
        Ad, Bd, Qd = discretise(jnp.array([[-a]]), jnp.array([[b]]), jnp.array([[q]]), h)
        np.testing.assert_allclose(Ad[0, 0], np.exp(-a * h), rtol=1e-13)
        np.testing.assert_allclose(Bd[0, 0], -b / a * np.expm1(-a * h), rtol=1e-13)
        np.testing.assert_allclose(Qd[0, 0], -q / (2 * a) * np.expm1(-2 * a * h), rtol=1e-13)


@pytest.mark.parametrize("stiff", [False, True], ids=["2x2", "stiff-non-normal-2x2"])
def test_van_loan_2x2_equals_quadrature(stiff):
    """The stiff case (||A h|| = 90) is where squaring Van Loan's exponential itself, whose
    e^{-Ah} block grows like e^{90}, returned Qd wrong by a factor 300; sub-steps and doubling
    keep it exact."""
    A = np.array([[-50.0, 40.0], [0.3, -0.1]]) if stiff else A2
    h = 1.0 if stiff else 0.8
    Ad, Bd, Qd = discretise(A, B2, QC2, h)
    Bd_ref, Qd_ref = quadrature(h, A)
    np.testing.assert_allclose(Ad, sla.expm(A * h), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Bd, Bd_ref, rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(Qd, Qd_ref, rtol=1e-12, atol=1e-15)


def test_grid_steps_through_every_switch_and_frame():
    t = np.array([1.0, 1.5, 3.0])
    g = FilterGrid(t, [0.5, 1.2, 1.5, 2.0], [1.0, 2.0, 3.0, 4.0], t0_s=0.0)
    ends = np.array([0.5, 1.0, 1.2, 1.5, 2.0, 3.0])
    np.testing.assert_allclose(g.dt_s, np.diff(np.concatenate([[0.0], ends])))
    np.testing.assert_allclose(g.u[:, 0], [0.0, 1.0, 1.0, 2.0, 3.0, 4.0])  # level at step start
    np.testing.assert_array_equal(g.frame, [-1, 0, -1, 1, -1, 2])
    np.testing.assert_allclose(g.u_frame[:, 0], [1.0, 3.0, 4.0])  # right-continuous at frames
    at_first = FilterGrid(t, t0_s=1.0)
    np.testing.assert_allclose(at_first.dt_s, [0.0, 0.5, 1.5])
    with pytest.raises(ValueError, match="strictly increasing"):
        FilterGrid([0.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="after the first frame"):
        FilterGrid(t, t0_s=2.0)
    with pytest.raises(ValueError, match="expected"):
        LinearGaussianSDE(A2, B2, QC2, C2, np.eye(3), X02, P02)


def test_steps_are_discretised_once_per_distinct_length():
    """A sampled record (frames every 0.5 s from t0 for 40 s, three dropped, inputs switching
    on and off the frames) has 6 distinct step lengths among its 80 steps (0 at t0, 0.2,
    0.25, 0.3, 0.5 and 1 s): `discretise_steps` computes 8 (6 rounded up to a power of two)
    and gives every step the discretisation of its own length, each equal to the stiff 2x2
    case's quadrature. A jittered record keeps one per step (no gather)."""
    t = np.delete(np.arange(0.0, 40.5, 0.5), [7, 13, 50])
    g = FilterGrid(t, [0.25, 4.0, 8.2], [1.0, 2.0, 3.0], t0_s=0.0)
    assert g.dt_s.size == 80 and np.unique(g.dt_s).size == 6 and g.dt_distinct.size == 8
    np.testing.assert_array_equal(g.dt_distinct[g.dt_index], g.dt_s)
    A = np.array([[-50.0, 40.0], [0.3, -0.1]])
    Ad, Bd, Qd = discretise_steps(A, B2, QC2, g, jnp.float64)
    assert Ad.shape == (80, 2, 2) and Bd.shape == (80, 2, 1)
    refs = {h: (sla.expm(A * h), *quadrature(h, A)) for h in np.unique(g.dt_s)}
    for k, h in enumerate(g.dt_s):
        Ad_ref, Bd_ref, Qd_ref = refs[h]
        np.testing.assert_allclose(Ad[k], Ad_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(Bd[k], Bd_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(Qd[k], Qd_ref, rtol=1e-12, atol=1e-15)
    jitter = np.random.default_rng(0).uniform(0.0, 1e-3, t.size)
    jittered = FilterGrid(t + jitter, t0_s=0.0)  # every length new
    assert jittered.dt_distinct.size == jittered.dt_s.size == t.size


# ---------------------------------------------------------------------------------------------
# Filter, smoother and likelihood against the dense Gaussian of the whole record
# ---------------------------------------------------------------------------------------------


batched_log_likelihood = jax.jit(jax.vmap(log_likelihood, in_axes=(None, None, 0)))


def test_log_likelihood_equals_dense_gaussian(lti_case):
    """Two records with different dropped values at once: also checks `jax.vmap` over data."""
    t0, noise, t, y, grid, model = lti_case
    ys = np.stack([lti_record(0)[1], lti_record(1)[1]])
    ll = batched_log_likelihood(model, grid, ys)
    for pattern in (0, 1):
        ref = dense_reference(t0, pattern, noise)[0]
        assert abs(float(ll[pattern]) - ref) <= 1e-8 * abs(ref), (pattern, float(ll[pattern]), ref)


def test_filter_and_smoother_equal_gaussian_conditioning(lti_case):
    t0, noise, t, y, grid, model = lti_case
    ref, condition, ok = dense_reference(t0, 0, noise)
    filt = kalman_filter(model, grid, y)
    smooth = rts_smoother(model, grid, y)
    n = 2
    for k in range(t.size):
        keep = ok.copy()
        keep[(k + 1) * 2 :] = False  # frames 1..k only
        m, P = condition(keep)
        np.testing.assert_allclose(filt.filtered_mean[k], m[k * n : (k + 1) * n], atol=1e-10)
        np.testing.assert_allclose(
            filt.filtered_cov[k], P[k * n : (k + 1) * n, k * n : (k + 1) * n], atol=1e-10
        )
    m, P = condition(ok)
    np.testing.assert_allclose(smooth.mean.ravel(), m, atol=1e-10)
    for k in range(t.size):
        np.testing.assert_allclose(
            smooth.cov[k], P[k * n : (k + 1) * n, k * n : (k + 1) * n], atol=1e-10
        )
    np.testing.assert_allclose(smooth.log_likelihood, ref, rtol=1e-10)
    # innovations: NaN exactly where the data are, standardised by the predicted covariance
    assert np.array_equal(np.isnan(filt.innovation), np.isnan(y))
    sd = np.sqrt(np.diagonal(filt.y_pred_cov, axis1=1, axis2=2))
    np.testing.assert_allclose(filt.standardised_innovation, (y - filt.y_pred) / sd)


def test_gradient_matches_finite_differences_without_retracing():
    """d log p / d(a11, q11, r22) by reverse mode equals central differences."""
    t, y = lti_record()
    grid = FilterGrid(t, U_TIMES, U_LEVELS, t0_s=0.0)

    def loglik(p):
        A = jnp.asarray(A2).at[0, 0].set(p[0])
        Qc = jnp.asarray(QC2).at[0, 0].set(p[1])
        R = jnp.asarray(R2).at[1, 1].set(p[2])
        return log_likelihood(lti_model(A=A, Qc=Qc, R=R), grid, y)

    p0 = np.array([A2[0, 0], QC2[0, 0], R2[1, 1]])
    grad = jax.jit(eqx.debug.assert_max_traces(jax.grad(loglik), max_traces=1))
    h = 1e-5
    fd = [(loglik(p0 + h * e) - loglik(p0 - h * e)) / (2 * h) for e in np.eye(3)]
    np.testing.assert_allclose(grad(jnp.asarray(p0)), fd, rtol=1e-6)
    grad(jnp.asarray(p0 * 1.1))  # new parameter values: no new trace


def test_extended_update_matches_numpy_ekf():
    """Nonlinear output h(x, u) at regular frames: the JAX EKF equals a plain numpy EKF."""
    dt, N = 0.5, 30
    t = dt * np.arange(1, N + 1)
    rng = np.random.default_rng(3)
    y = np.column_stack([np.sin(t) + 0.1 * rng.normal(size=N), 0.3 * rng.normal(size=N)])
    y[7, 0] = np.nan
    y[12] = np.nan

    def h(x, u):
        return jnp.stack([x[0] + 0.2 * x[1] ** 2 + u[0], jnp.tanh(x[1])])

    model = lti_model(output=h)
    grid = FilterGrid(t, U_TIMES, U_LEVELS, t0_s=0.0)
    res = kalman_filter(model, grid, y)

    def h_np(x, u):
        return np.array([x[0] + 0.2 * x[1] ** 2 + u[0], np.tanh(x[1])])

    def jac_np(x):
        return np.array([[1.0, 0.4 * x[1]], [0.0, 1.0 - np.tanh(x[1]) ** 2]])

    def step_mats(h_s):
        return sla.expm(A2 * h_s), *quadrature(h_s)

    mats = {}
    m, P, ll = X02.copy(), P02.copy(), 0.0
    means = []
    edges = np.unique(np.concatenate([U_TIMES[U_TIMES < t[-1]], t]))
    prev = 0.0
    for end in edges:
        key = round(end - prev, 12)
        if key not in mats:
            mats[key] = step_mats(end - prev)
        Ad, Bd, Qd = mats[key]
        m = Ad @ m + Bd @ u_at(prev)
        P = Ad @ P @ Ad.T + Qd
        prev = end
        k = np.searchsorted(t, end)
        if k == N or t[k] != end:
            continue
        ok = np.isfinite(y[k])
        if ok.any():
            H = jac_np(m)[ok]
            S = H @ P @ H.T + R2[np.ix_(ok, ok)]
            v = y[k][ok] - h_np(m, u_at(end))[ok]
            K = P @ H.T @ np.linalg.inv(S)
            m = m + K @ v
            P = P - K @ S @ K.T
            ll += scipy.stats.multivariate_normal(np.zeros(ok.sum()), S).logpdf(v)
        means.append(m.copy())
    np.testing.assert_allclose(res.filtered_mean, np.array(means), atol=1e-10)
    np.testing.assert_allclose(res.log_likelihood, ll, rtol=1e-10)


# ---------------------------------------------------------------------------------------------
# Stochastic ML fit of a thermal RC device with a random-walk ambient, from an independent
# simulator; the deterministic least-squares fit on the same data as the contrast
# ---------------------------------------------------------------------------------------------

TRUE = dict(tau_s=30.0, gain_K_per_W=3.0, q_ambient_K2_per_s=2e-3, sigma_K=0.1, ambient0_K=0.5)
POSITIVE = ("tau_s", "gain_K_per_W", "q_ambient_K2_per_s", "sigma_K")


def rc_design(seed, n_frames=400):
    """Irregular frames (0.6-1.4 s apart) and a heater switching on/off every 15-60 s."""
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.6, 1.4, n_frames))
    bt = np.concatenate([[0.0], np.cumsum(rng.uniform(15.0, 60.0, 40))])
    bt = bt[bt < t[-1]]
    lv = (np.arange(bt.size) % 2) * rng.uniform(0.5, 1.0, bt.size)  # W
    return t, bt, lv


def rc_theta(t, bt, lv, tau_s, gain_K_per_W):
    """Noise-free temperature rise at the frames: exact relaxation on each constant interval."""
    pts = np.unique(np.concatenate([[0.0], bt[(bt > 0) & (bt < t[-1])], t]))
    level = lv[np.searchsorted(bt, pts[:-1], side="right") - 1]
    decay = np.exp(-np.diff(pts) / tau_s)
    theta, out = 0.0, np.empty(pts.size - 1)
    for i in range(out.size):
        theta = theta * decay[i] + gain_K_per_W * level[i] * (1 - decay[i])
        out[i] = theta
    return out[np.searchsorted(pts[1:], t)], pts


def rc_simulate(t, bt, lv, seed, p=TRUE, drop=0.03):
    """y = theta + ambient + noise; the ambient takes N(0, q h) increments over every step."""
    rng = np.random.default_rng(seed)
    theta, pts = rc_theta(t, bt, lv, p["tau_s"], p["gain_K_per_W"])
    steps = np.sqrt(p["q_ambient_K2_per_s"] * np.diff(pts)) * rng.normal(size=pts.size - 1)
    walk = np.cumsum(steps)
    ambient = p["ambient0_K"] + walk[np.searchsorted(pts[1:], t)]
    y = theta + ambient + p["sigma_K"] * rng.normal(size=t.size)
    y[rng.random(t.size) < drop] = np.nan  # dropped frames
    return y


def rc_build(th):
    """States (temperature rise [K], ambient offset [K]); the ambient is a random walk."""
    zero = jnp.zeros(())
    tau = th["tau_s"]
    return LinearGaussianSDE(
        A=jnp.array([[-1.0 / tau, zero], [zero, zero]]),
        B=jnp.stack([th["gain_K_per_W"] / tau, zero])[:, None],
        Qc=jnp.diag(jnp.stack([zero, th["q_ambient_K2_per_s"]])),
        C=jnp.array([[1.0, 1.0]]),
        R=(th["sigma_K"] ** 2)[None, None],
        x0=jnp.stack([zero, th["ambient0_K"]]),
        P0=jnp.zeros((2, 2)),
    )


def test_random_walk_helper_builds_the_rc_model():
    th = {k: jnp.asarray(v) for k, v in TRUE.items()}
    tau, gain = TRUE["tau_s"], TRUE["gain_K_per_W"]
    base = LinearGaussianSDE(
        [[-1 / tau]], [[gain / tau]], [[0.0]], [[1.0]], [[TRUE["sigma_K"] ** 2]], [0.0], [[0.0]]
    )
    built = with_output_random_walks(base, [TRUE["q_ambient_K2_per_s"]], x0=[TRUE["ambient0_K"]])
    for got, want in zip(jax.tree.leaves(built), jax.tree.leaves(rc_build(th))):
        np.testing.assert_allclose(got, want, rtol=1e-15)
    with pytest.raises(ValueError, match="loading"):
        with_output_random_walks(base, [1.0, 2.0], loading=np.ones((2, 2)))


@pytest.fixture(scope="module")
def rc_data():
    t, bt, lv = rc_design(0)
    return t, bt, lv, rc_simulate(t, bt, lv, seed=1)


@pytest.fixture(scope="module")
def rc_fit(rc_data):
    t, bt, lv, y = rc_data
    start = dict(tau_s=15.0, gain_K_per_W=1.5, q_ambient_K2_per_s=1e-2, sigma_K=0.3, ambient0_K=0.0)
    grid = FilterGrid(t, bt, lv, t0_s=0.0)
    return fit_stochastic(rc_build, start, [(grid, y)], positive=POSITIVE)


def test_stochastic_fit_recovers_rc_parameters_within_3_se(rc_fit):
    assert rc_fit.converged and rc_fit.hessian_positive_definite
    z = rc_fit.z_scores(TRUE)
    assert set(z) == set(TRUE)
    assert all(abs(v) < 3 for v in z.values()), z
    # positive parameters get log-space intervals: geometric symmetry about the estimate
    lo, hi = rc_fit.ci95["tau_s"]
    np.testing.assert_allclose(hi / rc_fit.values["tau_s"], rc_fit.values["tau_s"] / lo)


def test_stochastic_fit_innovations_are_white(rc_fit, rc_data):
    rec = rc_fit.records[0]
    assert rec.whiteness[0].p_value > 0.01, rec.whiteness
    e = rec.standardised_innovation[:, 0]
    e = e[np.isfinite(e)]
    assert abs(e.std() - 1) < 0.1  # standardised by the filter's own S_k
    # one-step prediction beats the free-run simulation when the ambient wanders
    assert rec.one_step_fit_percent[0] > rec.simulation_fit_percent[0]
    y_sim, _ = free_run(rc_fit.model, FilterGrid(*rc_data[:3], t0_s=0.0))
    theta, _ = rc_theta(*rc_data[:3], rc_fit.values["tau_s"], rc_fit.values["gain_K_per_W"])
    np.testing.assert_allclose(y_sim[:, 0], theta + rc_fit.values["ambient0_K"], atol=1e-10)


def test_deterministic_least_squares_is_biased_and_non_white(rc_fit, rc_data):
    """The noise-free RC model + constant offset, fitted by scipy least squares: the wandering
    ambient lands in the residuals, which are strongly autocorrelated, and its naive standard
    errors are far too small (here tau = 14.9 s, K = 2.31 K/W: z = -9.8 and -4.9; the ML fit of
    the same data has z = -0.2 and -0.02)."""
    t, bt, lv, y = rc_data
    ok = np.isfinite(y)

    def resid(p):
        return (rc_theta(t, bt, lv, p[0], p[1])[0] + p[2] - y)[ok]

    sol = scipy.optimize.least_squares(resid, x0=[15.0, 1.5, 0.0], x_scale=[10.0, 1.0, 1.0])
    r = sol.fun
    dof = r.size - 3
    cov = np.linalg.inv(sol.jac.T @ sol.jac) * (r @ r / dof)
    se = np.sqrt(np.diag(cov))
    z_ls = (sol.x[:2] - [TRUE["tau_s"], TRUE["gain_K_per_W"]]) / se[:2]
    p_ls = ljung_box(r, 20).p_value
    assert p_ls < 1e-10, p_ls  # residuals far from white
    assert np.max(np.abs(z_ls)) > 3, z_ls  # biased beyond 3 of its own standard errors
    z_ml = rc_fit.z_scores(TRUE)
    assert max(abs(z_ml["tau_s"]), abs(z_ml["gain_K_per_W"])) < np.max(np.abs(z_ls))


def test_fit_input_errors_name_the_problem(rc_data):
    t, bt, lv, y = rc_data
    grid = FilterGrid(t, bt, lv, t0_s=0.0)
    with pytest.raises(ValueError, match="not in theta0"):
        fit_stochastic(rc_build, TRUE, [(grid, y)], positive=("tau",))
    with pytest.raises(ValueError, match="value > 0"):
        fit_stochastic(rc_build, TRUE | {"tau_s": -1.0}, [(grid, y)], positive=POSITIVE)
    with pytest.raises(ValueError, match="mark dropped frames with NaN"):
        log_likelihood(rc_build({k: jnp.asarray(v) for k, v in TRUE.items()}), grid, y[:-1])


def test_ljung_box_equals_direct_formula():
    rng = np.random.default_rng(5)
    x = rng.normal(size=200)
    x[[3, 50]] = np.nan
    xs = x[np.isfinite(x)]
    xs = xs - xs.mean()
    n, h = xs.size, 10
    r = [np.sum(xs[k:] * xs[: n - k]) / np.sum(xs * xs) for k in range(1, h + 1)]
    q = n * (n + 2) * sum(rk**2 / (n - k) for k, rk in enumerate(r, start=1))
    lb = ljung_box(x, h)
    assert lb.n == n and lb.lags == h
    np.testing.assert_allclose(lb.statistic, q, rtol=1e-12)
    np.testing.assert_allclose(lb.p_value, 1 - scipy.stats.chi2.cdf(q, h), rtol=1e-10)
    ar = np.zeros(300)
    for i in range(1, 300):
        ar[i] = 0.6 * ar[i - 1] + rng.normal()
    assert ljung_box(ar, h).p_value < 1e-6
