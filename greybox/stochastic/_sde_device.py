"""Stochastic grey-box fits of greybox devices: process noise, disturbance states, (extended)
Kalman-filter likelihood, the same free-parameter conventions as `greybox.fit`.

A `StochasticDevice` wraps a device (`AbstractLinearDevice` or any `AbstractODEDevice`) with
a noise structure (`NoiseStructure`, static) and the noise parameters (values):

    dx = f(t, x, u + S a_in) dt + dW_x,     E[dW_x dW_x^T] = diag(q_g over group g's states) dt
    da_in = dW_in,  da_out = dW_out          (random walks; intensities q_in, q_out)
    z_k = h(x(t_k)) + L a_out(t_k) + readout(t_k) + e_k,   e_k ~ N(0, diag(sd_j^2))

- process noise: one fitted intensity [state unit^2/s] per named group of state indices;
- disturbance states (structural options): "ambient_random_walk" (one random walk per output
  adding to it: ambient, offset or drift wander; `with_output_random_walks`),
  "ambient_random_walk_shared" (one walk added to every output), "input_random_walk" (one walk
  added to each input: an unmeasured load, a heater-power or ambient disturbance entering the
  dynamics);
- measurement noise: one standard deviation per output [output unit];
- initial state: the device's `initial_state()` with the run's settings applied (as in
  `greybox.simulate`), known (P0 = 0); the walks start at 0 with prior sd `walk_initial_sd`;
- the readout's offset and drift are subtracted from the readings (a time-varying known
  term); an exposure-averaging camera is not supported by the filter.

Parameter paths: the device's own paths (``U_W_per_m2K``, ``readout.offset``: the wrapper
forwards unknown attributes to the device) and ``process.<group>``,
``measurement.<output>``, ``output_walk.<output or "shared">``, ``input_walk.<input>``. So
`FreeParameter`s, `Experiment.settings`, per-run parameters and priors work as in `fit`
(one raw-to-model map, `_freeparams.apply_raw`).

The likelihood is the prediction-error decomposition of the continuous-discrete Kalman
filter at the frame times (dropped frames skipped):

- a linear device: `greybox.stochastic._kalman` (exact discretisation by Van Loan's method, exact
  Gaussian likelihood);
- otherwise the extended Kalman filter: on each step (constant input) the vector field is
  linearised at the current mean by `jax.jacfwd`, J = df/dx; the mean moves by the local
  linearisation m <- m + int_0^h e^{J s} ds f(m) (exact for an affine field; `substeps`
  local linearisations per step, 4 by default on a nonlinear device) and the covariance by
  Van Loan with J, P <- Ad P Ad^T + Qd; the output is linearised at the predicted mean. On a
  linear device it equals the linear filter.

The fit is `greybox.fit(..., noise=ProcessNoise(...))` (`greybox._estimate.likelihood`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._model.data import Experiment
from greybox._model.device import AbstractLinearDevice, AbstractODEDevice
from greybox._model.freeparams import FreeParameter, apply_raw, as_leaves
from greybox._simulate.schedules import fine_bucket_length
from greybox._simulate.simulate import as_arrays, require_x64
from greybox.stochastic._kalman import (
    FilterGrid,
    LinearGaussianSDE,
    discretise,
    measurement_update,
    scored_log_likelihood,
)
from greybox.stochastic._kalman import _run as _linear_run

__all__ = [
    "DISTURBANCES",
    "DeviceFilterResult",
    "NoiseStructure",
    "StochasticDevice",
    "device_filter",
    "device_log_likelihood",
    "draw_paths",
    "noise_parameters",
    "sample_paths",
    "stochastic_device",
]

DEFAULT_K_STEP = 10  # frames ahead of the k-step prediction in the diagnostics
DEFAULT_EKF_SUBSTEPS = 4  # EKF local linearisations per step of a nonlinear device
DISTURBANCES = ("ambient_random_walk", "ambient_random_walk_shared", "input_random_walk")
FILTERS = ("auto", "kalman", "ekf")
LIKELIHOOD = (
    "maximum likelihood, continuous-discrete (extended) Kalman filter, prediction-error form"
)


@dataclasses.dataclass(frozen=True)
class NoiseStructure:
    """The structural part of a stochastic device (hashable; fixed during a fit).

    - `process_groups`: ((name, (state index, ...)), ...): one process-noise intensity per
      group, on the diagonal of Qc for each of its states. Empty: no noise on the device's
      own states (only the disturbances).
    - `disturbances`: names from `DISTURBANCES`.
    - `walk_initial_sd`: prior sd of every walk's value at the start (output or input unit);
      0 (default): the walks start at 0, the readout offset and initial state carry the rest.
    - `filter`: "auto" (the linear filter for an `AbstractLinearDevice`, else the EKF),
      "kalman" (needs a linear device) or "ekf" (any device).
    - `substeps`: EKF local linearisations per step; None (default): 1 for a linear device
      (where the local linearisation is exact) and `DEFAULT_EKF_SUBSTEPS` (4) for a nonlinear
      one. The local linearisation's error falls fast with it: on the two-heater TCLab with
      radiation at 0.5-1.5 s frames the zero-noise EKF likelihood differs from the exact
      Gaussian likelihood of the simulation residuals by 4e-7 relative with 1 sub-step, 1e-7
      with 2, 2.4e-8 with 4 and 6e-9 with 8 (second order in the sub-step;
      tests/test_stochastic_device.py); each costs one Jacobian and one Van Loan exponential.
    """

    process_groups: tuple = ()
    disturbances: tuple = ()
    walk_initial_sd: float = 0.0
    filter: str = "auto"
    substeps: int | None = None

    def __post_init__(self):
        groups = tuple((str(g), tuple(int(i) for i in idx)) for g, idx in self.process_groups)
        object.__setattr__(self, "process_groups", groups)
        object.__setattr__(self, "disturbances", tuple(self.disturbances))
        names = [g for g, _ in groups]
        if len(set(names)) != len(names):
            raise ValueError(f"process_groups: a group name repeats ({names})")
        for g, idx in groups:
            if not g.isidentifier():
                raise ValueError(f"process_groups: {g!r} must be a name (letters, digits, _)")
            if not idx:
                raise ValueError(f"process_groups: group {g!r} lists no state")
        flat = [i for _, idx in groups for i in idx]
        if len(set(flat)) != len(flat):
            raise ValueError(f"process_groups: a state is in two groups ({flat})")
        for d in self.disturbances:
            if d not in DISTURBANCES:
                raise ValueError(f"disturbances: {d!r} is unknown; use any of {DISTURBANCES}")
        if "ambient_random_walk" in self.disturbances and (
            "ambient_random_walk_shared" in self.disturbances
        ):
            raise ValueError(
                "disturbances: give ambient_random_walk (one per output) or "
                "ambient_random_walk_shared (one for all), not both"
            )
        if len(set(self.disturbances)) != len(self.disturbances):
            raise ValueError(f"disturbances: a name repeats ({list(self.disturbances)})")
        if not self.walk_initial_sd >= 0:
            raise ValueError(f"walk_initial_sd: {self.walk_initial_sd} must be >= 0")
        if self.filter not in FILTERS:
            raise ValueError(f"filter: {self.filter!r} is unknown; use one of {FILTERS}")
        if self.substeps is not None and int(self.substeps) < 1:
            raise ValueError(f"substeps: {self.substeps} must be >= 1")

    def describe(self) -> str:
        """One line: the process-noise groups, the disturbances and any setting off its
        default (reports and `greybox compare`'s table of candidates)."""
        groups = ", ".join(f"{g} (states {list(i)})" for g, i in self.process_groups)
        parts = [f"process noise on {groups or 'no state'}"]
        parts.append(f"disturbances: {', '.join(self.disturbances) or 'none'}")
        if self.walk_initial_sd:
            parts.append(f"walks' initial sd {self.walk_initial_sd:g}")
        if self.filter != "auto":
            parts.append(f"filter {self.filter}")
        if self.substeps is not None:
            parts.append(f"{int(self.substeps)} EKF substeps")
        return "; ".join(parts)


class _Named(eqx.Module):
    """Scalars addressable by name (`noise.process.heaters`) for parameter paths."""

    names: tuple = eqx.field(static=True)
    values: tuple

    def __getattr__(self, name):
        try:
            names = object.__getattribute__(self, "names")
            values = object.__getattribute__(self, "values")
        except AttributeError:
            raise AttributeError(name) from None
        if name in names:
            return values[names.index(name)]
        raise AttributeError(f"{name!r} is none of {names}")

    def array(self, dtype=float):
        if not self.values:
            return jnp.zeros(0, dtype)
        return jnp.stack([jnp.asarray(v, dtype=dtype) for v in self.values])


_NOISE_FIELDS = ("process", "measurement", "output_walk", "input_walk")


class StochasticDevice(eqx.Module):
    """A device with process noise, disturbance states and measurement noise.

    Build it with `stochastic_device`. Unknown attributes are forwarded to `device`, so the
    device's parameter paths address it directly (`set_values(sd, ["U_W_per_m2K"], ...)`).
    """

    device: AbstractODEDevice
    process: _Named
    measurement: _Named
    output_walk: _Named
    input_walk: _Named
    structure: NoiseStructure = eqx.field(static=True)
    initial_sd: jnp.ndarray | None = None  # (n_device_states,) sd of the initial state
    score_first: bool = eqx.field(static=True, default=True)

    def __getattr__(self, name):
        try:
            device = object.__getattribute__(self, "device")
        except AttributeError:
            raise AttributeError(name) from None
        return getattr(device, name)

    # ---- sizes and structure -------------------------------------------------------------
    @property
    def use_ekf(self) -> bool:
        if self.structure.filter == "ekf":
            return True
        return not isinstance(self.device, AbstractLinearDevice)

    @property
    def ekf_substeps(self) -> int:
        """EKF local linearisations per step (the structure's `substeps`, or its default)."""
        if self.structure.substeps is not None:
            return int(self.structure.substeps)
        return 1 if isinstance(self.device, AbstractLinearDevice) else DEFAULT_EKF_SUBSTEPS

    @property
    def n_device_states(self) -> int:
        return int(self.device.n_states)

    @property
    def n_outputs(self) -> int:
        return int(self.device.n_outputs)

    @property
    def n_inputs(self) -> int:
        return int(self.device.n_inputs)

    @property
    def input_walk_index(self) -> tuple:
        return tuple(range(self.n_inputs)) if self.input_walk.names else ()

    @property
    def n_states(self) -> int:
        return self.n_device_states + len(self.input_walk.names) + len(self.output_walk.names)

    def _input_selector(self, dtype=float):
        p, k = self.n_inputs, len(self.input_walk.names)
        return jnp.eye(p, k, dtype=dtype)

    def _output_loading(self, dtype=float):
        q, m = self.n_outputs, len(self.output_walk.names)
        if m == 1 and q > 1:  # one walk shared by every output
            return jnp.ones((q, 1), dtype)
        return jnp.eye(q, m, dtype=dtype)

    # ---- the stochastic model ------------------------------------------------------------
    def diffusion(self, dtype=float):
        """Qc (n_aug, n_aug): process noise of the device states, then the walks."""
        n = self.n_device_states
        q_dev = jnp.zeros(n, dtype)
        for (_, idx), v in zip(self.structure.process_groups, self.process.values):
            q_dev = q_dev.at[jnp.asarray(idx)].set(jnp.asarray(v, dtype))
        q = jnp.concatenate([q_dev, self.input_walk.array(dtype), self.output_walk.array(dtype)])
        return jnp.diag(q)

    def measurement_cov(self, dtype=float):
        sd = self.measurement.array(dtype)
        return jnp.diag(sd**2)

    def initial_mean(self, dtype=float):
        x0 = jnp.asarray(self.device.initial_state(), dtype=dtype).reshape(-1)
        m = len(self.input_walk.names) + len(self.output_walk.names)
        return jnp.concatenate([x0, jnp.zeros(m, dtype)])

    def initial_cov(self, dtype=float):
        n = self.n_device_states
        m = len(self.input_walk.names) + len(self.output_walk.names)
        sd2 = float(self.structure.walk_initial_sd) ** 2
        dev = (
            jnp.zeros(n, dtype)
            if self.initial_sd is None
            else jnp.broadcast_to(jnp.asarray(self.initial_sd, dtype) ** 2, (n,))
        )
        return jnp.diag(jnp.concatenate([dev, jnp.full(m, sd2, dtype)]))

    def augmented_field(self, t, z, u):
        """d(augmented state)/dt: the device driven by u + the input walks; walks do not move."""
        n = self.n_device_states
        x = z[:n]
        k = len(self.input_walk.names)
        u = jnp.reshape(u, (-1,))
        if k:
            u = u + self._input_selector(z.dtype) @ z[n : n + k]
        dx = jnp.asarray(self.device.vector_field(t, x, u), z.dtype)
        return jnp.concatenate([dx, jnp.zeros(z.shape[0] - n, z.dtype)])

    def augmented_output(self, z):
        """Noise-free physical output h(x) + L a_out (readout terms excluded)."""
        n = self.n_device_states
        y = jnp.asarray(self.device.output(z[:n]), z.dtype).reshape(-1)
        m = len(self.output_walk.names)
        if m:
            y = y + self._output_loading(z.dtype) @ z[z.shape[0] - m :]
        return y

    def linear_sde(self, dtype=float) -> LinearGaussianSDE:
        """The `LinearGaussianSDE` of a linear device (readout terms excluded)."""
        if not isinstance(self.device, AbstractLinearDevice):
            raise ValueError(
                f"linear_sde: {type(self.device).__name__} is not an AbstractLinearDevice; "
                "its stochastic model is filtered by the EKF"
            )
        A, B = self.device.linear_dynamics()
        A = jnp.asarray(A, dtype)
        B = jnp.asarray(B, dtype).reshape(A.shape[0], -1)
        n, p = B.shape
        k = len(self.input_walk.names)
        m = len(self.output_walk.names)
        N = n + k + m
        A_aug = jnp.zeros((N, N), dtype).at[:n, :n].set(A)
        if k:
            A_aug = A_aug.at[:n, n : n + k].set(B @ self._input_selector(dtype))
        B_aug = jnp.zeros((N, p), dtype).at[:n].set(B)
        zero = jnp.zeros(N, dtype)
        C = jax.jacfwd(self.augmented_output)(zero)
        d = self.augmented_output(zero)
        return LinearGaussianSDE(
            A=A_aug,
            B=B_aug,
            Qc=self.diffusion(dtype),
            C=C,
            R=self.measurement_cov(dtype),
            x0=self.initial_mean(dtype),
            P0=self.initial_cov(dtype),
            d=d,
        )


def _channel_names(channels, n: int, prefix: str) -> tuple:
    if channels is None:
        return tuple(f"{prefix}{j}" for j in range(n))
    names = tuple(getattr(c, "name", c) for c in channels)
    if len(names) != n:
        raise ValueError(f"{prefix}: {len(names)} names given for {n} channels")
    for c in names:
        if not str(c).isidentifier():
            raise ValueError(f"channel name {c!r} cannot be a parameter name")
    return names


def stochastic_device(
    device,
    structure: NoiseStructure = NoiseStructure(),
    *,
    outputs=None,
    inputs=None,
    values: dict | None = None,
) -> StochasticDevice:
    """Wrap `device` with the noise `structure`.

    **Arguments:**

    - `device`: an `AbstractODEDevice` (linear or not) with its readout.
    - `structure`: a `NoiseStructure` (which state groups get process noise, which random-walk
      disturbances).
    - `outputs`, `inputs`: names of the output and input channels (strings or
      `greybox.Channel`s, e.g. `spec.outputs`); default y0, y1, ... and u0, u1, ...
    - `values`: starting values {noise path: SI value}, e.g. {"measurement.T1": 0.1}; the
      rest start at 1 (`greybox.fit` starts free noise parameters from the data, or set them).
    """
    if not isinstance(device, AbstractODEDevice):
        raise ValueError(
            f"{type(device).__name__}: a stochastic model needs a state-space device "
            "(AbstractODEDevice or AbstractLinearDevice)"
        )
    if structure.filter == "kalman" and not isinstance(device, AbstractLinearDevice):
        raise ValueError(
            f"filter: 'kalman' needs a linear device and {type(device).__name__} is not "
            "linear; use 'ekf' or 'auto'"
        )
    n = int(device.n_states)
    for g, idx in structure.process_groups:
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise ValueError(
                f"process_groups: group {g!r} names state(s) {bad}; the device has {n} "
                f"states (0 to {n - 1})"
            )
    out_names = _channel_names(outputs, int(device.n_outputs), "y")
    in_names = _channel_names(inputs, int(device.n_inputs), "u")
    walks = ()
    if "ambient_random_walk" in structure.disturbances:
        walks = out_names
    elif "ambient_random_walk_shared" in structure.disturbances:
        walks = ("shared",)
    in_walks = in_names if "input_random_walk" in structure.disturbances else ()
    for f in _NOISE_FIELDS:
        if hasattr(type(device), f) or f in getattr(device, "__dataclass_fields__", {}):
            raise ValueError(f"{type(device).__name__} has a field {f!r}; it clashes")
    values = dict(values or {})

    def named(field, names):
        vals = tuple(float(values.pop(f"{field}.{nm}", 1.0)) for nm in names)
        return _Named(names=tuple(names), values=vals)

    sd = StochasticDevice(
        device=device,
        process=named("process", [g for g, _ in structure.process_groups]),
        measurement=named("measurement", out_names),
        output_walk=named("output_walk", walks),
        input_walk=named("input_walk", in_walks),
        structure=structure,
    )
    if values:
        raise ValueError(f"values: {sorted(values)} are not noise parameters of this model")
    return sd


def noise_parameters(model: StochasticDevice, units: dict | None = None) -> list[FreeParameter]:
    """Every noise parameter of `model` as a `FreeParameter` (lower bound 0: fitted in log).

    `units`: {path: unit} for display (e.g. {"process.heaters": "K^2/s"}); defaults name the
    kind ("state^2/s", "output", "output^2/s", "input^2/s")."""
    units = units or {}
    default = {
        "process": "state^2/s",
        "measurement": "output",
        "output_walk": "output^2/s",
        "input_walk": "input^2/s",
    }
    out = []
    for f in _NOISE_FIELDS:
        for nm in getattr(model, f).names:
            path = f"{f}.{nm}"
            out.append(FreeParameter(path, unit=units.get(path, default[f]), lower=0.0))
    return out


# ---------------------------------------------------------------------------------------------
# One record: grid, readout terms, filters


def _t0(e: Experiment) -> np.float64:
    """Where the initial state holds: as `greybox.simulate`'s schedule (earliest of t_start,
    the first frame and the first input breakpoint). A numpy scalar, not a Python float: the
    compiled filters take it as an array argument, so runs that start at different times
    share one compiled filter (a Python float is a static argument of `jit`: one compile per
    start time)."""
    return np.float64(min(e.t_start_s, e.t_s[0], e.inputs.to_piecewise().times_s[0]))


def _grid(e: Experiment) -> FilterGrid:
    pw = e.inputs.to_piecewise()
    levels = np.asarray(pw.values, dtype=float).reshape(len(pw.times_s), -1)
    return FilterGrid(e.t_s, pw.times_s, levels, t0_s=_t0(e))


def padded_record(e: Experiment, lengths: tuple | None = None) -> tuple:
    """(grid, frame times, readings) of `e` padded to `lengths` (frames, steps; default its
    own rounded up by `schedules.fine_bucket_length`) by `FilterGrid.padded`, NaN readings on
    the padded frames: one compiled filter serves records of similar lengths. Padding changes no
    log-likelihood (its steps are exact identities, its frames unread) but costs their
    steps. The first `e.n_frames` rows of what the filter returns per frame are the
    record's."""
    grid = _grid(e)
    n, L = grid.n_frames, grid.n_steps
    n_pad, l_pad = _bucketed(n, L) if lengths is None else lengths
    grid = grid.padded(max(int(n_pad), n), max(int(l_pad), L))
    t_s = np.asarray(grid.t_s)
    y = np.asarray(e.y, dtype=float)
    y = np.concatenate([y, np.full((grid.n_frames - n, y.shape[1]), np.nan)])
    return grid, t_s, y


def stacked_records(experiments, bucket: bool = False) -> tuple:
    """(grid, frame times (E, N), readings (E, N, q)) of the runs padded to the longest one's
    frames and steps (`FilterGrid.padded`, NaN readings on the padded frames; with `bucket`,
    to those lengths rounded up by `schedules.fine_bucket_length`) and stacked along a
    leading run axis, their distinct step lengths brought to one count: a filter mapped over
    the runs (`lax.map`) is compiled once whatever their number. Without `bucket` a single
    run keeps its own length."""
    grids = [_grid(e) for e in experiments]
    n, steps = _longest(grids, bucket)
    grids = [g.padded(n, steps) for g in grids]
    k = max(g.dt_distinct.shape[0] for g in grids)
    for i, g in enumerate(grids):
        if k == steps:  # some run has every step its own: all have (no gather)
            distinct, index = g.dt_s, np.arange(steps, dtype=np.int32)
        else:  # one count of distinct lengths: the last one repeated (never gathered)
            d = np.asarray(g.dt_distinct)
            distinct, index = np.concatenate([d, np.full(k - d.size, d[-1])]), g.dt_index
        grids[i] = eqx.tree_at(lambda g: (g.dt_distinct, g.dt_index), g, (distinct, index))
    grid = jax.tree.map(lambda *xs: np.stack([np.asarray(x) for x in xs]), *grids)
    y = np.full((len(experiments), n, experiments[0].y.shape[1]), np.nan)
    for i, e in enumerate(experiments):
        y[i, : e.n_frames] = e.y
    return grid, np.asarray(grid.t_s), y


def stacked_lengths(experiments, k_step: int, bucket: bool = False) -> tuple:
    """(frames, steps, k-step loop) the runs' filters are padded to together: the longest
    run's frames and steps (`stacked_records`, rounded up as it rounds them with `bucket`)
    and the k-step prediction's longest loop (`_k_step_plan`: the most grid steps between a
    frame and the frame `k_step` before it; with `bucket` a power of two). A fit's
    diagnostics of all its runs share one compiled filter at these lengths."""
    grids = [_grid(e) for e in experiments]
    loop = max(_k_step_plan(g, int(k_step))[3] for g in grids)
    return (*_longest(grids, bucket), _rounded_loop(loop) if bucket else loop)


def _rounded_loop(n: int) -> int:
    """A k-step loop length rounded up to a power of two: a static size that records of
    similar lengths share (the steps past a frame's own are masked)."""
    return 1 << (int(n) - 1).bit_length()


def _longest(grids, bucket: bool) -> tuple[int, int]:
    """(frames, steps) of the longest of `grids`, rounded up by `schedules.fine_bucket_length` with
    `bucket`."""
    n = max(g.n_frames for g in grids)
    steps = max(g.n_steps for g in grids)
    return _bucketed(n, steps) if bucket else (n, steps)


def _bucketed(frames: int, steps: int) -> tuple[int, int]:
    """(frames, steps) rounded up by `schedules.fine_bucket_length`: the lengths a record is
    padded to, so records of similar lengths share one compiled filter."""
    return fine_bucket_length(frames), fine_bucket_length(steps)


def _readout_terms(device, t_s, t0, q: int):
    """Offset + drift of the readout at the frames (N, q) [SI]."""
    offsets, _ = device.readout.quadrature()
    if np.size(offsets) != 1 or float(np.asarray(offsets).reshape(-1)[0]) != 0.0:
        raise ValueError(
            "readout: the Kalman filter needs instantaneous readings; this camera averages "
            "over an exposure (set exposure 0 for a stochastic fit)"
        )
    t_s = jnp.asarray(t_s)
    zeros = jnp.zeros((t_s.shape[0], 1, q), t_s.dtype)
    return device.readout.observe(zeros, t_s, jnp.asarray(t0, t_s.dtype))


def _step_starts(grid: FilterGrid, dtype):
    dt_all = jnp.asarray(grid.dt_s, dtype)
    t_starts = jnp.asarray(grid.t0_s, dtype) + jnp.concatenate(
        [jnp.zeros(1, dtype), jnp.cumsum(dt_all)[:-1]]
    )
    return dt_all, t_starts


def _ekf_predictor(model: StochasticDevice, dtype):
    """(m, P, t, dt, u) -> (m, P) over one constant-input step: `model.ekf_substeps` local
    linearisations (mean exact for an affine field, covariance by Van Loan with J = df/dx)."""
    Qc = model.diffusion(dtype)
    k_sub = int(model.ekf_substeps)
    field = model.augmented_field
    jac = jax.jacfwd(field, argnums=1)

    def predict(m, P, t_i, dt, u_i):
        h_sub = dt / k_sub

        def sub(j, mP):
            m, P = mP
            t = t_i + j * h_sub
            J = jac(t, m, u_i)
            f = field(t, m, u_i)
            Ad, Bd, Qd = discretise(J, f[:, None], Qc, h_sub)
            P = Ad @ P @ Ad.T + Qd
            return m + Bd[:, 0], 0.5 * (P + P.T)

        if k_sub == 1:
            return sub(0, (m, P))
        return jax.lax.fori_loop(0, k_sub, sub, (m, P))

    return predict


def _ekf_run(model: StochasticDevice, grid: FilterGrid, y, keep_path: bool):
    """Extended Kalman filter over the grid: (log L, path), the path as the linear filter's
    (`_kalman._run`): the per-step log-likelihood terms, and with `keep_path` the per-step
    m_p, P_p, m_f, P_f, y_hat, S after them."""
    dtype = jnp.result_type(float)
    R = model.measurement_cov(dtype)
    dt_all, t_starts = _step_starts(grid, dtype)
    is_frame = grid.frame >= 0
    idx = jnp.maximum(grid.frame, 0)
    y_step = jnp.where(is_frame[:, None], y[idx], jnp.nan)
    predict = _ekf_predictor(model, dtype)
    h = model.augmented_output

    def step(carry, inputs):
        m, P, ll = carry
        dt, t_i, u_i, y_i = inputs
        m_p, P_p = predict(m, P, t_i, dt, u_i)
        y_hat = h(m_p)
        H = jax.jacfwd(h)(m_p)
        m_f, P_f, ll_i = measurement_update(m_p, P_p, y_i, y_hat, H, R)
        out = (ll_i,)
        if keep_path:
            out += (m_p, P_p, m_f, P_f, y_hat, H @ P_p @ H.T + R)
        return (m_f, P_f, ll + ll_i), out

    init = (model.initial_mean(dtype), model.initial_cov(dtype), jnp.zeros((), dtype))
    u_steps = jnp.asarray(grid.u, dtype)
    (_, _, ll), path = jax.lax.scan(step, init, (dt_all, t_starts, u_steps, y_step))
    return ll, path


def _record_loglik(model: StochasticDevice, grid: FilterGrid, t_s, t0, y):
    """log p(y) of one record (y the readings (N, q) in SI, NaN = dropped); without
    `model.score_first` the first frame is conditioned on: log p(y_2..y_N | y_1)."""
    y_adj = y - _readout_terms(model.device, t_s, t0, model.n_outputs)
    ll, (terms,) = _filter_path(model, grid, y_adj, keep_path=False)
    return scored_log_likelihood(ll, terms, grid, model.score_first)


def _filter_path(model: StochasticDevice, grid: FilterGrid, y_adj, keep_path: bool):
    """(log L, per-step path) of the filter that fits `model`: the extended Kalman filter, or
    the linear one (see `_ekf_run`)."""
    if model.use_ekf:
        return _ekf_run(model, grid, y_adj, keep_path)
    ll, path, _, _ = _linear_run(model.linear_sde(y_adj.dtype), grid, y_adj, keep_path)
    return ll, path


@dataclasses.dataclass(frozen=True)
class DeviceFilterResult:
    """The filter on one run, in the units of the readings (SI).

    - `log_likelihood`; `y_one_step` (N, q): one-step-ahead predictions of the readings and
      `y_one_step_sd` their sd (including measurement noise); `innovation` = y - y_one_step,
      `standardised_innovation` (NaN where a reading is missing);
    - `y_simulation` (N, q): free-run (simulation) prediction: the deterministic model from
      the initial state, no measurement used; `y_simulation_sd` its sd with process noise.
    - `filtered_mean` (N, n): augmented state [device states, input walks, output walks].
    - `y_k_step` (N, q), `y_k_step_sd`: k-step-ahead prediction (`k_step` frames): each reading
      predicted from the readings up to k frames before it (from the initial state for the
      first k frames); k = 1 is the one-step prediction, k -> infinity the simulation.
    """

    log_likelihood: float
    y_one_step: np.ndarray
    y_one_step_sd: np.ndarray
    innovation: np.ndarray
    standardised_innovation: np.ndarray
    y_simulation: np.ndarray
    y_simulation_sd: np.ndarray
    filtered_mean: np.ndarray
    k_step: int = 0
    y_k_step: np.ndarray | None = None
    y_k_step_sd: np.ndarray | None = None


def _k_step_plan(grid: FilterGrid, k: int, n_frames: int | None = None, round_up=False):
    """(start frame (N,) or -1 for the prior, first step (N,), last step (N,), loop length):
    the k-step-ahead prediction of frame j starts from the filtered state at frame j - k (the
    prior at t0 for j < k) and predicts through the grid steps up to frame j. Of a padded
    grid (`n_frames` real frames) the padded frames repeat the last real frame's plan;
    `round_up`: the loop length (a static size) rounded up to a power of two, so similar
    records share one compiled filter (the steps beyond a frame's are masked)."""
    step = np.asarray(grid.step, dtype=np.int64)
    real = step.size if n_frames is None else int(n_frames)
    j = np.minimum(np.arange(step.size), real - 1)
    start = np.where(j >= k, j - k, -1)
    first = np.where(start >= 0, step[np.maximum(start, 0)] + 1, 0)
    last = step[j]
    n = max(int(np.max(last - first + 1, initial=1)), 1)
    if round_up:
        n = _rounded_loop(n)
    return start.astype(np.int32), first.astype(np.int32), last.astype(np.int32), n


@jit
def _filter_arrays(model: StochasticDevice, grid: FilterGrid, t_s, t0, y, plan, n_loop: int):
    """One run: log L, one-step prediction and sd, simulation and sd, filtered means,
    k-step prediction and sd (every prediction in reading units, readout terms added), and
    log L as fitted (`scored_log_likelihood`: the first frame conditioned on unless
    `score_first`), from the same filter pass."""
    q = model.n_outputs
    dtype = y.dtype
    off = _readout_terms(model.device, t_s, t0, q)
    y_adj = y - off
    k = grid.step
    R = model.measurement_cov(dtype)

    def one(data):
        ll, (terms, _, _, m_f, P_f, y_hat, S) = _filter_path(model, grid, data, keep_path=True)
        scored = scored_log_likelihood(ll, terms, grid, model.score_first)
        return ll, scored, y_hat[k], S[k], m_f[k], P_f[k]

    ll, scored, yp, Sp, mf, Pf = jax.vmap(one)(jnp.stack([y_adj, jnp.full_like(y_adj, jnp.nan)]))
    sd1 = jnp.sqrt(jnp.diagonal(Sp[0], axis1=1, axis2=2))
    sds = jnp.sqrt(jnp.diagonal(Sp[1], axis1=1, axis2=2))
    yk, sdk = _k_step_arrays(model, grid, mf[0], Pf[0], plan, n_loop, R)
    return ll[0], yp[0] + off, sd1, yp[1] + off, sds, mf[0], yk + off, sdk, scored[0]


def _k_step_arrays(model, grid, mf, Pf, plan, n_loop, R):
    dtype = mf.dtype
    start, first, last = (jnp.asarray(a) for a in plan)
    dt_all, t_starts = _step_starts(grid, dtype)
    u_steps = jnp.asarray(grid.u, dtype)
    if model.use_ekf:
        predict = _ekf_predictor(model, dtype)

        def advance(s, m, P):
            return predict(m, P, t_starts[s], dt_all[s], u_steps[s])

    else:
        sde = model.linear_sde(dtype)
        # every step, not `discretise_steps`: run once per record, and so one compiled
        # program serves records of one length whatever their distinct step lengths
        Ad, Bd, Qd = discretise(sde.A, sde.B, sde.Qc, dt_all)

        def advance(s, m, P):
            return Ad[s] @ m + Bd[s] @ u_steps[s], Ad[s] @ P @ Ad[s].T + Qd[s]

    m0, P0 = model.initial_mean(dtype), model.initial_cov(dtype)
    n_steps = dt_all.shape[0]

    def one(j0, s0, s1):
        m = jnp.where(j0 >= 0, mf[jnp.maximum(j0, 0)], m0)
        P = jnp.where(j0 >= 0, Pf[jnp.maximum(j0, 0)], P0)

        def body(i, mP):
            s = s0 + i
            m2, P2 = advance(jnp.minimum(s, n_steps - 1), *mP)
            on = s <= s1
            return jnp.where(on, m2, mP[0]), jnp.where(on, P2, mP[1])

        m, P = jax.lax.fori_loop(0, n_loop, body, (m, P))
        H = jax.jacfwd(model.augmented_output)(m)
        S = H @ P @ H.T + R
        return model.augmented_output(m), jnp.sqrt(jnp.diag(S))

    return jax.vmap(one)(start, first, last)


def _run_arrays(m: StochasticDevice, e: Experiment, k_step: int, lengths=None):
    """`_filter_arrays` of one run, padded and cut back to its frames: to `lengths` (frames,
    steps, k-step loop: the runs of a fit to their common ones, `stacked_lengths`) or to bucketed
    ones, so runs of similar lengths share one compiled filter."""
    k_step = int(k_step)
    if k_step < 1:
        raise ValueError(f"k_step: {k_step} must be >= 1 (frames ahead)")
    n = e.n_frames
    grid, t_s, y = padded_record(e, None if lengths is None else lengths[:2])
    start, first, last, n_loop = _k_step_plan(grid, k_step, n, lengths is None)
    if lengths is not None:
        n_loop = max(n_loop, int(lengths[2]))
    out = jax.device_get(
        _filter_arrays(
            m, grid, jnp.asarray(t_s), _t0(e), jnp.asarray(y), (start, first, last), n_loop
        )
    )
    return tuple(x[:n] if np.ndim(x) and np.shape(x)[0] == grid.n_frames else x for x in out)


def device_filter(
    model: StochasticDevice, experiment: Experiment, *, k_step: int = DEFAULT_K_STEP
) -> DeviceFilterResult:
    """Run the (extended) Kalman filter of `model` on one run (its settings applied);
    `k_step`: horizon (frames) of the k-step-ahead prediction."""
    require_x64("device_filter")
    e = experiment
    m = as_arrays(e.apply_settings(model))
    ll, yp, sd1, ys, sds, mf, yk, sdk, _ = _run_arrays(m, e, k_step)
    y = np.asarray(e.y)
    v = y - yp
    return DeviceFilterResult(
        log_likelihood=float(ll),
        y_one_step=np.asarray(yp),
        y_one_step_sd=np.asarray(sd1),
        innovation=v,
        standardised_innovation=v / sd1,
        y_simulation=np.asarray(ys),
        y_simulation_sd=np.asarray(sds),
        filtered_mean=np.asarray(mf),
        k_step=int(k_step),
        y_k_step=np.asarray(yk),
        y_k_step_sd=np.asarray(sdk),
    )


def device_log_likelihood(model: StochasticDevice, experiment: Experiment) -> float:
    """log p(readings of `experiment` | model): the filter's prediction-error likelihood."""
    require_x64("device_log_likelihood")
    e = experiment
    m = as_arrays(e.apply_settings(model))
    return float(_loglik_jit(m, _grid(e), jnp.asarray(e.t_s), _t0(e), jnp.asarray(e.y)))


@jit
def _loglik_jit(model, grid, t_s, t0, y):
    return _record_loglik(model, grid, t_s, t0, y)


# ---------------------------------------------------------------------------------------------
# Sample paths (simulation with process noise)


def sample_paths(
    model: StochasticDevice,
    experiment: Experiment,
    n: int,
    *,
    seed: int = 0,
    measurement_noise: bool = False,
) -> np.ndarray:
    """`n` sample paths of the readings (n, N, q) [SI] for `experiment`'s input and frames.

    Each path draws the process noise of every step exactly (a linear device: the SDE's
    exact discretisation, x <- Ad x + Bd u + N(0, Qd); otherwise the local linearisation of
    the field at the current state with the same Van Loan covariance); `measurement_noise`
    adds N(0, R) at the frames. Readout terms are added. Settings of the run are applied.
    Each step (each frame) draws from its own key (`fold_in` of the path's key and its
    index), so a path does not depend on how far the run is padded: runs of similar lengths
    share one compiled sampler.
    """
    require_x64("sample_paths")
    e = experiment
    m = as_arrays(e.apply_settings(model))
    grid, t_s, _ = padded_record(e)  # one compiled sampler for waveforms of similar lengths
    keys = jax.random.split(jax.random.PRNGKey(int(seed)), int(n))
    z = _paths_jit(m, grid, jnp.asarray(t_s), _t0(e), keys, bool(measurement_noise))
    return np.asarray(z)[:, : e.n_frames]


@jit
def _paths_jit(model: StochasticDevice, grid: FilterGrid, t_s, t0, keys, meas: bool):
    dtype = jnp.result_type(float)
    Qc = model.diffusion(dtype)
    R = model.measurement_cov(dtype)
    off = _readout_terms(model.device, t_s, t0, model.n_outputs)
    dt_all = jnp.asarray(grid.dt_s, dtype)
    t_starts = jnp.asarray(grid.t0_s, dtype) + jnp.concatenate(
        [jnp.zeros(1, dtype), jnp.cumsum(dt_all)[:-1]]
    )
    u_steps = jnp.asarray(grid.u, dtype)
    n = model.n_states

    def chol(Q):
        # eigen-square-root (Qd may be singular: states without noise); called one matrix
        # at a time (lax.map / scan), never as a batched LAPACK call
        w, V = jnp.linalg.eigh(0.5 * (Q + Q.T))
        return V * jnp.sqrt(jnp.clip(w, 0, None))[None, :]

    x0 = model.initial_mean(dtype)
    L0 = chol(model.initial_cov(dtype))
    if not model.use_ekf:
        sde = model.linear_sde(dtype)
        Ad, Bd, Qd = discretise(sde.A, sde.B, sde.Qc, dt_all)  # every step (see above)
        Ld = jax.lax.map(chol, Qd)

        def one(eps):
            def step(x, inp):
                A_i, B_i, L_i, u_i, e_i = inp
                x = A_i @ x + B_i @ u_i + L_i @ e_i
                return x, x

            _, xs = jax.lax.scan(step, x0 + L0 @ eps[0], (Ad, Bd, Ld, u_steps, eps[1:]))
            return xs

    else:
        field = model.augmented_field
        jac = jax.jacfwd(field, argnums=1)

        def one(eps):
            def step(x, inp):
                dt, t_i, u_i, e_i = inp
                J = jac(t_i, x, u_i)
                f = field(t_i, x, u_i)
                _, B_i, Q_i = discretise(J, f[:, None], Qc, dt)
                x = x + B_i[:, 0] + chol(Q_i) @ e_i
                return x, x

            _, xs = jax.lax.scan(step, x0 + L0 @ eps[0], (dt_all, t_starts, u_steps, eps[1:]))
            return xs

    def draws(key, count, width):
        # one key per step (per frame): a path's draws do not depend on how many steps
        # follow, so the padded steps (0 s long, no noise) leave the real ones as they are
        return jax.vmap(lambda i: jax.random.normal(jax.random.fold_in(key, i), (width,), dtype))(
            jnp.arange(count)
        )

    def path(key):
        k1, k2 = jax.random.split(key)
        xs = one(draws(k1, dt_all.shape[0] + 1, n))[grid.step]
        y = jax.vmap(model.augmented_output)(xs) + off
        if meas:
            y = y + draws(k2, y.shape[0], y.shape[1]) * jnp.sqrt(jnp.diag(R))[None, :]
        return y

    return jax.lax.map(path, keys)


def draw_paths(
    model: StochasticDevice,
    free: Sequence[FreeParameter],
    raw_draws,
    inputs,
    t_s,
    *,
    t_start_s: float = 0.0,
    seed: int = 0,
    measurement_noise: bool = False,
) -> np.ndarray:
    """One sample path of the readings per parameter draw: (n, N, q) [SI].

    `raw_draws` (n, len(free)): raw coordinates of the shared `free` parameters (e.g.
    `greybox.uncertainty.raw_draws` from a fit's covariance); each path also draws its own
    process noise (and with `measurement_noise` the measurement noise), as `sample_paths`. The
    spread of the paths is the band of a simulation with process noise and parameter uncertainty.
    """
    require_x64("draw_paths")
    free = tuple(free)
    e = unread_run(model, inputs, t_s, t_start_s)
    grid, t_pad, _ = padded_record(e)  # one compiled sampler for waveforms of similar lengths
    draws = jnp.asarray(np.asarray(raw_draws, dtype=float).reshape(-1, len(free)))
    keys = jax.random.split(jax.random.PRNGKey(int(seed)), draws.shape[0])
    z = _draw_jit(
        as_arrays(model),
        as_leaves(free),  # the numbers as inputs: another fit's scales compile nothing new
        draws,
        grid,
        jnp.asarray(t_pad),
        _t0(e),
        keys,
        bool(measurement_noise),
    )
    return np.asarray(z)[:, : e.n_frames]


def unread_run(model, inputs, t_s, t_start_s: float = 0.0) -> Experiment:
    """A run of `model` driven by `inputs` at frames `t_s` with no readings yet (zeros): the
    grid of a prediction or a design run."""
    from greybox._model.waveforms import PiecewiseConstant

    t = np.asarray(t_s, dtype=float)
    return Experiment(
        "unread",
        t,
        np.zeros((t.size, int(model.n_outputs))),
        inputs if isinstance(inputs, PiecewiseConstant) else inputs.to_piecewise(),
        t_start_s=t_start_s,
    )


@jit
def _draw_jit(model, free, draws, grid, t_s, t0, keys, meas):
    def one(args):
        raw, key = args
        m = apply_raw(model, free, raw)
        return _paths_jit(m, grid, t_s, t0, key[None], meas)[0]

    return jax.lax.map(one, (draws, keys))
