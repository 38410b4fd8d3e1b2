"""3-DOF micro-robot blocks (PHYSICS.md §4, §9, §10): two-sided thermal RC, body geometry and
feature observation, and the planar stick-slip locomotion step (play surrogate or quasi-static
friction balance).

Conventions (body frame): x forward (towards the dimple), y to the left, heading psi
counter-clockwise from the world x axis. The left side (+y) carries the bare-Si frame, the
right side (-y) the gold-coated one. Pose state: (X, Y, psi) [m, m, rad]; foot offsets
u_L, u_R [m] along the body x axis. SI units throughout.
"""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp

from greybox.blocks._contacts import FrictionLaw, PlayContacts, implicit_friction_step
from greybox.blocks._thermal import ThermalNetwork


class TwoSidedThermal(eqx.Module):
    """Two-node RC per side (frame f, beams b) with side-to-side coupling (PHYSICS.md §4, §14).

    Nodes [f_L, b_L, f_R, b_R]; heat enters the frames. Scalar fields so every value can be
    fitted by dotted path: `frame_capacitance_J_per_K` C_f, `beam_capacitance_J_per_K` C_b,
    `frame_ground_W_per_K` G_f0, `frame_beam_W_per_K` G_fb, `beam_ground_W_per_K` G_b0,
    `side_coupling_W_per_K` G_LR.
    """

    frame_capacitance_J_per_K: float = 1.9e-7
    beam_capacitance_J_per_K: float = 4e-8
    frame_ground_W_per_K: float = 6e-5
    frame_beam_W_per_K: float = 3e-5
    beam_ground_W_per_K: float = 2e-5
    side_coupling_W_per_K: float = 5e-6

    def network(self) -> ThermalNetwork:
        cf, cb = self.frame_capacitance_J_per_K, self.beam_capacitance_J_per_K
        g0, gb = self.frame_ground_W_per_K, self.beam_ground_W_per_K
        return ThermalNetwork(
            capacitance_J_per_K=jnp.stack([cf, cb, cf, cb]),
            ground_conductance_W_per_K=jnp.stack([g0, gb, g0, gb]),
            coupling_conductance_W_per_K=jnp.stack(
                [self.frame_beam_W_per_K, self.frame_beam_W_per_K, self.side_coupling_W_per_K]
            ),
            couplings=((0, 1), (2, 3), (0, 2)),
            input_nodes=(0, 2),
        )

    def zoh_matrices(self, h_s):
        """Exact ZOH (Phi (L, 4, 4), Gamma (L, 4, 2)) for steps `h_s` (L,) [s] in closed form.

        The two sides are identical, so the sum and difference of the sides decouple into two
        2-node systems M z' = -K z + e_f q (K_diff adds 2 G_LR at the frame). Each is solved with
        the closed-form eigenbasis of the symmetric M^-1/2 K M^-1/2 (its off-diagonal
        -G_fb/sqrt(C_f C_b) is never zero, so the eigenvalues are distinct and differentiable):
        a few exponentials per step instead of a matrix-exponential series; equal to
        `greybox._simulate.simulate.zoh_matrices` of `network()` to rounding."""
        cf, cb = self.frame_capacitance_J_per_K, self.beam_capacitance_J_per_K
        gfb = self.frame_beam_W_per_K
        h = jnp.asarray(h_s)[:, None]
        m_half = jnp.stack([jnp.sqrt(cf), jnp.sqrt(cb)])

        def mode(frame_total):
            a, d = frame_total / cf, (self.beam_ground_W_per_K + gfb) / cb
            c = -gfb / jnp.sqrt(cf * cb)
            centre, radius = 0.5 * (a + d), jnp.sqrt(0.25 * (a - d) ** 2 + c**2)
            lam = jnp.stack([centre + radius, centre - radius])
            angle = 0.5 * jnp.arctan2(2.0 * c, a - d)
            q = jnp.array([[1.0, 0.0], [0.0, 1.0]]) * jnp.cos(angle) + jnp.array(
                [[0.0, -1.0], [1.0, 0.0]]
            ) * jnp.sin(angle)
            left, right = q / m_half[:, None], q.T * m_half[None, :]  # M^-1/2 Q, Q^T M^1/2
            decay = jnp.exp(-lam * h)  # (L, 2)
            gain = -jnp.expm1(-lam * h) / lam
            phi = jnp.einsum("ik,lk,kj->lij", left, decay, right)
            gamma = jnp.einsum("ik,lk,k->li", left, gain, q[0] / m_half[0])  # input at the frame
            return phi, gamma

        g_sum = self.frame_ground_W_per_K + gfb
        p_s, g_s = mode(g_sum)
        p_d, g_d = mode(g_sum + 2.0 * self.side_coupling_W_per_K)
        same, cross = 0.5 * (p_s + p_d), 0.5 * (p_s - p_d)
        phi = jnp.concatenate(
            [jnp.concatenate([same, cross], 2), jnp.concatenate([cross, same], 2)], 1
        )
        g_same, g_cross = 0.5 * (g_s + g_d), 0.5 * (g_s - g_d)
        gamma = jnp.concatenate(
            [jnp.stack([g_same, g_cross], 2), jnp.stack([g_cross, g_same], 2)], 1
        )
        return phi, gamma

    def frame_time_constant_s(self):
        """Dominant time constant C_f/(G_f0 + G_fb) of a frame (beam node held cold) [s]."""
        return self.frame_capacitance_J_per_K / (
            self.frame_ground_W_per_K + self.frame_beam_W_per_K
        )


