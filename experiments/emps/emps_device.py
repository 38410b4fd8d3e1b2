"""EMPS stage (Janot, Gautier, Brunot 2019) inside its position loop: reference in, position out.

A user-written greybox device (not in ``models/``): ``experiment.toml`` names it as
``device = "emps_device.py:SPEC"``.

Plant (rigid load on a ball screw, motor force referred to the load side):

    M dv/dt = tau_m - Fv v - Fc tanh(v / v_eps) - offset,      dq/dt = v

Controller (known, from the benchmark files; DATA.md section 5): a digital P/PD position loop
sampled at the rows of the run CSV (Ts = 1 ms). At sample k, with the measured position q_k,

    vir_k = kv (kp (qref_k - q_k) - (q_k - q_{k-2}) / (2 Ts)) + pulse_k      [V]
    tau_m = gtau * clip(vir_k, -vir_max, vir_max)                             [N]

held constant until the next sample (zero-order hold; `pulse_k` is the validation run's 0/5 V
pulse added to the controller output). gtau = 35.1507 N/V, kp = 160.18 1/s, kv = 243.45
V/(m/s), saturation 10 V. The velocity the controller uses is the 2-tap central difference of
the position (the benchmark's 0.5/0.5 FIR), which lags the true velocity by one sample; with
kv gtau = 8557 N s/m that lag alone is worth about 8.6 kg of apparent mass, which is why the
controller is simulated as sampled, not as a continuous PD law.

The friction sign is smoothed, sign(v) ~ tanh(v / v_eps): `v_eps_m_per_s` is a structural
option (default 1 mm/s, 1/125 of the 0.125 m/s plateau velocity; only the few ms around each
velocity reversal see the difference). The plant is integrated between samples by classical
RK4 with `substeps` sub-steps per sample (another option).

The simulation is not an ODE with piecewise-constant input (the control law is a per-sample
map with memory of q_{k-1}, q_{k-2}), so the device is an `AbstractSteppedDevice`: one
`lax.scan` over the samples. Every row of the run CSV must be one controller sample (do not
decimate the input: convert.py keeps the 1 kHz rows and thins only the fitted output).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp

from greybox import (
    AbstractSteppedDevice,
    Channel,
    DeviceSpec,
    FreeParameter,
    Option,
    ParameterInfo,
)
from greybox.blocks import SensorReadout

# Controller constants stored in DATA_EMPS.mat / DATA_EMPS_PULSES.mat
GTAU_N_PER_V = 35.15065188
KP_PER_S = 160.18
KV_V_S_PER_M = 243.45
SAMPLE_PERIOD_S = 1e-3
VIR_MAX_V = 10.0

# Starting guesses of a user without the published values (round numbers, deliberately off)
NOMINAL = {"M_kg": 80.0, "Fv_N_s_per_m": 100.0, "Fc_N": 10.0, "offset_N": 0.0}

INPUTS = (
    Channel("qref", "m", {"m": (1.0, 0.0), "mm": (1e-3, 0.0)}, "reference position"),
    Channel(
        "pulse",
        "V",
        {"V": (1.0, 0.0)},
        "voltage pulse added to the controller output (0 in the estimation run)",
    ),
)
OUTPUTS = (Channel("q", "m", {"m": (1.0, 0.0), "mm": (1e-3, 0.0)}, "measured position"),)


class EMPS(AbstractSteppedDevice):
    """Closed-loop EMPS: state (q, v, q_{k-1}, q_{k-2}); input (qref [m], pulse [V]); output q.

    - `M_kg`, `Fv_N_s_per_m`, `Fc_N`, `offset_N`: the inverse-dynamic-model parameters.
    - `gtau_N_per_V`, `kp_per_s`, `kv_V_s_per_m`, `sample_period_s`, `vir_max_V`: the known
      controller (fixed).
    - `initial_q_m`, `initial_v_m_per_s`: state at the first row (known per run from the data).
    - `v_eps_m_per_s` (static): velocity scale of the smooth sign; `substeps` (static): RK4
      sub-steps per sample.
    """

    M_kg: float
    Fv_N_s_per_m: float
    Fc_N: float
    offset_N: float
    readout: SensorReadout  # the encoder: position + offset, no blur
    gtau_N_per_V: float = GTAU_N_PER_V
    kp_per_s: float = KP_PER_S
    kv_V_s_per_m: float = KV_V_S_PER_M
    sample_period_s: float = SAMPLE_PERIOD_S
    vir_max_V: float = VIR_MAX_V
    initial_q_m: float = 0.0
    initial_v_m_per_s: float = 0.0
    v_eps_m_per_s: float = eqx.field(static=True, default=1e-3)
    substeps: int = eqx.field(static=True, default=2)

    @property
    def n_states(self) -> int:
        return 4

    @property
    def n_inputs(self) -> int:
        return 2

    @property
    def n_outputs(self) -> int:
        return 1

    def initial_state(self):
        q0 = jnp.asarray(self.initial_q_m, dtype=float)
        v0 = jnp.asarray(self.initial_v_m_per_s, dtype=float)
        ts = self.sample_period_s
        return jnp.stack([q0, v0, q0 - v0 * ts, q0 - 2.0 * v0 * ts])

    def control_force_N(self, x, u):
        """Motor force [N] held over the sample that starts in state `x` with input `u`."""
        q, q2 = x[0], x[3]
        vel = (q - q2) / (2.0 * self.sample_period_s)
        vir = self.kv_V_s_per_m * (self.kp_per_s * (u[0] - q) - vel) + u[1]
        return self.gtau_N_per_V * jnp.clip(vir, -self.vir_max_V, self.vir_max_V)

    def acceleration(self, v, force_N):
        friction = self.Fv_N_s_per_m * v + self.Fc_N * jnp.tanh(v / self.v_eps_m_per_s)
        return (force_N - friction - self.offset_N) / self.M_kg

    def step(self, x, dt, u):
        """State at the next sample: RK4 sub-steps of the plant under the held force; the
        sample memory shifts only on a real interval (padding has dt = 0)."""
        force = self.control_force_N(x, u)
        h = dt / self.substeps

        def f(z):
            return jnp.stack([z[1], self.acceleration(z[1], force)])

        z = x[:2]
        for _ in range(self.substeps):
            k1 = f(z)
            k2 = f(z + 0.5 * h * k1)
            k3 = f(z + 0.5 * h * k2)
            k4 = f(z + h * k3)
            z = z + h / 6.0 * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
        shifted = jnp.concatenate([z, x[:1], x[2:3]])
        return jnp.where(dt > 0, shifted, x)

    def grid_states(self, x0, dt_s, u_grid):
        """States (L+1, 4) at the sample instants, from the L intervals `dt_s`."""

        def body(x, inp):
            x = self.step(x, *inp)
            return x, x

        _, xs = jax.lax.scan(body, x0, (dt_s, u_grid))
        return jnp.concatenate([x0[None], xs])

    def output(self, x):
        return x[:1]

    def observe_schedule(self, sched, method):
        grid = self.grid_states(self.initial_state(), sched["dt"], sched["u_grid"])
        outputs = jax.vmap(self.output)(grid[sched["eval_index"]])
        n_frames = sched["t_s"].shape[0]
        z = self.readout.observe(outputs.reshape(n_frames, -1, 1), sched["t_s"], sched["t_start"])
        return z, jnp.all(jnp.isfinite(z))


def build(*, v_eps_m_per_s: float = 1e-3, substeps: int = 2) -> EMPS:
    """EMPS at the round starting guesses `NOMINAL`, read by an encoder (no camera blur)."""
    return EMPS(
        **NOMINAL,
        readout=SensorReadout(),
        v_eps_m_per_s=v_eps_m_per_s,
        substeps=substeps,
    )


PARAMETERS = (
    ParameterInfo("M_kg", "kg", NOMINAL["M_kg"], 10.0, 500.0, "moving mass", "identifiable"),
    ParameterInfo(
        "Fv_N_s_per_m",
        "N s/m",
        NOMINAL["Fv_N_s_per_m"],
        1.0,
        2000.0,
        "viscous friction coefficient",
        "identifiable (constant-velocity segments of both signs)",
    ),
    ParameterInfo(
        "Fc_N",
        "N",
        NOMINAL["Fc_N"],
        0.1,
        200.0,
        "Coulomb friction level",
        "identifiable (velocity reversals)",
    ),
    ParameterInfo(
        "offset_N",
        "N",
        NOMINAL["offset_N"],
        -100.0,
        100.0,
        "constant force offset (motor/amplifier offset, gravity component)",
        "identifiable",
    ),
    ParameterInfo("gtau_N_per_V", "N/V", GTAU_N_PER_V, None, None, "drive gain", "fixed (data)"),
    ParameterInfo("kp_per_s", "1/s", KP_PER_S, None, None, "position gain", "fixed (data)"),
    ParameterInfo(
        "kv_V_s_per_m", "V s/m", KV_V_S_PER_M, None, None, "velocity gain", "fixed (data)"
    ),
    ParameterInfo(
        "sample_period_s", "s", SAMPLE_PERIOD_S, None, None, "controller period", "fixed (data)"
    ),
    ParameterInfo(
        "vir_max_V", "V", VIR_MAX_V, None, None, "controller output saturation", "fixed (data)"
    ),
    ParameterInfo(
        "initial_q_m", "m", 0.0, None, None, "position at the first row", "known per run"
    ),
    ParameterInfo(
        "initial_v_m_per_s",
        "m/s",
        0.0,
        None,
        None,
        "velocity at the first row",
        "known per run (first difference of q)",
    ),
)


def default_free_parameters(**_options) -> list[FreeParameter]:
    """M, Fv, Fc and the force offset, within their table ranges."""
    return [
        FreeParameter(p.path, unit=p.unit, lower=p.lower, upper=p.upper) for p in PARAMETERS[:4]
    ]


SPEC = DeviceSpec(
    name="emps",
    inputs=INPUTS,
    outputs=OUTPUTS,
    build=build,
    parameters=PARAMETERS,
    default_free=default_free_parameters,
    options=(
        Option(
            "v_eps_m_per_s",
            1e-3,
            "velocity scale of the smooth Coulomb sign, sign(v) ~ tanh(v / v_eps)",
            minimum=1e-6,
            maximum=0.1,
            unit="m/s",
        ),
        Option("substeps", 2, "RK4 sub-steps of the plant per controller sample", minimum=1),
    ),
    description=__doc__.split("\n\n")[0],
)
