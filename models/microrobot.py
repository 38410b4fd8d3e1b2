"""The untethered 3-DOF stick-slip micro-robot steered by differential laser heating.

laser P(t) [W], world-fixed Gaussian spot -> spot in body coordinates at the current pose ->
absorbed q_i = A_i(lambda) F_i P on the left (bare Si) and right (gold) frames -> two-node RC
per side with side coupling (exact ZOH sub-steps) -> beam elongation -> exact chevron
kinematics -> free foot strokes s_L, s_R -> stick-slip contacts (play surrogate or
quasi-static friction balance, `Locomotion.model`) -> pose (X, Y, psi) -> two tracked body
features in the camera (exposure averaged, per-run image offsets).

Simulation is a per-step map, not an ODE, so the device is an `AbstractSteppedDevice`: each
ZOH interval of the schedule (laser edges and camera instants) is split into `substeps`
(static, default 4) sub-steps that double in length through the interval (`substep_growth`):
the beam rise turns over within about a millisecond of a laser edge and the play operator
only sees the stroke at sub-step ends. Against a 96-uniform-sub-step reference (20 mW, 1 s,
30 fps), 4 graded sub-steps are within 0.03 um at periods >= 16 ms (0.1 um at 8 ms, where 8
are needed), while 4 uniform ones miss 0.6 um at 8 ms. `method` ("zoh" or "adaptive") does
not change anything here: the thermal step is always exact ZOH (closed form,
`TwoSidedThermal.zoh_matrices`) and the contact model is chosen by the device field
`locomotion.model` ("play": fast surrogate for fitting; "friction": detailed balance).

Nominal values: PHYSICS.md §3, §4, §12, §14 (robot geometry [assumed]). What pose video
identifies (PHYSICS.md §13.6): the per-side play width W = (F_a + F_b)/k (not friction and
stiffness separately), the thermal gain carried by the left absorptance (with G fixed) and the
thermal time constant through step size against period, and the turning gain.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox import AbstractSteppedDevice, Channel, DeviceSpec, FreeParameter, Option, ParameterInfo
from greybox.blocks import (
    BodyGeometry,
    Camera,
    ChevronExact,
    GaussianSpot,
    Locomotion,
    RectangularFrame,
    ThermalElongation,
    TwoSidedThermal,
    absorbed_fractions,
    material_absorptance,
)
from greybox.devices import LASER_POWER

from ._gait import (  # noqa: F401  (the robot's gait analyses, used through this module)
    cycle_summary,
    pose_history,
    pulse_schedule,
    speed_vs_duty,
    speed_vs_period,
    turning_vs_power_ratio,
)

NAME = "microrobot"
INPUTS = (LASER_POWER,)


def _feature_channel(name: str, what: str) -> Channel:
    return Channel(name, "m", {"um": (1e-6, 0.0), "nm": (1e-9, 0.0), "px": None}, what)


OUTPUTS = (
    _feature_channel("f1_x", "image x of tracked feature 1 (front, near the dimple)"),
    _feature_channel("f1_y", "image y of tracked feature 1"),
    _feature_channel("f2_x", "image x of tracked feature 2 (rear, between the feet)"),
    _feature_channel("f2_y", "image y of tracked feature 2"),
)

FRAME_OUTER_M = 150e-6
FRAME_HOLE_M = 90e-6
FRAME_LATERAL_M = 110e-6  # frame centres at body y = +-110 um (left = +y)
BEAM_LENGTH_M = 300e-6
BEAM_ANGLE_RAD = float(np.deg2rad(2.0))
CTE_PER_K = 2.8e-6
N_STATES = 14  # 4 thermal rises [K], X, Y, psi, u_L, u_R, 5 contact velocities


def substep_fractions(n: int, growth: float) -> np.ndarray:
    """Sub-step lengths as fractions of an interval, each `growth` times the previous (sum
    1): short steps right after a laser edge, where the beam rise turns over (PHYSICS.md §4,
    two-node RC), long ones once it relaxes. n = 4 at growth 2 resolves the stroke extrema
    about as well as 16 uniform sub-steps; growth 1 gives equal sub-steps."""
    f = growth ** np.arange(n)
    return f / f.sum()


class MicroRobot(AbstractSteppedDevice):
    """Laser-steered stick-slip robot; outputs the two features' image positions [m].

    State (14,): thermal rises [f_L, b_L, f_R, b_R] [K], pose X, Y [m], psi [rad], foot
    offsets u_L, u_R [m], the last step's generalised velocities (5,) (Newton warm start).
    Per-run known settings: `spot.x_m`, `spot.y_m` (beam centre in world/start-body frame).
    """

    spot: GaussianSpot
    frame_left: RectangularFrame
    frame_right: RectangularFrame
    absorptance_left: float
    absorptance_right: float
    thermal: TwoSidedThermal
    elongation: ThermalElongation
    kinematics: ChevronExact
    locomotion: Locomotion
    geometry: BodyGeometry
    camera: Camera
    leg_gain: float = 1.0
    image_offset_x_m: float = 0.0
    image_offset_y_m: float = 0.0
    substeps: int = eqx.field(static=True, default=4)
    substep_growth: float = eqx.field(static=True, default=2.0)

    @property
    def readout(self) -> Camera:
        """The two features are filmed: the camera is the readout."""
        return self.camera

    @property
    def n_states(self) -> int:
        return N_STATES

    @property
    def n_inputs(self) -> int:
        return 1

    @property
    def n_outputs(self) -> int:
        return 4

    def initial_state(self):
        return jnp.zeros(N_STATES)

    def absorbed_fractions(self, pose):
        """Absorbed W per W of laser (left, right) at body pose (X, Y, psi)."""
        return absorbed_fractions(
            self.spot,
            (self.frame_left, self.frame_right),
            (self.absorptance_left, self.absorptance_right),
            pose,
        )

    def strokes_m(self, theta_K):
        """Free foot strokes (s_L, s_R) [m] from the beam-node rises."""
        beams = jnp.stack([theta_K[1], theta_K[3]])
        return self.leg_gain * self.kinematics(self.elongation(beams))

    def thermal_matrices(self, h_s):
        """Exact ZOH (Phi (L, 4, 4), Gamma (L, 4, 2)) for sub-steps `h_s` (L,) [s]."""
        return self.thermal.zoh_matrices(h_s)

    def step(self, x, power_W, phi, gamma, h_s):
        """One sub-step: heat at the pose of the step start, exact thermal step, contact step."""
        theta, mech = x[:4], x[4:]
        q = self.absorbed_fractions(mech[:3]) * power_W
        theta = phi @ theta + gamma @ q
        mech = self.locomotion.step(mech, self.strokes_m(theta), self.geometry, h_s)
        return jnp.concatenate([theta, mech])

    def grid_states(self, x0, dt_s, power_W):
        """States (L+1, 14) at the ends of ZOH intervals `dt_s` (L,) with laser `power_W` (L,).

        One flat `lax.scan` over the L * substeps sub-steps, so the loop body is a single small
        step (no nested loop, no per-step gathers). Sub-steps grow geometrically through each
        interval (`substep_fractions`): the beam node peaks within about a millisecond of a
        laser edge, and the play operator only sees the stroke at sub-step ends."""
        n_sub = self.substeps
        h = (dt_s[:, None] * substep_fractions(n_sub, self.substep_growth)[None, :]).reshape(-1)
        phi, gamma = self.thermal_matrices(h)

        def sub(x, inp):
            x = self.step(x, *inp)
            return x, x

        _, xs = jax.lax.scan(sub, x0, (jnp.repeat(power_W, n_sub), phi, gamma, h))
        return jnp.concatenate([x0[None], xs[n_sub - 1 :: n_sub]])

    def output(self, x):
        offset = jnp.stack([self.image_offset_x_m, self.image_offset_y_m] * 2)
        return self.geometry.features_m(x[4:7]) + offset

    def observe_schedule(self, sched, method):
        grid = self.grid_states(self.initial_state(), sched["dt"], sched["u_grid"][:, 0])
        outputs = jax.vmap(self.output)(grid[sched["eval_index"]])
        n_frames = sched["t_s"].shape[0]
        z = self.readout.observe(outputs.reshape(n_frames, -1, 4), sched["t_s"], sched["t_start"])
        return z, jnp.all(jnp.isfinite(z))


def build(
    *,
    contacts: str = "play",
    wavelength_nm: float = 800.0,
    substeps: int = 4,
    substep_growth: float = 2.0,
) -> MicroRobot:
    """The robot at nominal values (PHYSICS.md §14); `contacts` = "play" or "friction";
    filmed at 0.645 um per pixel with a 10 ms exposure (an experiment's [camera] replaces
    both)."""
    wavelength_m = wavelength_nm * 1e-9
    model = MicroRobot(
        spot=GaussianSpot(waist_m=150e-6, x_m=0.0, y_m=60e-6),
        frame_left=RectangularFrame.square(0.0, FRAME_LATERAL_M, FRAME_OUTER_M, FRAME_HOLE_M),
        frame_right=RectangularFrame.square(0.0, -FRAME_LATERAL_M, FRAME_OUTER_M, FRAME_HOLE_M),
        absorptance_left=float(material_absorptance("Si", wavelength_m, 10e-6)),
        absorptance_right=float(material_absorptance("Au", wavelength_m)),
        thermal=TwoSidedThermal(),
        elongation=ThermalElongation(
            cte_per_K=CTE_PER_K, length_m=BEAM_LENGTH_M, beam_fraction=1.0
        ),
        kinematics=ChevronExact(length_m=BEAM_LENGTH_M, angle_rad=BEAM_ANGLE_RAD),
        locomotion=Locomotion(model=contacts),
        geometry=BodyGeometry(),
        camera=Camera(m_per_px=0.645e-6, exposure_s=0.010),
        substeps=substeps,
        substep_growth=substep_growth,
    )
    return model


PARAMETERS = (
    ParameterInfo(
        "absorptance_left",
        "1",
        0.448,
        0.40,
        0.70,
        "bare-Si frame absorptance (800 nm, 10 um)",
        "product with spot fraction and 1/G: the thermal gain carrier",
    ),
    ParameterInfo(
        "absorptance_right",
        "1",
        0.024,
        0.02,
        0.06,
        "gold-coated frame absorptance (800 nm)",
        "weak: the gold side barely moves",
    ),
    ParameterInfo(
        "spot.waist_m", "m", 150e-6, 25e-6, 500e-6, "1/e^2 spot radius", "not identifiable"
    ),
    ParameterInfo(
        "spot.x_m", "m", 0.0, -300e-6, 300e-6, "beam centre, world x", "known per-run setting"
    ),
    ParameterInfo(
        "spot.y_m", "m", 60e-6, -300e-6, 300e-6, "beam centre, world y", "known per-run setting"
    ),
    ParameterInfo(
        "thermal.frame_capacitance_J_per_K",
        "J/K",
        1.9e-7,
        5e-8,
        1e-6,
        "frame heat capacity C_f",
        "sets tau: identified through step size against period",
    ),
    ParameterInfo(
        "thermal.frame_ground_W_per_K",
        "W/K",
        6e-5,
        1e-5,
        3e-4,
        "frame -> substrate G_f0",
        "product with absorptance only",
    ),
    ParameterInfo(
        "thermal.beam_capacitance_J_per_K",
        "J/K",
        4e-8,
        1e-8,
        1e-7,
        "beam heat capacity C_b",
        "not identifiable (2nd node)",
    ),
    ParameterInfo(
        "thermal.frame_beam_W_per_K", "W/K", 3e-5, 1e-5, 1e-4, "frame -> beams G_fb", "no"
    ),
    ParameterInfo(
        "thermal.beam_ground_W_per_K", "W/K", 2e-5, 1e-5, 1e-4, "beams -> anchor G_b0", "no"
    ),
    ParameterInfo(
        "thermal.side_coupling_W_per_K", "W/K", 5e-6, 0.0, 3e-5, "left-right coupling G_LR", "no"
    ),
    ParameterInfo(
        "locomotion.foot_forward_N",
        "N",
        0.3e-6,
        0.05e-6,
        10e-6,
        "foot forward capacity F_f+",
        "only through W = (F_a + F_b)/k",
    ),
    ParameterInfo(
        "locomotion.foot_backward_N",
        "N",
        1.5e-6,
        0.05e-6,
        10e-6,
        "foot backward capacity F_f-",
        "only whether the gait exists",
    ),
    ParameterInfo(
        "locomotion.dimple_forward_N",
        "N",
        0.8e-6,
        0.05e-6,
        10e-6,
        "dimple forward capacity F_d+",
        "only through W",
    ),
    ParameterInfo(
        "locomotion.dimple_backward_N",
        "N",
        0.8e-6,
        0.05e-6,
        10e-6,
        "dimple backward capacity F_d-",
        "only whether the gait exists",
    ),
    ParameterInfo(
        "locomotion.stiffness_N_per_m",
        "N/m",
        5.0,
        1.0,
        2000.0,
        "actuator-plus-leg stiffness k",
        "only through W",
    ),
    ParameterInfo(
        "locomotion.turn_gain",
        "1",
        1.0,
        0.0,
        1.0,
        "play-surrogate turning gain kappa_psi",
        "identifiable from two tracked features",
    ),
    ParameterInfo(
        "image_offset_x_m", "m", 0.0, None, None, "image x of the start-body origin", "one per run"
    ),
    ParameterInfo(
        "image_offset_y_m", "m", 0.0, None, None, "image y of the start-body origin", "one per run"
    ),
)


def default_free_parameters(**_options) -> list[FreeParameter]:
    """Thermal gain and time constant, friction via foot capacity and stiffness with log-normal
    priors (the data fix only their ratio W), turning gain, and per-run image offsets.

    The gain starts low (0.30, nominal 0.45) and the turning gain mid-range: the step per cycle
    is S_pp - W, so a start that over-predicts the walk by more than the walk itself fits
    worse than no motion at all, and Levenberg-Marquardt then descends into the play dead
    zone (S_pp < W everywhere, all motion gradients zero). A start that under-predicts always
    fits better than standing still, so a monotone descent never gets there."""
    return [
        FreeParameter("absorptance_left", unit="1", lower=0.05, upper=1.0, initial=0.30),
        FreeParameter(
            "thermal.frame_capacitance_J_per_K",
            unit="J/K",
            lower=1e-9,
            prior_median=1.9e-7,
            prior_log_sd=1.0,
        ),
        FreeParameter(
            "locomotion.foot_forward_N", unit="N", lower=1e-9, prior_median=0.3e-6, prior_log_sd=1.0
        ),
        FreeParameter(
            "locomotion.stiffness_N_per_m",
            unit="N/m",
            lower=1e-3,
            prior_median=5.0,
            prior_log_sd=0.3,
        ),
        FreeParameter("locomotion.turn_gain", unit="1", lower=0.0, upper=3.0, initial=0.5),
        FreeParameter("image_offset_x_m", unit="m", per_experiment=True, scale=1e-6),
        FreeParameter("image_offset_y_m", unit="m", per_experiment=True, scale=1e-6),
    ]


def play_width_estimate(result) -> tuple[float, float]:
    """(W [m], standard error [m]) of the per-side play width at a fit's shared parameters.

    Delta method on the fit's raw covariance: W is what pose data identify even when the
    friction capacities and the stiffness are each prior-dominated."""
    from greybox.uncertainty import delta_method

    value, cov = delta_method(
        lambda m: m.locomotion.play_width_m(),
        result.model,
        result.free,
        result.raw,
        result.covariance_raw,
    )
    return float(value[0]), float(np.sqrt(cov[0, 0]))


SPEC = DeviceSpec(
    name="microrobot",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=PARAMETERS,
    default_free=default_free_parameters,
    options=(
        Option(
            "contacts",
            "play",
            "foot contacts: smooth play operator or directional Coulomb friction (Newton solve)",
            choices=("play", "friction"),
        ),
        Option(
            "wavelength_nm",
            800.0,
            "laser wavelength (sets nominal absorptances)",
            minimum=200.0,
            maximum=20000.0,
            unit="nm",
        ),
        Option("substeps", 4, "sub-steps per input interval", minimum=1, maximum=64),
        Option(
            "substep_growth", 2.0, "ratio of successive sub-step lengths", minimum=1.0, maximum=10.0
        ),
    ),
    description=__doc__.split("\n\n")[0],
)
