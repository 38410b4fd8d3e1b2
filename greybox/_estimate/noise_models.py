"""Configuration objects of a fit: the noise model, its loss or filter, the simulation path.

`greybox.fit(model, experiments, free, noise=..., simulation=...)` takes these instead of
strings; TOML keeps its strings and io maps them to these objects once (`from_strings`).

- `OutputError(loss=Huber(1.5) | StudentT(4.0) | L2(), sigma=None)`: deterministic
  simulation (free-run) error, the least-squares back end. `sigma`: declared measurement sd
  per output [SI], or None to estimate it robustly from the residuals.
- `ProcessNoise(structure, filter=None | KalmanFilter() | ExtendedKalmanFilter(substeps),
  initial_state=InitialState(...), k_step=10, whiteness_lags=20)`: process noise on the
  states (`NoiseStructure`), measurement noise, maximum likelihood by the continuous-discrete
  (extended) Kalman filter, the likelihood back end. The free list may name device paths and
  noise paths (`process.<group>`, `measurement.<output>`, `output_walk.<name>`,
  `input_walk.<input>`, see `greybox.stochastic.noise_parameters`).
- `ZOH()`, `Adaptive(rtol, atol, max_steps)`, `Stiff(rtol, atol, max_steps)`: the simulation
  path (exact zero-order hold for linear devices; diffrax with jump times otherwise, explicit
  or, for a stiff device, implicit).

Every object is a frozen dataclass: hashable, comparable, printable, safe as a static field.
"""

from __future__ import annotations

import dataclasses

__all__ = [
    "L2",
    "Adaptive",
    "ExtendedKalmanFilter",
    "Huber",
    "InitialState",
    "KalmanFilter",
    "OutputError",
    "ProcessNoise",
    "StudentT",
    "ZOH",
    "from_strings",
]


# ---- losses of the output-error back end ---------------------------------------------------
@dataclasses.dataclass(frozen=True)
class L2:
    """Plain least squares (Gaussian errors)."""

    name = "l2"


@dataclasses.dataclass(frozen=True)
class Huber:
    """Huber loss: quadratic within `c` noise sds, linear beyond (robust to outliers)."""

    c: float = 1.5
    name = "huber"

    def __post_init__(self):
        if not float(self.c) > 0:
            raise ValueError(f"Huber: c = {self.c} must be > 0 (noise sds)")


@dataclasses.dataclass(frozen=True)
class StudentT:
    """Student-t negative log-likelihood with `nu` degrees of freedom (heavy tails)."""

    nu: float = 4.0
    name = "student_t"

    def __post_init__(self):
        if not float(self.nu) > 0:
            raise ValueError(f"StudentT: nu = {self.nu} must be > 0")


LOSS_TYPES = (L2, Huber, StudentT)


# ---- simulation paths ----------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class ZOH:
    """Exact zero-order-hold discretisation (linear devices)."""

    name = "zoh"


@dataclasses.dataclass(frozen=True)
class Adaptive:
    """Adaptive ODE solve (diffrax, jump times at input breakpoints); tolerances and step
    budget of the solver (not of the optimiser)."""

    rtol: float = 1e-8
    atol: float = 1e-10
    max_steps: int = 16384
    name = "adaptive"


@dataclasses.dataclass(frozen=True)
class Stiff(Adaptive):
    """`Adaptive` with an implicit solver (diffrax Kvaerno5) for stiff devices: time scales
    far apart, where the explicit solver's steps shrink to the fastest one."""

    name = "stiff"


# ---- filters and the initial state of the likelihood back end -----------------------------
@dataclasses.dataclass(frozen=True)
class KalmanFilter:
    """The exact continuous-discrete Kalman filter (needs a linear device)."""

    name = "kalman"


@dataclasses.dataclass(frozen=True)
class ExtendedKalmanFilter:
    """The extended Kalman filter; `substeps` local linearisations per step (None: 1 on a
    linear device, 4 on a nonlinear one)."""

    substeps: int | None = None
    name = "ekf"

    def __post_init__(self):
        if self.substeps is not None and int(self.substeps) < 1:
            raise ValueError(f"ExtendedKalmanFilter: substeps = {self.substeps} must be >= 1")


@dataclasses.dataclass(frozen=True)
class InitialState:
    """The initial state of every run: mean = the device's `initial_state()` with the run's
    settings and per-run estimates applied (free a per-run initial-state path to estimate it
    with the other parameters), covariance diag(`sd`^2).

    - `sd` = 0 (default): the initial state is known.
    - `sd` > 0 (a float for every device state, or one per state) [state units]: a declared
      prior x0 ~ N(mean, diag(sd^2)) (e.g. 0 on the measured states, a few K on an unmeasured
      node).
    - `diffuse=True`: a prior of sd `DIFFUSE_SD` x the readings' spread on every device state
      (a vague initial state).
    - `score_first`: False (default): the first frame of each run is conditioned on, not
      scored: the likelihood is p(y_2..y_N | y_1). The usual case reads the initial state (of
      the measured states at least) off the first reading, which then carries no information
      and, scored, would let the measurement sd collapse to 0 with an unbounded likelihood.
      True scores it too (a prior on the initial state that is independent of the data).
    """

    sd: float | tuple = 0.0
    diffuse: bool = False
    score_first: bool = False

    def __post_init__(self):
        sd = self.sd
        if isinstance(sd, (list, tuple)):
            object.__setattr__(self, "sd", tuple(float(s) for s in sd))
            vals = self.sd
        else:
            object.__setattr__(self, "sd", float(sd))
            vals = (self.sd,)
        if not all(v >= 0 for v in vals):
            raise ValueError(f"InitialState: sd = {self.sd} must be >= 0 (state units)")

    @property
    def known(self) -> bool:
        """True when the initial state has no spread (sd 0, not diffuse)."""
        vals = self.sd if isinstance(self.sd, tuple) else (self.sd,)
        return not self.diffuse and all(v == 0 for v in vals)

    @property
    def scores_first_reading(self) -> bool:
        """Whether the first reading of each run counts in the likelihood (see the class)."""
        return bool(self.score_first)


