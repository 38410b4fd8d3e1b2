"""Differentiable stick-slip contacts (PHYSICS.md §8): the smooth play operator and the
quasi-static friction balance solved by damped Newton with an implicit-function derivative.

Two models of the same physics, simplest first:

- **play operator** (rate-independent, exact in the quasi-static limit): the foot offset u
  relative to the body stays in the sticking band [s - F_a/k, s + F_b/k] of the free stroke s,
  with F_a = min(F_f+, F_d-) and F_b = min(F_f-, F_d+); increments of u are booked to the
  weaker contact. One cycle of stroke swing S_pp moves the body max(0, S_pp - (F_a + F_b)/k).
- **regularised friction, implicit Euler**: each contact obeys the directional smooth Coulomb
  law f(v) = F(v) tanh(v/v_eps) + c v with F(v) = F- + (F+ - F-) sigmoid(v/(delta v_eps));
  the velocities of one step solve J^T f(J v) + K (q + h v - q_rest) = 0, the stationarity
  condition of a strictly convex incremental potential (unique solution).

Every function is smooth (softplus, logaddexp, sigmoid, tanh): no `where` with NaN branches.
SI units: m, m/s, N, N/m, s.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

# ---------------------------------------------------------------------------- smooth helpers


def smooth_max(x, lo, eps):
    """Smooth max(x, lo) = lo + eps softplus((x - lo)/eps); error <= eps log 2 at x = lo."""
    return lo + eps * jax.nn.softplus((x - lo) / eps)


def smooth_min(x, hi, eps):
    """Smooth min(x, hi) = hi - eps softplus((hi - x)/eps)."""
    return hi - eps * jax.nn.softplus((hi - x) / eps)


def smooth_clip(x, lo, hi, eps):
    """Smooth clip of x to [lo, hi] (smooth max, then smooth min), width eps [same unit as x]."""
    return smooth_min(smooth_max(x, lo, eps), hi, eps)


def soft_min_force(a, b, scale_N=1e-6, beta=50.0):
    """Smooth min of two forces by logsumexp: -(s/beta) log(e^{-beta a/s} + e^{-beta b/s}).

    Always below min(a, b), by at most (s/beta) log 2 (14 nN at the defaults)."""
    return -(scale_N / beta) * jnp.logaddexp(-beta * a / scale_N, -beta * b / scale_N)


def split_increment(du, eps):
    """(positive part, negative part) of an increment with pos - neg = du exactly."""
    return du * jax.nn.sigmoid(du / eps), -du * jax.nn.sigmoid(-du / eps)


def directional_friction_N(v, forward_N, backward_N, v_eps, delta=0.1, viscous=1e-5):
    """Directional smooth Coulomb law f(v) [N] (resisting force for slip velocity v [m/s]).

    f(v) = F(v) tanh(v/v_eps) + c v, F(v) = F- + (F+ - F-) sigmoid(v/(delta v_eps)): f(0) = 0,
    f(+inf) -> +F+ (capacity against forward slip), f(-inf) -> -F-. Monotone for F-/F+ <~ 20.
    A sub-threshold force F makes it creep at v_eps artanh(F/F_cap): keep v_eps tiny (<= 10 nm/s).
    """
    cap = backward_N + (forward_N - backward_N) * jax.nn.sigmoid(v / (delta * v_eps))
    return cap * jnp.tanh(v / v_eps) + viscous * v


# ---------------------------------------------------------------------------- play operator


class PlayContacts(eqx.Module):
    """Two-contact inchworm as a smooth play operator (PHYSICS.md §8.1, §8.2 item 1).

    - `foot_forward_N`, `foot_backward_N`: foot friction capacities F_f+ / F_f- [N].
    - `dimple_forward_N`, `dimple_backward_N`: body (dimple) capacities F_d+ / F_d- [N].
    - `stiffness_N_per_m`: actuator-plus-leg stiffness k [N/m].
    - `clip_eps_m`: play clip smoothing width [m] (<= 0.2 nm converges, §8.2).
    - `slip_eps_m`: width of the slip-direction split; far below any per-step increment (a
      width near the increments of a slowly cooling tail books part of them to neither
      direction), and harmless for gradients since d(du sigmoid(du/eps))/d(du) <= 1.1.
    - `force_scale_N`, `beta`: soft-min / contact-selection sharpness, width s/beta (s = 1 uN,
      beta = 500: 2 nN). A width comparable to the gap between two capacities (beta = 50,
      20 nN, against F_d-/2 - F_f+ = 50 nN) books ~8 % of every increment to the wrong
      contact, biases the step and makes F_f+ seem identifiable apart from W (it is not).
    """

    foot_forward_N: float
    foot_backward_N: float
    dimple_forward_N: float
    dimple_backward_N: float
    stiffness_N_per_m: float
    clip_eps_m: float = 1e-10
    slip_eps_m: float = 1e-14
    force_scale_N: float = 1e-6
    beta: float = 500.0

    def band_N(self):
        """(F_a, F_b): forward / backward actuator force at which a contact first slips."""
        fa = soft_min_force(
            self.foot_forward_N, self.dimple_backward_N, self.force_scale_N, self.beta
        )
        fb = soft_min_force(
            self.foot_backward_N, self.dimple_forward_N, self.force_scale_N, self.beta
        )
        return fa, fb

    def play_width_m(self):
        """W = (F_a + F_b)/k: stroke swing lost to sticking every cycle [m]."""
        fa, fb = self.band_N()
        return (fa + fb) / self.stiffness_N_per_m

    def step(self, offset_m, body_m, stroke_m):
        """One play step: (foot offset u+, body position x_b+) [m] for the new free stroke s.

        du > 0 slips the feet forward if F_f+ < F_d- (else the body backward); du < 0 slips the
        body forward if F_d+ < F_f- (else the feet backward)."""
        fa, fb = self.band_N()
        k = self.stiffness_N_per_m
        new = smooth_clip(offset_m, stroke_m - fa / k, stroke_m + fb / k, self.clip_eps_m)
        pos, neg = split_increment(new - offset_m, self.slip_eps_m)
        s = self.force_scale_N
        feet_slip_fwd = jax.nn.sigmoid(
            self.beta * (self.dimple_backward_N - self.foot_forward_N) / s
        )
        body_slip_fwd = jax.nn.sigmoid(
            self.beta * (self.foot_backward_N - self.dimple_forward_N) / s
        )
        return new, body_m - pos * (1.0 - feet_slip_fwd) + neg * body_slip_fwd


def play_step_per_cycle_m(stroke_pp_m, play_width_m):
    """Closed form: body advance per cycle max(0, S_pp - W) [m] (PHYSICS.md §5)."""
    return jnp.maximum(0.0, stroke_pp_m - play_width_m)


# ---------------------------------------------------------------- implicit friction balance


def _stop(tree):
    return jax.tree.map(jax.lax.stop_gradient, tree)


def solve_convex(residual, x0, params, *, tol, max_iter=60, n_search=48, jacobian=None):
    """Root of `residual(x, params)`, the gradient of a strictly convex potential.

    Damped Newton: along the Newton direction d the potential's slope phi'(t) = d.r(x + t d)
    increases monotonically, so the step t is the largest of 1, 1/2, 1/4, ... (at most
    `n_search` halvings) with phi'(t) <= 0, found by backtracking: a guaranteed decrease,
    within a factor two of the exact line minimum, and t = 1 (quadratic convergence) near the
    root; one or two residual evaluations per Newton step on average. Iterations run on stopped
    gradients; the result then gets an implicit-function correction whose value is zero and
    whose derivative is -J^{-1} dr/dparams (the implicit-function theorem, in forward and
    reverse mode) without differentiating the iterations. Stops at |r|_inf <= `tol` or after
    `max_iter` Newton steps. `jacobian(x, params)` (default: `jax.jacfwd(residual)`) may be a
    cheaper closed form.
    """
    p_stop = _stop(params)
    jac = jax.jacfwd(residual) if jacobian is None else jacobian

    def body(carry):
        x, r, it = carry
        d = -jnp.linalg.solve(jac(x, p_stop), r)

        def shorter(c):
            t, _, _, k = c
            trial = x + 0.5 * t * d
            return 0.5 * t, trial, residual(trial, p_stop), k + 1

        def uphill(c):
            _, _, rt, k = c
            return (rt @ d > 0.0) & (k < n_search - 1)

        full = x + d
        start = (1.0, full, residual(full, p_stop), 0)
        _, x_new, r_new, _ = jax.lax.while_loop(uphill, shorter, start)
        return x_new, r_new, it + 1

    def cond(carry):
        _, r, it = carry
        return (jnp.max(jnp.abs(r)) > tol) & (it < max_iter)

    x0 = jax.lax.stop_gradient(x0)
    x, _, _ = jax.lax.while_loop(cond, body, (x0, residual(x0, p_stop), 0))
    x = jax.lax.stop_gradient(x)
    j = jax.lax.stop_gradient(jac(x, p_stop))
    correction = -jnp.linalg.solve(j, residual(x, params))
    # value x exactly (no extra, unsafeguarded step); derivative -J^{-1} dr/dparams
    return x + (correction - jax.lax.stop_gradient(correction))


class FrictionLaw(eqx.Module):
    """Regularisation of the directional Coulomb law shared by all contacts of a body.

    - `v_eps_m_per_s`: tanh velocity scale (<= 10 nm/s keeps creep negligible, §8.2).
    - `delta`: direction-switch width relative to v_eps; `viscous_N_s_per_m`: c.
    """

    v_eps_m_per_s: float = 1e-8
    delta: float = 0.1
    viscous_N_s_per_m: float = 1e-5

    def __call__(self, v, forward_N, backward_N):
        return directional_friction_N(
            v, forward_N, backward_N, self.v_eps_m_per_s, self.delta, self.viscous_N_s_per_m
        )


def implicit_friction_step(
    law: FrictionLaw,
    jacobian,
    forward_N,
    backward_N,
    spring_N_per_m,
    coords,
    rest,
    h_s,
    v_guess,
    *,
    tol_N=1e-15,
    max_iter=40,
):
    """Generalised velocities v (n,) [m/s or rad/s] of one implicit-Euler quasi-static step.

    Solves J^T f(J v) + K (coords + h v - rest) = 0: contact slip velocities J v (m,) with
    directional friction capacities `forward_N`/`backward_N` (m,), springs `spring_N_per_m`
    (n,) pulling `coords` (n,) towards `rest` (n,) (0 stiffness for free coordinates).
    """

    def residual(v, p):
        jac, fwd, bwd, k, q, r, h = p
        return jac.T @ law(jac @ v, fwd, bwd) + k * (q + h * v - r)

    def residual_jacobian(v, p):
        # J^T diag(f'(J v)) J + diag(k h): one elementwise derivative of the law instead of
        # differentiating the whole residual along n directions
        jac, fwd, bwd, k, _, _, h = p
        slope = jax.jvp(lambda w: law(w, fwd, bwd), (jac @ v,), (jnp.ones(jac.shape[0]),))[1]
        return jac.T @ (slope[:, None] * jac) + jnp.diag(k * h)

    params = (jacobian, forward_N, backward_N, spring_N_per_m, coords, rest, h_s)
    return solve_convex(
        residual, v_guess, params, tol=tol_N, max_iter=max_iter, jacobian=residual_jacobian
    )


class FrictionContacts(eqx.Module):
    """The 1-D two-contact inchworm with regularised friction (PHYSICS.md §8.2 item 2).

    Coordinates q = (x_b, u): body position and foot offset; contacts: dimple (velocity v_b)
    and foot (v_b + du/dt). Same capacities as `PlayContacts`, plus the friction `law`.
    """

    foot_forward_N: float
    foot_backward_N: float
    dimple_forward_N: float
    dimple_backward_N: float
    stiffness_N_per_m: float
    law: FrictionLaw = FrictionLaw()

    def step(self, offset_m, body_m, stroke_m, h_s, v_guess):
        """(u+, x_b+, velocities (2,)) after one implicit-Euler step of length h_s [s]."""
        jac = jnp.array([[1.0, 0.0], [1.0, 1.0]])  # rows: dimple, foot; columns: x_b, u
        fwd = jnp.stack([self.dimple_forward_N, self.foot_forward_N])
        bwd = jnp.stack([self.dimple_backward_N, self.foot_backward_N])
        k = jnp.stack([jnp.zeros_like(self.stiffness_N_per_m), self.stiffness_N_per_m])
        q = jnp.stack([body_m, offset_m])
        rest = jnp.stack([jnp.zeros_like(stroke_m), stroke_m])
        v = implicit_friction_step(self.law, jac, fwd, bwd, k, q, rest, h_s, v_guess)
        return offset_m + h_s * v[1], body_m + h_s * v[0], v
