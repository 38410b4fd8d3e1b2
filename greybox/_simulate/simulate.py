"""One simulation entry point with two paths that agree (PHYSICS.md §11, STYLE.md §G2).

- ``method="zoh"``: exact zero-order-hold discretisation of a linear device. The time grid is
  the union of the input's switching times and every camera evaluation instant, so each
  interval has a constant input and x+ = expm(A h) x + int_0^h expm(A s) ds B u is exact;
  the intervals are stepped with `lax.scan`, or, on an accelerator or for a long record, with
  `lax.associative_scan` (the interval maps x -> Phi x + Gamma u compose associatively, so
  the states are prefix compositions computed in log depth; `zoh_scan_kind`).
- ``method="adaptive"``: diffrax Tsit5 with a PID controller clipped to the input's jump times
  (`ClipStepSizeController(jump_ts=...)`), forward-mode adjoint (Levenberg-Marquardt builds
  Jacobians with jvp) and ``throw=False`` so that a failed solve never aborts an outer fit.
- ``method="stiff"``: the same with Kvaerno5 (implicit ESDIRK, L-stable) for a device whose
  time scales lie far apart, where Tsit5's steps are held to the fastest one for the whole
  record (a 10 ms sensor lag beside a 60 s plate over 10 minutes: Tsit5 runs out of 2,000
  steps, Kvaerno5 does not; tests/test_stiff_method.py).

Observations are produced at arbitrary (irregular) camera timestamps; the camera's exposure is
averaged with Gauss-Legendre nodes evaluated identically on both paths.

The numpy preprocessing (`greybox._simulate.schedules`) depends only on data, never on
parameters, so it is built once per experiment; everything after it is a pure, jit-able
function of the model.
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._model.device import (
    METHODS,
    ODE_METHODS,
    AbstractDevice,
    AbstractSteppedDevice,
    check_method,
)
from greybox._platform import on_accelerator
from greybox._simulate.schedules import schedule_row


def require_x64(where: str) -> None:
    """Fits and simulations need float64; the library never flips global config itself."""
    if not jax.config.jax_enable_x64:
        raise ValueError(
            f"{where}: float64 is disabled; call jax.config.update('jax_enable_x64', True) "
            "before using greybox (the greybox command and scripts do this for you)"
        )


# what to do when the adaptive solve of a run fails: said by simulate, fit and validate
SOLVER_FAILED = (
    "the adaptive ODE solver ran out of steps or its step size collapsed. Where the "
    "device's time scales lie far apart (a lag of milliseconds beside a time constant of "
    "minutes; look for a fitted time constant far below the frame interval) use the "
    "implicit solver (method = \"stiff\"; [fit] method in experiment.toml); otherwise raise "
    "the solver's step budget (solver_max_steps; [fit] solver_max_steps), which is not the "
    "optimiser's max_steps, or check the parameters"
)


class SolverFailed(ValueError):
    """A run's adaptive ODE solve failed (`SOLVER_FAILED` says what to do)."""


_EXPM_MAX_SQUARINGS = 24  # handles |A h| up to ~4e6: far beyond any RC time-constant ratio


_TAYLOR_COEFFS = [1.0 / math.factorial(k) for k in range(13)]  # degree 12


