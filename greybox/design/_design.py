"""Optimal experiment design and inverse (target-tracking) waveform design (pure, no I/O).

**What the next experiment should be.** For a device model at nominal values (with the
free parameters' priors) or at a fitted posterior (model, free, raw, covariance), the Fisher
information of the free raw parameters from one run is

    F = J^T J,   J = d(camera reading / sigma) / d(raw)  at the run's frame times,

with the same raw transforms (logit / log / linear) and the same simulation code as
`greybox.fit` (`observe_schedule`), so F is exactly the Gauss-Newton information the fit
will see on noise-free data. Per-run nuisance parameters (camera offsets, drift) are
marginalised per run (Schur complement F_ss - F_sn F_nn^-1 F_ns), which makes the
information of the shared parameters additive over runs; shared parameters that are not of
interest are marginalised the same way. Log-normal priors add their information.

Criteria on the information M of the parameters of interest (p of them):
"D" (default) det(M)^(1/p), "A" 1/trace(M^-1) and "E" min eig(M), all "larger is better";
`n_draws > 0` gives the Bayesian version: the log-criterion averaged over draws from the
posterior covariance (`greybox.uncertainty.raw_draws`), so the design is robust to not knowing
the parameters it is meant to measure.

Waveform families and how they are optimised (honest choices):

- pulse trains (power, period, duty per run): the switching times are data in the exact
  ZOH schedule, so period and duty are not differentiable there. They are searched on a
  lab-friendly grid (periods in whole ms, log-spaced; duties in 5 % steps), the power is set
  in closed form to the largest value the power range and the average-power cap allow (the
  information grows with power), and a union of `n_runs` runs is chosen from the candidates
  by greedy selection followed by exchange passes (Fedorov-style): the per-run information
  is additive, so each candidate is simulated once.
- multilevel sequences: levels on a fixed hold grid (hold >= the minimum pulse width, so
  every constant segment respects it; equal neighbours merge, which is how the switching
  times are chosen) are continuous variables optimised by projected gradient ascent with
  gradients through the simulator (`jax.grad` of the criterion of `jax.jacfwd` Jacobians);
  the projection enforces the power range and the average-power cap exactly.

**Process noise.** For a `StochasticDevice` (a model with process noise, e.g. the `model`
of a `ProcessNoise` fit) the information of a run is the expected Fisher information of the
Kalman-filter likelihood that fit maximises (`greybox.stochastic._fisher`: the Gaussian
information of the readings' mean and covariance, exact for a linear device), so process
noise, which makes long runs less informative than output error would, is in every
criterion. `sigma` is then the model's measurement sd; per-run parameters are marginalised
the same way; pulse trains only (the multilevel gradient and `track_target` are output-error
only).

**Inverse design.** `track_target` finds a piecewise-constant laser waveform on a fixed
grid that makes the shuttle follow a target (a step to a stroke within a settling time),
by projected gradient descent through the simulator, and reports whether the target is met
in simulation and the response's band from the parameter uncertainty.

Impossible requests raise `ValueError` naming the option (infeasible constraints, a
target the laser cannot reach, a parameter of interest that no waveform of the family can
identify); nothing returns a silently poor design.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._estimate.identifiability import TINY, WEAK_SD
from greybox._estimate.prediction import Band, prediction_band, raw_draws
from greybox._model.device import check_method, with_camera
from greybox._model.freeparams import FreeParameter, as_leaves
from greybox._model.parameters import get_value, set_values
from greybox._model.waveforms import PiecewiseConstant, PulseTrain
from greybox._simulate.schedules import model_schedules, schedule_for, schedule_row
from greybox._simulate.simulate import as_arrays, observe_schedule, require_x64

CRITERIA = ("D", "A", "E")
FAMILIES = ("pulse_train", "multilevel")


# --------------------------------------------------------------------------- constraints


MAX_DESIGN_RUNS = 100  # runs chosen jointly (greedy + exchange: cost grows as runs^2)
MAX_DESIGN_FRAMES = 2e6  # frames of all runs: the sensitivities of every frame are held
MAX_DRAWS = 1000  # posterior draws of a Bayesian design (each one a full information matrix)

@dataclasses.dataclass(frozen=True)
class LabConstraints:
    """What the lab can do, in SI units.

    - `power_max_W`: highest laser power; `power_min_W`: lowest non-zero level (the laser can
      always be off).
    - `average_power_max_W`: cap on each run's mean power (energy / duration); None = no cap.
    - `min_pulse_s`: shortest pulse and shortest time between two edges.
    - `run_duration_s`: length of one run; `n_runs`: number of runs.
    - `fps`, `exposure_s`: camera frame rate and exposure (frames at (k + 1/2)/fps).
    - `lead_s`: laser-off time at the start of every run (the shuttle's rest position, which
      the fit uses to start each run's camera offset).
    """

    power_max_W: float
    run_duration_s: float
    n_runs: int = 1
    power_min_W: float = 0.0
    average_power_max_W: float | None = None
    min_pulse_s: float = 0.01
    fps: float = 30.0
    exposure_s: float = 0.010
    lead_s: float = 0.3

    def __post_init__(self):
        self.check()

    def check(self) -> None:
        """Raise ValueError naming the first infeasible or malformed constraint."""

        def bad(field, msg):
            raise ValueError(f"{field}: {msg}")

        for name in ("power_max_W", "run_duration_s", "min_pulse_s", "fps", "power_min_W",
                     "exposure_s", "lead_s"):  # fmt: skip
            v = getattr(self, name)
            if not (isinstance(v, (int, float, np.floating)) and math.isfinite(v)):
                bad(name, f"{v!r} is not a finite number")
        if not self.power_max_W > 0:
            bad("power_max_W", f"{self.power_max_W} W: the laser must be able to emit (> 0)")
        if not 0 <= self.power_min_W <= self.power_max_W:
            bad("power_min_W", f"{self.power_min_W} W must lie in [0, power_max_W]")
        if int(self.n_runs) != self.n_runs or self.n_runs < 1:
            bad("n_runs", f"{self.n_runs!r} must be a whole number >= 1")
        if self.n_runs > MAX_DESIGN_RUNS:  # each run is one more exchange pass over all runs
            bad("n_runs", f"{self.n_runs} runs; design at most {MAX_DESIGN_RUNS} at a time")
        if not self.fps > 0:
            bad("fps", f"{self.fps} must be > 0 frames/s")
        if not 0 <= self.exposure_s <= 1.0 / self.fps:
            bad("exposure_s", f"{self.exposure_s} s must lie in [0, 1/fps = {1 / self.fps:g} s]")
        if not self.min_pulse_s > 0:
            bad("min_pulse_s", f"{self.min_pulse_s} s must be > 0")
        if not self.lead_s >= 3.0 / self.fps:
            bad("lead_s", f"{self.lead_s} s leaves fewer than 3 laser-off frames at the start")
        frames = self.run_duration_s * self.fps * self.n_runs
        if frames > MAX_DESIGN_FRAMES:
            bad(
                "run_duration_s",
                f"{self.n_runs} runs x {self.run_duration_s:g} s x {self.fps:g} frames/s = "
                f"{frames:.3g} frames to evaluate per candidate; at most {MAX_DESIGN_FRAMES:g} "
                "(shorter or fewer runs)",
            )
        if not self.run_duration_s > self.lead_s + 2 * self.min_pulse_s:
            bad(
                "run_duration_s",
                f"{self.run_duration_s} s leaves no room for one pulse after the "
                f"{self.lead_s} s lead (minimum pulse {self.min_pulse_s} s); make runs longer",
            )
        cap = self.average_power_max_W
        if cap is not None:
            if not (math.isfinite(cap) and cap > 0):
                bad("average_power_max_W", f"{cap!r} W: no light at all could be delivered")
            if self.power_min_W * self.min_pulse_s > cap * self.run_duration_s:
                bad(
                    "average_power_max_W",
                    f"{cap} W cannot hold even one {self.min_pulse_s} s pulse at the minimum "
                    f"power {self.power_min_W} W (energy {self.power_min_W * self.min_pulse_s:g}"
                    f" J > {cap * self.run_duration_s:g} J per run)",
                )

    def frame_times(self) -> np.ndarray:
        """Nominal frame times of one run [s]."""
        n = int(math.floor(self.run_duration_s * self.fps + 1e-9))
        return (np.arange(n) + 0.5) / self.fps

    @property
    def total_duration_s(self) -> float:
        return self.run_duration_s * self.n_runs


# ---------------------------------------------------------------------- information


@dataclasses.dataclass(frozen=True)
class DesignProblem:
    """A device model and what is to be measured. Build with `design_problem`."""

    model: object  # camera already set to the lab's exposure
    free: tuple  # FreeParameter, shared first then per-run (as fit orders them)
    raw_shared: np.ndarray  # where the information is evaluated
    raw_per: np.ndarray  # per-run nuisance raw values (one row, used for every run)
    interest: tuple  # indices into the shared parameters
    sigma: np.ndarray  # (n_y,) noise sd [SI]
    prior_information: np.ndarray  # (ns, ns) from log-normal priors (+ existing data)
    draws: np.ndarray  # (D, ns) raw draws for the Bayesian criterion (D = 0: local design)
    method: str

    @property
    def shared(self) -> tuple:
        return tuple(p for p in self.free if not p.per_experiment)

    @property
    def per_run(self) -> tuple:
        return tuple(p for p in self.free if p.per_experiment)

    @property
    def interest_paths(self) -> tuple:
        return tuple(self.shared[k].path for k in self.interest)


def design_problem(
    model,
    free: Sequence[FreeParameter],
    interest: Sequence[str],
    sigma=None,
    *,
    raw=None,
    covariance_raw=None,
    include_existing: bool = False,
    n_draws: int = 0,
    seed: int = 0,
    exposure_s: float | None = None,
    method: str | None = None,
) -> DesignProblem:
    """What to design for.

    **Arguments:**
    - `model`, `free`: the device at nominal (or fitted) values and its free parameters
      (shared and per-run, as for `greybox.fit`); priors in `free` add information.
    - `interest`: paths of the shared parameters whose standard errors the design shrinks
      (the other shared ones are nuisance parameters, marginalised).
    - `sigma`: camera noise sd per output [SI]; None for a `StochasticDevice` (process
      noise: its measurement sd, and the information is the Kalman-filter likelihood's).
    - `raw`, `covariance_raw`: a fitted posterior (`FitResult` or `load_params` fields);
      the information is evaluated at `raw`, and with `n_draws > 0` averaged over draws from
      the covariance (Bayesian design). `include_existing=True` adds the information the
      fitted data already hold (the inverse covariance) to every design.
    - `exposure_s`: camera exposure of the new runs (None: the model's).

    **Raises:** ValueError naming `interest` for a path that is not a shared free parameter.
    """
    require_x64("design_problem")
    free = tuple(free)
    if exposure_s is not None:
        model = with_camera(model, exposure_s=exposure_s)
    method = check_method(model.device if _stochastic(model) else model, method)
    shared = [p for p in free if not p.per_experiment]
    per_run = [p for p in free if p.per_experiment]
    free = tuple(shared + per_run)
    paths = [p.path for p in shared]
    interest = tuple(interest)
    if not interest:
        raise ValueError("interest: name at least one parameter to measure")
    idx = []
    for path in interest:
        if path not in paths:
            raise ValueError(
                f"interest: {path!r} is not a shared free parameter ({paths}); free it "
                "(add it to the free list) or choose another"
            )
        idx.append(paths.index(path))
    if sigma is None and _stochastic(model):  # process noise: the model's measurement sd
        sigma = np.asarray(model.measurement.values, dtype=float)
    sig = np.atleast_1d(np.asarray(sigma, dtype=float))
    if not np.all(sig > 0):
        raise ValueError("sigma: the noise sd must be > 0 (SI units of the output)")
    ns = len(shared)
    if raw is None:
        raw_shared = np.array([float(p.to_raw(get_value(model, p.path))) for p in shared])
    else:
        raw_shared = np.asarray(raw, dtype=float)[:ns]
        model = set_values(model, paths, [p.to_value(r) for p, r in zip(shared, raw_shared)])
    raw_per = np.array([float(p.to_raw(get_value(model, p.path))) for p in per_run])
    prior = np.zeros((ns, ns))
    for k, p in enumerate(shared):
        if p.has_prior:
            g = jax.grad(lambda r, p=p: p.prior_residual(p.to_value(r)))(raw_shared[k])
            prior[k, k] += float(g) ** 2
    if include_existing:
        if covariance_raw is None:
            raise ValueError("include_existing: needs covariance_raw from a fit")
        cov = np.asarray(covariance_raw, dtype=float)[:ns, :ns]
        if not np.all(np.isfinite(cov)):
            raise ValueError("covariance_raw: not finite (a parameter was not identified)")
        prior = prior + np.linalg.pinv((cov + cov.T) / 2, hermitian=True)
    draws = np.zeros((0, ns))
    if n_draws:
        if not 0 < n_draws <= MAX_DRAWS:
            raise ValueError(f"n_draws: {n_draws} draws; give 1 to {MAX_DRAWS}")
        if covariance_raw is None:
            raise ValueError("n_draws: a Bayesian design needs covariance_raw (a fitted posterior)")
        draws = raw_draws(np.append(raw_shared, []), covariance_raw, shared, n_draws, seed=seed)
    return DesignProblem(
        model=as_arrays(model),
        free=free,
        raw_shared=raw_shared,
        raw_per=raw_per,
        interest=tuple(idx),
        sigma=sig,
        prior_information=prior,
        draws=draws,
        method=method,
    )


def _run_jacobian(model, shared, per_run, raw_shared, raw_per, sched, method):
    """d(camera readings)/d(raw shared, raw per-run) for one schedule row: (N, n_y, ns + np)."""

    def readings(r):
        ns = len(shared)
        m = set_values(
            model, [p.path for p in shared], [p.to_value(r[i]) for i, p in enumerate(shared)]
        )
        m = set_values(
            m, [p.path for p in per_run], [p.to_value(r[ns + j]) for j, p in enumerate(per_run)]
        )
        return observe_schedule(m, sched, method=method)[0]

    return jax.jacfwd(readings)(jnp.concatenate([raw_shared, raw_per]))


def _marginal(jac, weight, sigma, ns):
    """Shared-parameter information of one run with its per-run parameters marginalised.

    `jac` (N, n_y, P), `weight` (N,) 1 for real frames, 0 for padding."""
    j = (jac * (weight[:, None, None] / sigma[None, :, None])).reshape(-1, jac.shape[-1])
    return _schur(j.T @ j, ns)


def _schur(f, ns):
    """The first `ns` parameters' information with the others marginalised (Schur)."""
    a, b, d = f[:ns, :ns], f[:ns, ns:], f[ns:, ns:]
    if d.shape[0] == 0:
        return a
    return a - b @ jnp.linalg.solve(d, b.T)


def _interest_info(f_shared, interest):
    """Information of the parameters of interest, other shared ones marginalised."""
    ns = f_shared.shape[-1]
    rest = [k for k in range(ns) if k not in interest]
    interest = list(interest)
    fi = f_shared[np.ix_(interest, interest)]
    if not rest:
        return fi
    fr = f_shared[np.ix_(rest, rest)]
    fb = f_shared[np.ix_(interest, rest)]
    return fi - fb @ jnp.linalg.solve(fr, fb.T)


def log_criterion(m, kind: str = "D"):
    """log of the design criterion of information matrix `m` (larger is better; jnp)."""
    m = (m + m.T) / 2
    p = m.shape[0]
    if kind == "D":
        return jnp.linalg.slogdet(m)[1] / p
    if kind == "A":
        return -jnp.log(jnp.trace(jnp.linalg.inv(m)))
    if kind == "E":
        return jnp.log(jnp.linalg.eigvalsh(m)[0])
    raise ValueError(f"criterion: {kind!r} is unknown; use one of {CRITERIA}")


@jit
def _batch_information(model, shared, per_run, raw_shared, raw_per, sched, weight, sigma, method):
    """(R, ns, ns) marginal information of a batch of padded runs at one parameter point."""
    ns = len(shared)

    def one(row, w):
        jac = _run_jacobian(model, shared, per_run, raw_shared, raw_per, row, method)
        return _marginal(jac, w, sigma, ns)

    return jax.vmap(one)(sched, weight)


def _schedules(problem: DesignProblem, waveforms, t_list):
    runs = [(w, t, 0.0) for w, t in zip(waveforms, t_list, strict=True)]
    sched = model_schedules(problem.model, runs)
    n_pad = sched["t_s"].shape[1]
    weight = np.zeros((len(runs), n_pad))
    for i, t in enumerate(t_list):
        weight[i, : np.size(t)] = 1.0
    return sched, jnp.asarray(weight)


def run_information(problem: DesignProblem, waveforms, t_s, *, chunk: int = 64) -> np.ndarray:
    """Marginal information of the shared raw parameters from each run (per-run nuisance
    parameters profiled out): (D, R, ns, ns) for the D parameter points (the evaluation point
    only, D = 1, unless the problem holds posterior draws).

    `waveforms`: inputs in SI; `t_s`: one array of frame times for all runs or one per run.
    """
    waveforms = list(waveforms)
    t_list = t_s if isinstance(t_s, (list, tuple)) else [np.asarray(t_s)] * len(waveforms)
    points = problem.draws if problem.draws.shape[0] else problem.raw_shared[None]
    if _stochastic(problem.model):
        return _process_information(problem, points, waveforms, t_list)
    # the parameters' numbers as inputs: a design of other bounds compiles nothing new
    shared, per_run = as_leaves(problem.shared), as_leaves(problem.per_run)
    out = []
    for start in range(0, len(waveforms), chunk):
        sched, weight = _schedules(
            problem, waveforms[start : start + chunk], t_list[start : start + chunk]
        )
        out.append(
            np.stack(
                [
                    np.asarray(
                        _batch_information(
                            problem.model,
                            shared,
                            per_run,
                            jnp.asarray(r),
                            jnp.asarray(problem.raw_per),
                            sched,
                            weight,
                            jnp.asarray(problem.sigma),
                            problem.method,
                        )
                    )
                    for r in points
                ]
            )
        )
    return np.concatenate(out, axis=1)


def _stochastic(model) -> bool:
    from greybox.stochastic._sde_device import StochasticDevice

    return isinstance(model, StochasticDevice)


def _process_information(problem: DesignProblem, points, waveforms, t_list) -> np.ndarray:
    """`run_information` for a process-noise model: the expected information of the
    Kalman-filter likelihood per run (`greybox.stochastic._fisher`), per-run parameters
    marginalised."""
    from greybox.stochastic._fisher import expected_information

    ns = len(problem.shared)
    free = problem.shared + problem.per_run
    return np.stack(
        [
            np.stack(
                [
                    np.asarray(
                        _schur(
                            jnp.asarray(
                                expected_information(
                                    problem.model, free, np.append(r, problem.raw_per), w, t
                                )
                            ),
                            ns,
                        )
                    )
                    for w, t in zip(waveforms, t_list, strict=True)
                ]
            )
            for r in points
        ]
    )


def design_score(problem: DesignProblem, total_info: np.ndarray, kind: str = "D") -> float:
    """Criterion of summed run information `total_info` (D, ns, ns) incl. prior information:
    the mean log-criterion over parameter points (the Bayesian criterion when D > 1)."""
    vals = []
    for f in np.asarray(total_info):
        m = np.asarray(_interest_info(jnp.asarray(f + problem.prior_information), problem.interest))
        vals.append(float(log_criterion(jnp.asarray(m), kind)))
    return float(np.mean(vals))


def interest_information(problem: DesignProblem, total_info: np.ndarray) -> np.ndarray:
    """(p, p) information of the parameters of interest at the evaluation point (data +
    priors), other shared parameters marginalised. `total_info`: (ns, ns) summed over runs."""
    f = np.asarray(total_info) + problem.prior_information
    return np.asarray(_interest_info(jnp.asarray(f), problem.interest))


def design_standard_errors(problem: DesignProblem, total_info: np.ndarray) -> dict:
    """{path: predicted standard error in SI} of the parameters of interest (delta method at
    the evaluation point; NaN where the information is singular)."""
    m = interest_information(problem, total_info)
    vals, vecs = np.linalg.eigh((m + m.T) / 2)
    out = {}
    if vals.max() <= 0 or vals.min() <= vals.max() * TINY:
        cov = np.full_like(m, np.nan)
    else:
        cov = (vecs / vals) @ vecs.T
    for i, k in enumerate(problem.interest):
        p = problem.shared[k]
        out[p.path] = abs(p.value_derivative(problem.raw_shared[k])) * math.sqrt(cov[i, i])
    return out


# --------------------------------------------------------------------------- designs


@dataclasses.dataclass(frozen=True)
class DesignedRun:
    """One run of a design: its name, the waveform (SI) and its description in the
    experiment loader's waveform language (power in mW, times in ms or s)."""

    name: str
    waveform: PiecewiseConstant
    description: dict
    family: str

    @property
    def energy_J(self) -> float:
        return float(self.waveform.mean()) * self.waveform.duration_s

    @property
    def peak_W(self) -> float:
        return float(np.max(self.waveform.values))


@dataclasses.dataclass(frozen=True)
class Design:
    """A proposed set of runs and what it is predicted to achieve.

    `information` is the summed marginal information of the shared raw parameters (ns, ns)
    at the evaluation point; `score` the (mean log) criterion; `standard_errors` {path: SE
    in SI} for the parameters of interest; `verdict` says whether every parameter of interest
    is identified (data-only raw sd < 0.5)."""

    runs: tuple
    criterion: str
    bayesian: bool
    score: float
    information: np.ndarray
    standard_errors: dict
    constraints: LabConstraints
    verdict: str

    @property
    def energy_J(self) -> float:
        return sum(r.energy_J for r in self.runs)

    @property
    def duration_s(self) -> float:
        return sum(r.waveform.duration_s for r in self.runs)


def evaluate_design(
    problem: DesignProblem,
    runs: Sequence[DesignedRun],
    constraints: LabConstraints,
    *,
    criterion: str = "D",
    t_s=None,
) -> Design:
    """Score given runs (e.g. a baseline) with the problem's information and criterion.

    `t_s`: frame times (one array for all runs or one per run); default the constraints'."""
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: {criterion!r} is unknown; use one of {CRITERIA}")
    runs = tuple(runs)
    if t_s is None:
        t_s = [_frames_for(r.waveform, constraints) for r in runs]
    info = run_information(problem, [r.waveform for r in runs], t_s)
    return _finish(problem, runs, info.sum(axis=1), constraints, criterion)


def _frames_for(wave: PiecewiseConstant, c: LabConstraints) -> np.ndarray:
    n = int(math.floor(wave.end_s * c.fps + 1e-9))
    return (np.arange(n) + 0.5) / c.fps


def _finish(problem, runs, total, constraints, criterion) -> Design:
    score = design_score(problem, total, criterion)
    point = total[0] if not problem.draws.shape[0] else run_point_info(problem, runs, constraints)
    se = design_standard_errors(problem, point)
    # data-only identifiability of each parameter of interest (priors left out)
    m = np.asarray(_interest_info(jnp.asarray(point), problem.interest))
    vals = np.linalg.eigvalsh((m + m.T) / 2)
    bad = []
    if vals.min() <= max(vals.max(), 1e-300) * TINY:
        bad = list(problem.interest_paths)
    else:
        sd = np.sqrt(np.diag(np.linalg.inv(m)))
        bad = [problem.interest_paths[i] for i in range(sd.size) if not sd[i] < WEAK_SD]
    verdict = (
        "every parameter of interest is identified by these runs"
        if not bad
        else f"not identifiable from these runs: {', '.join(bad)}"
    )
    return Design(
        runs=tuple(runs),
        criterion=criterion,
        bayesian=bool(problem.draws.shape[0]),
        score=score,
        information=np.asarray(point),
        standard_errors=se,
        constraints=constraints,
        verdict=verdict,
    )


def run_point_info(problem, runs, constraints) -> np.ndarray:
    """Summed information at the evaluation point only (ignores the posterior draws)."""
    local = dataclasses.replace(problem, draws=np.zeros((0, problem.raw_shared.size)))
    t = [_frames_for(r.waveform, constraints) for r in runs]
    return run_information(local, [r.waveform for r in runs], t).sum(axis=1)[0]


def pulse_train_candidates(
    c: LabConstraints, *, n_periods: int = 14, duties: Sequence[float] | None = None
) -> list[DesignedRun]:
    """Feasible pulse trains for one run: log-spaced periods (whole ms) from 2 x the minimum
    pulse to half the run, duties in 5 % steps; power at the largest value the range and the
    average cap allow. Each fills the run after the lead; the rest is a laser-off tail."""
    span = c.run_duration_s - c.lead_s
    p_lo = max(2 * c.min_pulse_s, 1e-3)
    periods = np.unique(np.round(np.geomspace(p_lo, span / 2, n_periods) * 1e3)) / 1e3
    duties = np.arange(0.05, 0.951, 0.05) if duties is None else np.asarray(duties, dtype=float)
    out = []
    for period in periods:
        if period < p_lo - 1e-12:
            continue
        n = int(math.floor(span / period + 1e-9))
        if n < 1:
            continue
        for duty in duties:
            duty = round(float(duty), 4)
            on, off = duty * period, (1 - duty) * period
            if on < c.min_pulse_s - 1e-12 or off < c.min_pulse_s - 1e-12:
                continue
            power = c.power_max_W
            if c.average_power_max_W is not None:
                power = min(power, c.average_power_max_W * c.run_duration_s / (n * on))
            power = math.floor(power * 1e5) / 1e5  # 0.01 mW resolution, rounded down
            if power <= 0 or power < c.power_min_W:
                continue
            tail = c.run_duration_s - c.lead_s - n * period
            desc = {
                "type": "pulse_train",
                "power_mW": round(power * 1e3, 2),
                "period_ms": round(float(period) * 1e3, 3),
                "duty": duty,
                "n_pulses": n,
                "delay_ms": round(c.lead_s * 1e3, 3),
                "tail_ms": round(float(max(tail, 0.0)) * 1e3, 3),
            }
            wave = PulseTrain(
                desc["power_mW"] * 1e-3,
                desc["period_ms"] * 1e-3,
                duty,
                n,
                delay_s=desc["delay_ms"] * 1e-3,
                tail_s=desc["tail_ms"] * 1e-3,
            ).to_piecewise()
            name = f"pt_{desc['power_mW']:g}mW_{desc['period_ms']:g}ms_d{int(round(duty * 100))}"
            out.append(DesignedRun(name, wave, desc, "pulse_train"))
    if not out:
        raise ValueError(
            "min_pulse_s: no pulse train fits the constraints (minimum pulse, power range and "
            "average-power cap); relax one of them"
        )
    return out


def habitual_baseline(c: LabConstraints, period_s: float = 0.4) -> list[DesignedRun]:
    """The usual experiment to compare a design with: `n_runs` 50 % duty pulse trains of
    `period_s` at the highest power the range and the average cap allow."""
    cands = pulse_train_candidates(c, n_periods=1, duties=[0.5])
    span = c.run_duration_s - c.lead_s
    period = max(min(period_s, span), 2 * c.min_pulse_s)
    n = max(int(math.floor(span / period + 1e-9)), 1)
    power = c.power_max_W
    if c.average_power_max_W is not None:
        power = min(power, c.average_power_max_W * c.run_duration_s / (n * 0.5 * period))
    power = math.floor(power * 1e5) / 1e5
    if power <= 0:
        return cands[:1] * c.n_runs
    desc = {
        "type": "pulse_train",
        "power_mW": round(power * 1e3, 2),
        "period_ms": round(period * 1e3, 3),
        "duty": 0.5,
        "n_pulses": n,
        "delay_ms": round(c.lead_s * 1e3, 3),
        "tail_ms": round(max(span - n * period, 0.0) * 1e3, 3),
    }
    wave = PulseTrain(
        desc["power_mW"] * 1e-3, period, 0.5, n, delay_s=c.lead_s, tail_s=desc["tail_ms"] * 1e-3
    ).to_piecewise()
    return [DesignedRun(f"b{i + 1}_50pct", wave, desc, "pulse_train") for i in range(c.n_runs)]


def _select(problem, infos, n_runs, kind, fixed=None):
    """Greedy then exchange selection (with repetition) of n_runs candidate indices that
    maximise the criterion of the summed information. `infos`: (D, C, ns, ns)."""
    base = np.zeros_like(infos[:, 0]) if fixed is None else fixed
    ridge = 1e-12 * np.eye(infos.shape[-1]) * max(np.abs(infos).max(), 1e-300)

    def score(chosen):
        total = base + infos[:, chosen].sum(axis=1) + ridge
        return _score_fast(problem, total, kind)

    chosen: list[int] = []
    for _ in range(n_runs):
        best = max(range(infos.shape[1]), key=lambda c: score(chosen + [c]))
        chosen.append(best)
    for _ in range(3):  # exchange passes
        improved = False
        for slot in range(n_runs):
            current = score(chosen)
            for cand in range(infos.shape[1]):
                trial = chosen[:slot] + [cand] + chosen[slot + 1 :]
                s = score(trial)
                if s > current + 1e-12:
                    chosen, current, improved = trial, s, True
        if not improved:
            break
    return chosen


def _score_fast(problem, total, kind):
    """numpy version of `design_score` (the selection calls it thousands of times)."""
    vals = []
    for f in total:
        f = f + problem.prior_information
        ii = list(problem.interest)
        rest = [k for k in range(f.shape[0]) if k not in ii]
        m = f[np.ix_(ii, ii)]
        if rest:
            b = f[np.ix_(ii, rest)]
            m = m - b @ np.linalg.lstsq(f[np.ix_(rest, rest)], b.T, rcond=None)[0]
        m = (m + m.T) / 2
        ev = np.linalg.eigvalsh(m)
        if ev[0] <= 0:
            return -np.inf
        if kind == "D":
            vals.append(np.sum(np.log(ev)) / ev.size)
        elif kind == "A":
            vals.append(-np.log(np.sum(1.0 / ev)))
        else:
            vals.append(np.log(ev[0]))
    return float(np.mean(vals))


def design_experiment(
    problem: DesignProblem,
    constraints: LabConstraints,
    *,
    family: str = "pulse_train",
    criterion: str = "D",
    n_periods: int = 14,
    duties: Sequence[float] | None = None,
    hold_s: float | None = None,
    n_iter: int = 60,
    seed: int = 0,
) -> Design:
    """Choose `constraints.n_runs` runs maximising `criterion` of the information of the
    parameters of interest (see the module docstring for the families and how each is
    optimised).

    **Raises:** ValueError naming `interest` when no waveform of the family identifies a
    parameter of interest (singular information for every candidate union), naming the
    constraint when nothing is feasible.
    """
    if criterion not in CRITERIA:
        raise ValueError(f"criterion: {criterion!r} is unknown; use one of {CRITERIA}")
    if family not in FAMILIES:
        raise ValueError(f"family: {family!r} is unknown; use one of {FAMILIES}")
    c = constraints
    if family == "pulse_train":
        cands = pulse_train_candidates(c, n_periods=n_periods, duties=duties)
        infos = run_information(problem, [r.waveform for r in cands], c.frame_times())
        chosen = _select(problem, infos, c.n_runs, criterion)
        runs = [cands[k] for k in chosen]
        runs = [dataclasses.replace(r, name=f"d{i + 1}_{r.name}") for i, r in enumerate(runs)]
        total = infos[:, chosen].sum(axis=1)
    else:
        if _stochastic(problem.model):
            raise ValueError(
                f"family: {family!r} optimises levels by gradients of the output-error "
                "information; a process-noise model designs pulse trains (family='pulse_train')"
            )
        # start from the best pulse-train union sampled on the hold grid, then refine by
        # projected gradient ascent (a random start converges far more slowly)
        start = design_experiment(
            problem,
            c,
            family="pulse_train",
            criterion=criterion,
            n_periods=n_periods,
            duties=duties,
        )
        runs, total = _design_multilevel(
            problem, c, criterion, hold_s, n_iter, seed, [r.waveform for r in start.runs]
        )
    design = _finish(problem, tuple(runs), total, c, criterion)
    _check_identified(problem, design, family)
    return design


def _check_identified(problem, design: Design, family: str) -> None:
    m = np.asarray(_interest_info(jnp.asarray(design.information), problem.interest))
    vals = np.linalg.eigvalsh((m + m.T) / 2)
    if vals.min() <= max(vals.max(), 1e-300) * 1e-8 or "not identifiable" in design.verdict:
        # which parameters: those with weight on the weakest direction
        _, vecs = np.linalg.eigh((m + m.T) / 2)
        names = [problem.interest_paths[i] for i in np.flatnonzero(np.abs(vecs[:, 0]) > 0.1)]
        raise ValueError(
            f"interest: no {family} design within these constraints identifies "
            f"{', '.join(names) or 'the parameters of interest'} from the camera data (the "
            "information is singular or the data-only sd exceeds "
            f"{WEAK_SD} in raw units: {design.verdict}); the parameter enters only through a "
            "product with another free parameter or is fixed by its prior; free one of them "
            "only, or add a prior"
        )


# --------------------------------------------------------- multilevel (gradient) family


def _hold_grid(c: LabConstraints, hold_s: float | None):
    h = c.min_pulse_s if hold_s is None else float(hold_s)
    if h < c.min_pulse_s - 1e-12:
        raise ValueError(f"hold_s: {h} s is shorter than min_pulse_s {c.min_pulse_s} s")
    k = int(math.floor((c.run_duration_s - c.lead_s) / h + 1e-9))
    if k < 1:
        raise ValueError("hold_s: longer than the run after its lead; shorten it")
    return h, c.lead_s + h * np.arange(k)


def _template(times, end_s):
    """A waveform with an edge at every hold boundary (so the schedule grid has them all)."""
    vals = 1.0 + (np.arange(times.size) % 2)
    if times[0] <= 0:
        return PiecewiseConstant(times, vals, end_s)
    return PiecewiseConstant(np.concatenate([[0.0], times]), np.concatenate([[0.0], vals]), end_s)


def _segment_index(row, times):
    """Index of the hold level in force on each grid interval of a schedule row (its
    intervals before the padding's empty ones; K = the 'off' slot)."""
    dt = np.asarray(row["dt"])
    dt = dt[: np.count_nonzero(dt)]
    left = float(row["t_start"]) + np.concatenate([[0.0], np.cumsum(dt)[:-1]])
    mid = left + dt / 2
    idx = np.searchsorted(times, mid, side="right") - 1
    return np.where(idx < 0, times.size, idx)


def _hold_mean(wave: PiecewiseConstant, a: float, b: float) -> float:
    """Mean level of `wave` over [a, b)."""
    ts = np.unique(np.concatenate([[a, b], wave.times_s[(wave.times_s > a) & (wave.times_s < b)]]))
    widths = np.diff(ts)
    return float(np.sum(np.asarray(wave(ts[:-1])).reshape(-1) * widths) / (b - a))


def projected_adam(value_and_grad, x, project, *, step, decay, n_iter, maximise):
    """Projected gradient steps scaled by Adam's moment estimates (beta 0.9, 0.999): from
    `x`, `n_iter` steps of size `step * decay**it` up (`maximise`) or down the gradient,
    each projected back onto the feasible set by `project`. Returns the best finite
    iterate seen (the objective is not monotone under projection)."""
    m1, m2 = np.zeros_like(x), np.zeros_like(x)
    best_x, best_v = x, (-np.inf if maximise else np.inf)
    for it in range(n_iter):
        v, g = value_and_grad(jnp.asarray(x))
        v, g = float(v), np.asarray(g)
        if np.isfinite(v) and (v > best_v if maximise else v < best_v):
            best_v, best_x = v, x
        m1 = 0.9 * m1 + 0.1 * g
        m2 = 0.999 * m2 + 0.001 * g**2
        d = (m1 / (1 - 0.9 ** (it + 1))) / (np.sqrt(m2 / (1 - 0.999 ** (it + 1))) + 1e-30)
        delta = step * d * decay**it
        x = project(x + delta if maximise else x - delta)
    return best_x


def project_levels(x, lo, hi, mean_max):
    """Euclidean projection of levels `x` (..., K) onto {lo <= x <= hi, mean(x) <= mean_max},
    with `lo` applied to non-zero levels only through the clip (lo = 0 for the off state)."""
    x = np.asarray(x, dtype=float)
    y = np.clip(x, lo, hi)
    if mean_max is None:
        return y
    out = y.copy()
    for i in np.ndindex(x.shape[:-1]):
        if out[i].mean() <= mean_max:
            continue
        a, b = 0.0, float(np.max(x[i]) - lo)
        for _ in range(80):  # bisection on the shift
            m = (a + b) / 2
            if np.clip(x[i] - m, lo, hi).mean() > mean_max:
                a = m
            else:
                b = m
        out[i] = np.clip(x[i] - b, lo, hi)
    return out


@jit
def _levels_value_and_grad(
    levels, model, shared, per_run, raw_per, sched, seg_pad, weight, sigma, points, prior,
    interest, method, kind,
):  # fmt: skip
    """(criterion, its gradient) of a multilevel design's hold `levels` (R, K): the runs'
    marginal information summed with the prior's, averaged over the parameter `points`. One
    compiled function per structure: the device's values, the parameters' numbers and the
    points are its inputs, so the design of another device compiles nothing new."""
    ns = len(shared)

    def objective(lv):
        u = jnp.concatenate([lv, jnp.zeros((lv.shape[0], 1))], axis=1)[:, seg_pad]

        def at(r):
            def one(row, uu, w):
                row = dict(row, u_grid=uu[:, None])
                jac = _run_jacobian(model, shared, per_run, r, raw_per, row, method)
                return _marginal(jac, w, sigma, ns)

            f = jax.vmap(one)(sched, u, weight).sum(axis=0) + prior
            return log_criterion(_interest_info(f, interest), kind)

        return jnp.mean(jax.vmap(at)(points))

    return jax.value_and_grad(objective)(levels)


def _design_multilevel(problem, c: LabConstraints, kind, hold_s, n_iter, seed, starts=None):
    h, times = _hold_grid(c, hold_s)
    k = times.size
    t = c.frame_times()
    template = _template(times, c.run_duration_s)
    one = schedule_for(problem.model, template, t, on_device=False)  # every run: this one
    seg = _segment_index({key: v[0] for key, v in one.items()}, times)
    sched = jax.tree.map(lambda x: np.repeat(x, c.n_runs, axis=0), one)
    n_int = sched["dt"].shape[1]
    seg_pad = np.full(n_int, k)
    seg_pad[: seg.size] = seg
    n_pad = sched["t_s"].shape[1]
    weight = np.zeros((c.n_runs, n_pad))
    weight[:, : t.size] = 1.0
    mean_max = None
    if c.average_power_max_W is not None:
        mean_max = c.average_power_max_W * c.run_duration_s / (k * h)
    points = problem.draws if problem.draws.shape[0] else problem.raw_shared[None]
    fixed = (
        problem.model,
        as_leaves(problem.shared),
        as_leaves(problem.per_run),
        jnp.asarray(problem.raw_per),
        sched,
        jnp.asarray(seg_pad),
        jnp.asarray(weight),
        jnp.asarray(problem.sigma),
        jnp.asarray(points),
        jnp.asarray(problem.prior_information),
        tuple(problem.interest),
        problem.method,
        kind,
    )

    def value_and_grad(levels):
        return _levels_value_and_grad(jnp.asarray(levels), *fixed)

    rng = np.random.default_rng(seed)
    lo, hi = c.power_min_W, c.power_max_W
    if starts is None:  # random binary levels at full power
        x = rng.choice([0.0, 1.0], size=(c.n_runs, k)) * hi
    else:  # given waveforms, averaged over each hold
        x = np.array([[_hold_mean(w, a, a + h) for a in times] for w in starts])
    x = project_levels(x, lo, hi, mean_max)
    best_x = projected_adam(
        value_and_grad,
        x,
        lambda z: project_levels(z, lo, hi, mean_max),
        step=0.03 * (hi - lo),
        decay=0.98,
        n_iter=n_iter,
        maximise=True,
    )
    # lab resolution: 0.01 mW, rounded so the average cap still holds
    x = np.floor(np.asarray(best_x) * 1e5) / 1e5
    x = np.where(x < lo, 0.0, x) if lo > 0 else x
    runs = []
    for i in range(c.n_runs):
        levels = np.concatenate([[0.0], x[i]])
        tt = np.concatenate([[0.0], times])
        keep = np.append(True, np.diff(levels) != 0)
        wave = PiecewiseConstant(tt[keep], levels[keep], c.run_duration_s)
        desc = {
            "type": "steps",
            "times_s": [round(float(v), 6) for v in tt[keep]],
            "power_mW": [round(float(v) * 1e3, 2) for v in levels[keep]],
            "end_s": round(c.run_duration_s, 6),
        }
        runs.append(DesignedRun(f"d{i + 1}_multilevel", wave, desc, "multilevel"))
    total = run_information(problem, [r.waveform for r in runs], t).sum(axis=1)
    return runs, total


# ------------------------------------------------------------------ report and files


def comparison_table(problem: DesignProblem, design: Design, baseline: Design | None) -> list:
    """Rows {path, unit, value, se_design, se_baseline, ratio} (SI; ratio = baseline SE /
    design SE, > 1 means the design measures the parameter better)."""
    rows = []
    for k in problem.interest:
        p = problem.shared[k]
        se_d = design.standard_errors[p.path]
        se_b = baseline.standard_errors[p.path] if baseline is not None else float("nan")
        rows.append(
            {
                "path": p.path,
                "unit": p.unit,
                "value": float(p.to_value(problem.raw_shared[k])),
                "se_design": se_d,
                "se_baseline": se_b,
                "ratio": se_b / se_d if baseline is not None else float("nan"),
            }
        )
    return rows


def det_gain(problem: DesignProblem, design: Design, baseline: Design) -> float:
    """det(M_design)^(1/p) / det(M_baseline)^(1/p) of the interest information."""
    a = interest_information(problem, design.information)
    b = interest_information(problem, baseline.information)
    p = a.shape[0]
    return float(np.exp((np.linalg.slogdet(a)[1] - np.linalg.slogdet(b)[1]) / p))


def format_design_table(rows: list, *, design_label="design", baseline_label="baseline") -> str:
    """Plain-text table of `comparison_table` rows."""
    head = f"{'parameter':<28} {'value':>11} {design_label + ' SE':>14} "
    head += f"{baseline_label + ' SE':>14} {'SE ratio':>9}"
    lines = [head, "-" * len(head)]
    for r in rows:
        lines.append(
            f"{r['path'] + ' [' + r['unit'] + ']':<28} {r['value']:>11.5g} {r['se_design']:>14.4g} "
            f"{r['se_baseline']:>14.4g} {r['ratio']:>9.3g}"
        )
    return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class TrackingDesign:
    """A waveform that makes the shuttle follow a target, and how well it does in simulation.

    - `waveform`: laser power (SI) on the hold grid; `description`: loader "steps" table.
    - `t_s`, `response`, `target`: dense simulation of the shuttle (m, no camera averaging)
      and the target at those times; `settled`: mask of the times the target must hold.
    - `max_error`: largest |response - target| over `settled` [m]; `tolerance` [m]; `met`.
    - `band`: the response's 95 % band from the parameter uncertainty (None without a
      covariance).
    """

    waveform: PiecewiseConstant
    description: dict
    t_s: np.ndarray
    response: np.ndarray
    target: np.ndarray
    settled: np.ndarray
    max_error: float
    tolerance: float
    met: bool
    average_power_W: float
    band: Band | None
    iterations: int


def _steady_output(model, power_W):
    """Steady-state output [m] of a linear device at constant input `power_W`."""
    a, b = model.linear_dynamics()
    x = -jnp.linalg.solve(a, b * power_W)[:, 0]
    return float(model.output(x)[0])


def track_target(
    model,
    *,
    stroke_m: float,
    step_time_s: float,
    settling_s: float,
    duration_s: float,
    power_max_W: float,
    average_power_max_W: float | None = None,
    hold_s: float = 0.005,
    tolerance: float = 0.02,
    dt_s: float = 0.001,
    n_iter: int = 400,
    free=None,
    raw=None,
    covariance_raw=None,
) -> TrackingDesign:
    """Laser waveform (levels on a `hold_s` grid in [0, `power_max_W`], mean <= the average
    cap) that steps the shuttle from rest to `stroke_m` at `step_time_s`, settled within
    `settling_s` and held to `duration_s` within `tolerance` x stroke.

    Optimised by projected gradient descent (Adam-scaled steps, exact projection onto the
    power box and the average cap) on the squared tracking error in the settled window plus
    a penalty on overshoot during the transient, with gradients through the exact ZOH
    simulator. With `free`, `raw`, `covariance_raw` (a fit) the response comes with its
    95 % confidence band (`greybox.uncertainty.prediction_band`).

    **Raises:** ValueError naming the option when the target is out of reach: a stroke the
    laser cannot hold at `power_max_W`, a settling time shorter than full power can achieve,
    or an average cap below the power needed to hold the stroke.
    """
    require_x64("track_target")
    model = as_arrays(with_camera(model, exposure_s=0.0))
    for name, v in (
        ("stroke_m", stroke_m),
        ("settling_s", settling_s),
        ("duration_s", duration_s),
        ("power_max_W", power_max_W),
        ("hold_s", hold_s),
        ("tolerance", tolerance),
    ):
        if not (math.isfinite(v) and v > 0):
            raise ValueError(f"{name}: {v!r} must be a positive number")
    if not 0 <= step_time_s < duration_s - settling_s:
        raise ValueError(
            f"step_time_s: {step_time_s} s leaves no settled window before duration_s "
            f"{duration_s} s (settling {settling_s} s)"
        )
    if not hasattr(model, "linear_dynamics"):
        raise ValueError("model: track_target needs a linear-dynamics device (ZOH simulation)")
    y_max = _steady_output(model, power_max_W)
    if y_max < stroke_m * (1 + tolerance):
        raise ValueError(
            f"stroke_m: {stroke_m:.4g} m is beyond what power_max_W = {power_max_W:g} W "
            f"holds in steady state ({y_max:.4g} m); lower the target or raise the power"
        )
    # bisection for the hold power (the stroke map is monotonic)
    lo_p, hi_p = 0.0, power_max_W
    for _ in range(60):
        mid = (lo_p + hi_p) / 2
        lo_p, hi_p = (mid, hi_p) if _steady_output(model, mid) < stroke_m else (lo_p, mid)
    p_hold = hi_p
    tau = _slowest_time_constant(model)
    reach = y_max * (1 - math.exp(-settling_s / tau))
    if reach < stroke_m * (1 - tolerance):
        raise ValueError(
            f"settling_s: {settling_s} s is too short: even {power_max_W:g} W from rest reaches "
            f"only {reach:.4g} m of {stroke_m:.4g} m in that time (thermal time constant "
            f"{tau:.3g} s); allow more settling time or raise power_max_W"
        )
    settled_energy = p_hold * (duration_s - step_time_s - settling_s)
    if average_power_max_W is not None and average_power_max_W * duration_s < settled_energy:
        raise ValueError(
            f"average_power_max_W: {average_power_max_W:g} W is below what holding the stroke "
            f"needs ({settled_energy / duration_s:.4g} W averaged over the run); raise the cap "
            "or shorten the run"
        )
    times = np.arange(step_time_s, duration_s - 1e-12, hold_s)
    k = times.size
    t = np.arange(1, int(round(duration_s / dt_s)) + 1) * dt_s
    t = t[t <= duration_s + 1e-12]
    template = _template(times, duration_s)
    row = schedule_row(model, template, t)
    seg = _segment_index(row, times)
    seg_pad = np.full(row["dt"].shape[0], k)
    seg_pad[: seg.size] = seg
    target = np.where(t >= step_time_s, stroke_m, 0.0)
    settled = (t >= step_time_s + settling_s) | (t < step_time_s)
    transient = ~settled
    w = jnp.asarray(settled.astype(float))
    wt = jnp.asarray(transient.astype(float))
    tgt = jnp.asarray(target)
    n = t.size
    mean_max = None
    if average_power_max_W is not None:
        mean_max = average_power_max_W * duration_s / (k * hold_s)

    args = (
        model,
        row,
        jnp.asarray(seg_pad),
        w,
        wt,
        tgt,
        jnp.asarray(float(stroke_m)),
        jnp.asarray(float(tolerance)),
    )

    def value_and_grad(levels):
        return _track_value_and_grad(levels, *args, n)

    def response(levels):
        return _track_response(levels, model, row, jnp.asarray(seg_pad), n)

    # start: full power for the time a first-order response needs, then the hold power
    boost = -tau * math.log(max(1 - stroke_m / y_max, 1e-12))
    x = np.where(times - step_time_s < boost, power_max_W, p_hold)
    x = project_levels(x[None], 0.0, power_max_W, mean_max)[0]
    best_x = projected_adam(
        value_and_grad,
        x,
        lambda z: project_levels(z[None], 0.0, power_max_W, mean_max)[0],
        step=0.02 * power_max_W,
        decay=0.99,
        n_iter=n_iter,
        maximise=False,
    )
    x = np.round(np.asarray(best_x) * 1e5) / 1e5
    x = project_levels(x[None], 0.0, power_max_W, mean_max)[0]
    levels = np.concatenate([[0.0], x]) if step_time_s > 0 else x
    tt = np.concatenate([[0.0], times]) if step_time_s > 0 else times
    keep = np.append(True, np.diff(levels) != 0)
    wave = PiecewiseConstant(tt[keep], levels[keep], duration_s)
    y = np.asarray(response(jnp.asarray(x)))
    err = float(np.max(np.abs(y - target)[settled]))
    tol_m = tolerance * stroke_m
    band = None
    if covariance_raw is not None and free is not None and raw is not None:
        band = prediction_band(model, free, raw, covariance_raw, wave, t, method="zoh")
    desc = {
        "type": "steps",
        "times_s": [round(float(v), 6) for v in tt[keep]],
        "power_mW": [round(float(v) * 1e3, 2) for v in levels[keep]],
        "end_s": round(duration_s, 6),
    }
    return TrackingDesign(
        waveform=wave,
        description=desc,
        t_s=t,
        response=y,
        target=target,
        settled=settled,
        max_error=err,
        tolerance=tol_m,
        met=err <= tol_m,
        average_power_W=float(wave.mean() * wave.duration_s / duration_s),
        band=band,
        iterations=n_iter,
    )


def _track_response(levels, model, row, seg_pad, n):
    u = jnp.concatenate([levels, jnp.zeros(1)])[seg_pad]
    z, _ = observe_schedule(model, dict(row, u_grid=u[:, None]), method="zoh")
    return z[:n, 0]


@jit
def _track_value_and_grad(levels, model, row, seg_pad, w, wt, tgt, stroke, tolerance, n):
    """Tracking loss and its gradient in the levels (module level: compiled once per shape)."""

    def loss(x):
        e = (_track_response(x, model, row, seg_pad, n) - tgt) / stroke
        over = jax.nn.relu(e - tolerance / 2)
        return jnp.sum(w * e**2) / jnp.sum(w) + jnp.sum(wt * over**2) / jnp.maximum(jnp.sum(wt), 1)

    return jax.value_and_grad(loss)(levels)


def _slowest_time_constant(model) -> float:
    a, _ = model.linear_dynamics()
    ev = np.linalg.eigvals(np.asarray(a))
    return float(1.0 / np.min(np.abs(ev.real)))