class BodyGeometry(eqx.Module):
    """Contact and feature positions in the body frame [m] (PHYSICS.md §12 assumed geometry).

    Dimple at (`dimple_x_m`, 0); feet at (`foot_x_m` + u_i, +-`foot_y_m`); tracked features 1
    and 2 at (`feature1_x_m`, `feature1_y_m`) and (`feature2_x_m`, `feature2_y_m`)."""

    dimple_x_m: float = 250e-6
    foot_x_m: float = -200e-6
    foot_y_m: float = 120e-6
    feature1_x_m: float = 200e-6
    feature1_y_m: float = 0.0
    feature2_x_m: float = -200e-6
    feature2_y_m: float = 0.0

    def features_m(self, pose):
        """World positions (f1_x, f1_y, f2_x, f2_y) [m] of the two features at pose (X, Y, psi)."""
        x, y, psi = pose[0], pose[1], pose[2]
        c, s = jnp.cos(psi), jnp.sin(psi)
        out = []
        for fx, fy in (
            (self.feature1_x_m, self.feature1_y_m),
            (self.feature2_x_m, self.feature2_y_m),
        ):
            out += [x + c * fx - s * fy, y + s * fx + c * fy]
        return jnp.stack(out)

    def contact_jacobian(self, psi, u_left, u_right):
        """(6, 5) map from q_dot = (X', Y', psi', u_L', u_R') to body-frame contact slip velocities.

        Rows: (along, across) for dimple, left foot, right foot; geometry frozen at step start."""
        c, s = jnp.cos(psi), jnp.sin(psi)
        zero, one = jnp.zeros_like(psi), jnp.ones_like(psi)
        rows = []
        for rx, ry, col in (
            (self.dimple_x_m, 0.0, None),
            (self.foot_x_m + u_left, self.foot_y_m, 3),
            (self.foot_x_m + u_right, -self.foot_y_m, 4),
        ):
            along = [c, s, -ry * one, zero, zero]
            across = [-s, c, rx * one, zero, zero]
            if col is not None:
                along[col] = one
            rows += [jnp.stack(along), jnp.stack(across)]
        return jnp.stack(rows)