def expm_taylor(x):
    """Matrix exponential of `x` (..., n, n) by a degree-12 Taylor series with scaling and
    squaring, for a whole batch of matrices at once.

    Plain polynomial arithmetic with a fixed loop length: its forward-mode derivative is cheap,
    unlike the branchy Pade implementation. After scaling |x / 2^s|_1 <= 1/4, so the
    truncation error is below 1e-15 relative. The series is evaluated in Paterson-Stockmeyer
    form (x^2, x^3, x^4, then Horner in x^4: 5 products instead of 12), and the squarings
    beyond the largest `s` of the batch are skipped (`lax.cond` in a loop of fixed length, so
    that reverse mode works as well as forward mode): most steps of a simulation need none or
    few, and each product costs as much again in every forward-mode tangent. (Under `vmap`,
    where `s` differs per member, the cond becomes a select and all squarings run, masked.)
    """
    n = x.shape[-1]
    norm = jnp.max(jnp.sum(jnp.abs(x), axis=-2), axis=-1)
    s = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.25)), 0, _EXPM_MAX_SQUARINGS)
    y = x / (2.0**s)[..., None, None]
    eye = jnp.broadcast_to(jnp.eye(n, dtype=x.dtype), x.shape)
    y2 = y @ y
    y3 = y2 @ y
    y4 = y2 @ y2
    c = _TAYLOR_COEFFS

    def block(j):  # sum_{i<4} c[4j+i] y^i
        return c[4 * j] * eye + c[4 * j + 1] * y + c[4 * j + 2] * y2 + c[4 * j + 3] * y3

    t = block(2) + c[12] * y4
    t = block(1) + y4 @ t
    t = block(0) + y4 @ t
    s_max = jnp.max(s)

    def square(i, t):
        def on(t):
            return jnp.where((i < s)[..., None, None], t @ t, t)

        return jax.lax.cond(i < s_max, on, lambda t: t, t)

    return jax.lax.fori_loop(0, _EXPM_MAX_SQUARINGS, square, t)


def zoh_matrices(a, b, dt):
    """Exact ZOH transition and input matrices (Phi (L, n, n), Gamma (L, n, m)) for steps `dt`."""
    n, m = b.shape
    if n == 1:  # scalar state: closed form, far cheaper to differentiate than a matrix series
        a0 = a[0, 0]
        phi = jnp.exp(a0 * dt)
        # Gamma = b (e^{ah} - 1) / a, written with expm1 so that tiny a h keeps full precision
        gain = jnp.where(a0 != 0, jnp.expm1(a0 * dt) / jnp.where(a0 != 0, a0, 1.0), dt)
        return phi[:, None, None], gain[:, None, None] * b[None]
    aug = jnp.zeros((n + m, n + m)).at[:n, :n].set(a).at[:n, n:].set(b)
    # expm([[A, B], [0, 0]] h) = [[Phi, Gamma], [0, I]] gives both ZOH matrices at once
    blocks = expm_taylor(aug[None] * dt[:, None, None])
    return blocks[:, :n, :n], blocks[:, :n, n:]


ZOH_SCANS = ("auto", "sequential", "associative")
ASSOCIATIVE_MIN_INTERVALS = 16384  # on a CPU the two scans ran within ~20 % of each other at
# 1,000-64,000 intervals (1- and 3-node chevron, linear TCLab); beyond this, log depth wins


def zoh_scan_kind(n_intervals: int, scan: str = "auto") -> str:
    """Which scan steps the ZOH intervals: "sequential" (one interval after another) or
    "associative" (`jax.lax.associative_scan`, log depth: what an accelerator needs, since a
    sequential scan runs one tiny kernel per interval). "auto" takes the associative scan on
    an accelerator (`greybox._platform.on_accelerator()`) or for records of at least
    `ASSOCIATIVE_MIN_INTERVALS` intervals, else the sequential one. Both give the same
    states to rounding (`tests/test_simulate_scan.py`)."""
    if scan not in ZOH_SCANS:
        raise ValueError(f"zoh_scan: {scan!r} is unknown; use one of {ZOH_SCANS}")
    if scan != "auto":
        return scan
    if on_accelerator() or int(n_intervals) >= ASSOCIATIVE_MIN_INTERVALS:
        return "associative"
    return "sequential"


def _compose(earlier, later):
    """(A2, b2) o (A1, b1) = (A2 A1, A2 b1 + b2): the map x -> A1 x + b1, then A2 x + b2."""
    a1, b1 = earlier
    a2, b2 = later
    return a2 @ a1, (a2 @ b1[..., None])[..., 0] + b2