DIFFUSE_SD = 10.0  # the diffuse prior's sd, in units of the readings' spread


# ---- noise models --------------------------------------------------------------------------
@dataclasses.dataclass(frozen=True)
class OutputError:
    """Deterministic model, noise on the readings only: least squares on the simulation
    (free-run) error with a robust `loss`; `sigma`: declared measurement sd per output [SI]
    (a float or a tuple), or None to estimate it from the residuals."""

    loss: L2 | Huber | StudentT = Huber(1.5)
    sigma: float | tuple | None = None
    name = "output error"

    def __post_init__(self):
        if not isinstance(self.loss, LOSS_TYPES):
            raise ValueError(
                f"OutputError: loss {self.loss!r} is not a loss object; use greybox.Huber(c), "
                "greybox.StudentT(nu) or greybox.L2()"
            )
        if isinstance(self.sigma, list):
            object.__setattr__(self, "sigma", tuple(float(s) for s in self.sigma))

    @property
    def horizons(self) -> tuple:
        return ("simulation",)


@dataclasses.dataclass(frozen=True)
class ProcessNoise:
    """Process noise on the states and measurement noise: maximum likelihood by the
    continuous-discrete (extended) Kalman filter.

    - `structure`: a `NoiseStructure` (which state groups carry process noise, which
      random-walk disturbances).
    - `filter`: None (the exact Kalman filter for a linear device, else the EKF),
      `KalmanFilter()` or `ExtendedKalmanFilter(substeps)`.
    - `initial_state`: `InitialState` (mean and covariance of the initial state; how the
      first reading counts).
    - `k_step`: horizon (frames) of the k-step prediction in the result; `whiteness_lags`:
      lags of the innovations' Ljung-Box test.
    - `start_noise`: start free noise parameters without `initial` from the data and the
      linearised device (`greybox._estimate.noise_starts`).
    """

    structure: object = None
    filter: KalmanFilter | ExtendedKalmanFilter | None = None
    initial_state: InitialState = InitialState()
    k_step: int = 10
    whiteness_lags: int = 20
    start_noise: bool = True
    name = "process noise"

    def __post_init__(self):
        from greybox.stochastic._sde_device import NoiseStructure

        if self.structure is None:
            object.__setattr__(self, "structure", NoiseStructure())
        if not isinstance(self.structure, NoiseStructure):
            raise ValueError(
                f"ProcessNoise: structure {self.structure!r} is not a greybox.NoiseStructure"
            )
        if self.filter is not None and not isinstance(
            self.filter, (KalmanFilter, ExtendedKalmanFilter)
        ):
            raise ValueError(
                f"ProcessNoise: filter {self.filter!r}: use None, greybox.KalmanFilter() or "
                "greybox.ExtendedKalmanFilter(substeps)"
            )
        if not isinstance(self.initial_state, InitialState):
            raise ValueError(
                f"ProcessNoise: initial_state {self.initial_state!r} is not a "
                "greybox.InitialState"
            )
        if int(self.k_step) < 1:
            raise ValueError(f"ProcessNoise: k_step = {self.k_step} must be >= 1 (frames)")
        if int(self.whiteness_lags) < 1:
            raise ValueError(f"ProcessNoise: whiteness_lags = {self.whiteness_lags} must be >= 1")

    @property
    def horizons(self) -> tuple:
        return ("simulation", "one-step", "k-step")

    def structure_with_filter(self):
        """The `NoiseStructure` with this object's filter choice written into it."""
        s = self.structure
        if self.filter is None:
            return s
        sub = getattr(self.filter, "substeps", s.substeps)
        return dataclasses.replace(s, filter=self.filter.name, substeps=sub)


# ---- the strings of experiment.toml and of the old keywords --------------------------------
def loss_from_string(loss: str, huber_c: float = 1.5, student_nu: float = 4.0):
    """The loss object of a string ("l2", "huber", "student_t")."""
    if loss == "l2":
        return L2()
    if loss == "huber":
        return Huber(float(huber_c))
    if loss == "student_t":
        return StudentT(float(student_nu))
    raise ValueError(f"loss: {loss!r} is unknown; use one of ('l2', 'huber', 'student_t')")


def simulation_from_string(
    method: str | None,
    solver_rtol: float = 1e-8,
    solver_atol: float = 1e-10,
    solver_max_steps: int = 16384,
):
    """The simulation object of a method string ("zoh", "adaptive", "stiff"), or None (the
    device's default path)."""
    if method is None:
        return None
    if method == "zoh":
        return ZOH()
    solvers = {kind.name: kind for kind in (Adaptive, Stiff)}
    if method in solvers:
        return solvers[method](float(solver_rtol), float(solver_atol), int(solver_max_steps))
    raise ValueError(f"method: {method!r} is unknown; use 'zoh', 'adaptive' or 'stiff'")


def from_strings(
    *,
    loss: str = "huber",
    huber_c: float = 1.5,
    student_nu: float = 4.0,
    sigma=None,
    method: str | None = None,
    solver_rtol: float = 1e-8,
    solver_atol: float = 1e-10,
    solver_max_steps: int = 16384,
) -> tuple:
    """(OutputError, simulation object or None) of the string settings (TOML, old keywords)."""
    noise = OutputError(loss_from_string(loss, huber_c, student_nu), sigma)
    return noise, simulation_from_string(method, solver_rtol, solver_atol, solver_max_steps)