class Locomotion(eqx.Module):
    """Planar stick-slip of a body with a front dimple and two actuated feet (PHYSICS.md §8-9).

    Friction capacities [N]: feet `foot_forward_N` F_f+, `foot_backward_N` F_f-, `foot_lateral_N`;
    dimple `dimple_forward_N`, `dimple_backward_N`, `dimple_lateral_N`. `stiffness_N_per_m` k of
    each actuator-plus-leg. `model` (static) selects the step:

    - "play" (fast surrogate, recommended for fitting): a smooth play operator per side with
      the dimple shared by the two legs, band F_a = min(F_f+, F_d-/2), F_b = min(F_f-, F_d+/2);
      the body advances by the mean of the two sides' advances d_L, d_R and turns by
      dpsi = -`turn_gain` (d_L - d_R)/(2 `foot_y_m`) (a hotter left side turns it right, i.e.
      towards the cooler side). Rate independent: the step length only needs to resolve the
      stroke extrema.
    - "friction" (detailed): implicit-Euler quasi-static balance of the 5 coordinates with the
      directional smooth Coulomb `law` at the three contacts, solved by damped Newton on a
      strictly convex incremental potential and differentiated by the implicit-function
      theorem. Under symmetric heating it reduces to the play model (`turn_gain` unused).
    """

    foot_forward_N: float = 0.3e-6
    foot_backward_N: float = 1.5e-6
    foot_lateral_N: float = 1.5e-6
    dimple_forward_N: float = 0.8e-6
    dimple_backward_N: float = 0.8e-6
    dimple_lateral_N: float = 0.8e-6
    stiffness_N_per_m: float = 5.0
    turn_gain: float = 1.0
    clip_eps_m: float = 1e-10
    law: FrictionLaw = FrictionLaw()
    model: str = eqx.field(static=True, default="play")

    def __check_init__(self):
        if self.model not in ("play", "friction"):
            raise ValueError(f"model: {self.model!r} must be 'play' (fast surrogate) or 'friction'")

    def side_play(self) -> PlayContacts:
        """The per-side 1-D play operator (the dimple's capacity is shared by the two legs)."""
        return PlayContacts(
            self.foot_forward_N,
            self.foot_backward_N,
            self.dimple_forward_N / 2,
            self.dimple_backward_N / 2,
            self.stiffness_N_per_m,
            self.clip_eps_m,
        )

    def play_width_m(self):
        """Per-side play width W = (F_a + F_b)/k [m]."""
        return self.side_play().play_width_m()

    def step(self, mech, strokes_m, geometry: BodyGeometry, h_s):
        """Advance the mechanical state (10,) = (X, Y, psi, u_L, u_R, 5 velocities) by one step
        of length `h_s` [s] with new free strokes (s_L, s_R) [m]."""
        if self.model == "play":
            return self._play(mech, strokes_m, geometry)
        return self._friction(mech, strokes_m, geometry, h_s)

    def _play(self, mech, strokes_m, geometry):
        offsets, advances = self.side_play().step(mech[3:5], 0.0, strokes_m)  # both sides at once
        advance = 0.5 * (advances[0] + advances[1])
        psi = mech[2]
        dpsi = -self.turn_gain * (advances[0] - advances[1]) / (2.0 * geometry.foot_y_m)
        pose = mech[:3] + jnp.stack([advance * jnp.cos(psi), advance * jnp.sin(psi), dpsi])
        return jnp.concatenate([pose, offsets, mech[5:]])

    def _friction(self, mech, strokes_m, geometry, h_s):
        q, v0 = mech[:5], mech[5:]
        jac = geometry.contact_jacobian(q[2], q[3], q[4])
        fwd = jnp.stack(
            [
                self.dimple_forward_N,
                self.dimple_lateral_N,
                self.foot_forward_N,
                self.foot_lateral_N,
                self.foot_forward_N,
                self.foot_lateral_N,
            ]
        )
        bwd = jnp.stack(
            [
                self.dimple_backward_N,
                self.dimple_lateral_N,
                self.foot_backward_N,
                self.foot_lateral_N,
                self.foot_backward_N,
                self.foot_lateral_N,
            ]
        )
        zero = jnp.zeros_like(self.stiffness_N_per_m)
        k = jnp.stack([zero, zero, zero, self.stiffness_N_per_m, self.stiffness_N_per_m])
        rest = jnp.concatenate([jnp.zeros(3), jnp.asarray(strokes_m)])
        # warm start from the last step's velocities (measured: 10 Newton steps on average at
        # 16 steps per cycle, against 15 from rest and 21 from the play surrogate's step)
        v = implicit_friction_step(self.law, jac, fwd, bwd, k, q, rest, h_s, v0)
        return jnp.concatenate([q + h_s * v, v])


def absorbed_fractions(spot, frames, absorptances, pose):
    """Absorbed W per W of laser for each frame at body pose (X, Y, psi); the beam is fixed."""
    local = spot.shifted_to_body(pose[0], pose[1], pose[2])
    return jnp.stack([a * f.fraction(local) for a, f in zip(absorptances, frames)])