def _zoh_grid_states(model: AbstractDevice, x0, dt, u_grid, scan: str = "auto"):
    """States at every grid point (L+1, n) by exact ZOH steps x+ = Phi x + Gamma u.

    Each interval is the affine map x -> Phi x + Gamma u; the maps compose associatively, so
    the states are also the prefix compositions applied to x0 (`zoh_scan_kind`)."""
    a, b = model.linear_dynamics()
    phi, gamma = zoh_matrices(a, b, dt)
    drive = (gamma @ u_grid[..., None])[..., 0]  # (L, n): Gamma u of each interval
    if zoh_scan_kind(dt.shape[0], scan) == "associative":
        phi_cum, drive_cum = jax.lax.associative_scan(_compose, (phi, drive))
        xs = (phi_cum @ x0[:, None])[..., 0] + drive_cum
    else:

        def step(x, inp):
            p, d = inp
            x = p @ x + d
            return x, x

        _, xs = jax.lax.scan(step, x0, (phi, drive))
    return jnp.concatenate([x0[None], xs]), jnp.array(True)


# Up to this many breakpoints, `input_at` compares t with all of them at once instead of a
# binary search: inside the adaptive solver (a vmapped, differentiated while loop) the search
# is a nested loop; the chevron benchmark's adaptive fit (128 breakpoints a run) took 0.561 ->
# 0.485 s, with 256 and 512 breakpoints 7 % and 2 % less time (same estimates, bit for bit).
COMPARE_ALL_MAX_BREAKS = 512


def input_at(breaks, levels, t):
    """Right-continuous piecewise-constant lookup (0 before the first breakpoint)."""
    method = "compare_all" if breaks.shape[-1] <= COMPARE_ALL_MAX_BREAKS else "scan"
    idx = jnp.searchsorted(breaks, t, side="right", method=method) - 1
    return jnp.where(idx >= 0, levels[jnp.clip(idx, 0)], 0.0)


ADJOINTS = {"forward": "ForwardMode", "reverse": "RecursiveCheckpointAdjoint"}  # diffrax's


class _InputDriven(eqx.Module):
    """The device's vector field under its piecewise-constant input: a module, not a closure,
    so that two solves of one structure are the same function to `diffeqsolve`'s own jit,
    whose trace is then made once."""

    model: AbstractDevice
    breaks: jax.Array
    levels: jax.Array

    def __call__(self, t, x, args):
        return self.model.vector_field(t, x, input_at(self.breaks, self.levels, t))


def _adaptive_states(
    model: AbstractDevice,
    x0,
    t_start,
    eval_t,
    breaks,
    levels,
    jump_ts,
    rtol,
    atol,
    max_steps,
    adjoint="forward",
    stiff=False,
):
    """States at the (sorted) evaluation instants, and whether the solve succeeded. `stiff`:
    Kvaerno5 (implicit, L-stable ESDIRK; its Newton iterations take their tolerances from
    the step-size controller) instead of Tsit5."""

    import diffrax as dfx  # here: a device simulated by ZOH never imports it (0.13 s)

    controller = dfx.ClipStepSizeController(
        dfx.PIDController(rtol=rtol, atol=atol), jump_ts=jump_ts
    )
    sol = dfx.diffeqsolve(
        dfx.ODETerm(_InputDriven(model, breaks, levels)),
        dfx.Kvaerno5() if stiff else dfx.Tsit5(),
        t_start,
        eval_t[-1],
        None,
        x0,
        saveat=dfx.SaveAt(ts=eval_t),
        stepsize_controller=controller,
        adjoint=getattr(dfx, ADJOINTS[adjoint])(),
        max_steps=max_steps,
        throw=False,
    )
    return sol.ys, sol.result == dfx.RESULTS.successful


def observe_schedule(
    model: AbstractDevice,
    sched: dict,
    *,
    method: str = "zoh",
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 16384,
    adjoint: str = "forward",
    zoh_scan: str = "auto",
):
    """Camera readings (N, n_y) [SI] and a success flag for one (padded) schedule dict.

    Pure and jit/vmap-able: `sched` holds the arrays of one row of `schedules.stacked_schedules`.
    `adjoint` (adaptive path only): "forward" (ForwardMode; what Levenberg-Marquardt's jvp
    Jacobians need) or "reverse" (RecursiveCheckpointAdjoint, for `jax.grad`/`jacrev`).
    """
    if isinstance(model, AbstractSteppedDevice):
        return model.observe_schedule(sched, method)
    x0 = jnp.asarray(model.initial_state(), dtype=float)
    n_frames = sched["t_s"].shape[0]
    if method == "zoh":
        grid, ok = _zoh_grid_states(model, x0, sched["dt"], sched["u_grid"], zoh_scan)
        states = grid[sched["eval_index"]]
    elif method in ODE_METHODS:
        sorted_states, ok = _adaptive_states(
            model,
            x0,
            sched["t_start"],
            sched["eval_t"],
            sched["breaks"],
            sched["levels"],
            sched["jump_ts"],
            rtol,
            atol,
            max_steps,
            adjoint,
            stiff=method == "stiff",
        )
        states = sorted_states[sched["unsort"]]
    else:
        raise ValueError(f"method: {method!r} is unknown; use one of {METHODS}")
    outputs = jax.vmap(model.output)(states)
    outputs = outputs.reshape(n_frames, -1, outputs.shape[-1])
    z = model.readout.observe(outputs, sched["t_s"], sched["t_start"])
    return z, ok


def simulate(
    model: AbstractDevice,
    inputs,
    t_s,
    *,
    method: str | None = None,
    t_start_s: float = 0.0,
    rtol: float = 1e-8,
    atol: float = 1e-10,
    max_steps: int = 16384,
    throw: bool = True,
    zoh_scan: str = "auto",
):
    """Simulate what the camera sees for a given input waveform.

    **Arguments:**
    - `model`: a device (e.g. `greybox.get_device("chevron_laser").model()`).
    - `inputs`: a waveform (`PulseTrain`, `PiecewiseConstant`, ...) in the device's input units
      (laser power in W), one channel per device input.
    - `t_s`: frame timestamps [s], shape (N,), strictly increasing, any spacing.
    - `method`: "zoh" (exact, linear devices), "adaptive" (diffrax Tsit5 with jump times) or
      "stiff" (the same with Kvaerno5, implicit: time scales far apart); None picks the
      device's default (`greybox._model.device.default_method`).
    - `t_start_s`: time [s] at which the device is in `model.initial_state()` (default 0).
    - `rtol`, `atol`, `max_steps`: adaptive solver settings (state units: K).
    - `throw`: raise if the adaptive solve fails; with False the result is NaN instead.
    - `zoh_scan`: how the ZOH path steps its intervals: "sequential", "associative" (a
      parallel prefix scan, for accelerators and long records) or "auto" (`zoh_scan_kind`).

    **Returns:** observations in SI (m for displacement), shape (N,) for one output, else (N, n_y).
    """
    require_x64("simulate")
    method = check_method(model, method)
    row = schedule_row(model, inputs, t_s, t_start_s=t_start_s)
    zoh_scan_kind(0, zoh_scan)  # a clear error for a misspelt scan before compiling
    z, ok = _observe_jit(as_arrays(model), row, method, rtol, atol, max_steps, zoh_scan)
    if not bool(ok):
        if throw:
            raise SolverFailed(f"simulate: {SOLVER_FAILED}")
        z = jnp.full_like(z, jnp.nan)
    z = np.asarray(z)[: np.size(t_s)]
    return z[:, 0] if z.shape[1] == 1 else z


def as_arrays(model, on_device: bool = True):
    """Turn Python-number leaves into float arrays, so new values never trigger a recompile:
    on the device (all in one `jax.device_put`: one dispatch per leaf cost about a millisecond
    of every chevron fit), or kept on the host as numpy arrays."""
    leaves, treedef = jax.tree.flatten(model)
    numbers = [
        i for i, x in enumerate(leaves) if isinstance(x, (float, int)) and not isinstance(x, bool)
    ]
    values = [np.asarray(leaves[i], dtype=float) for i in numbers]
    for i, v in zip(numbers, jax.device_put(values) if on_device else values):
        leaves[i] = v
    return jax.tree.unflatten(treedef, leaves)


@jit
def _observe_jit(model, row, method, rtol, atol, max_steps, zoh_scan="auto"):
    return observe_schedule(
        model, row, method=method, rtol=rtol, atol=atol, max_steps=max_steps, zoh_scan=zoh_scan
    )
