"""The likelihood back end of `greybox.fit` (noise=`ProcessNoise(...)`): maximum likelihood of
a stochastic device through the continuous-discrete (extended) Kalman filter.

- Objective: -log L of every run (prediction-error decomposition, `_sde_device`) plus the
  log-normal priors, over the raw coordinates of the free parameters (`greybox._estimate.problem`).
- Starts of the noise parameters without `initial`: from the data and the linearised device
  (`greybox._estimate.noise_starts`).
- Initial state (`InitialState`): mean = the device's initial state with the run's settings
  and per-run estimates; covariance diag(sd^2); with a known initial state (sd 0, the
  default) the first frame of each run is conditioned on, not scored, so reading the initial
  state off the first reading cannot make the likelihood unbounded.
- Optimiser, compiled as one program (one `lax.while_loop`, no host loop per step, the
  filter and its gradient traced once: `_newton`):
  BFGS on the exact reverse-mode gradient with a backtracking line search, then Newton steps
  on the Hessian (central differences of that gradient, negative curvature mirrored so a
  saddle is left, not approached) until the Newton decrement g^T |H|^-1 g (twice the
  log-likelihood still to gain) is below `DECREMENT_TOL`. Steps are capped at `MAX_RAW_STEP`
  raw units. Raw coordinates are log / logit for bounded parameters, so physical and noise
  parameters of very different magnitudes are steps of the same size. Every start of a
  multi-start reuses the one compiled solver. (A forward-over-reverse AD Hessian through the
  filter's scan measured 18x the cost of a gradient and 3x its compile time on the RC3
  test; the differences of the gradient cost 2 P gradients and compile nothing new.)
- Covariance: the inverse Hessian of -log L + priors at the optimum (determined subspace,
  `greybox._estimate.identifiability`); the status is "not converged" with the combination
  named when the Hessian is not positive definite there.
- Verdicts: a process-noise or random-walk intensity that fell towards zero (below a tenth
  of its start) and whose zero the data do not reject (the boundary likelihood-ratio test at
  5 %: setting it to 0 costs less than 1.355 in log L) is
  "not needed" (no noise on that state; the fit stays valid, no interval); one whose zero
  they reject is inside its range however far below its start it ended (the generic "shrank
  to 1e-3 of its start" rule of a lower bound does not apply: zero is tested). An intensity
  that vanished where the cost still falls as it rises from zero (the log coordinate hides
  that slope) is first restarted from its start value (`revive`); where zero is the
  bound-constrained minimum it is not, which saved a whole second solve (6 s of a 15 s fit
  of 600 frames). A measurement sd that fell towards zero is judged the same way where
  -log L levels off there (readings with no noise beyond the process noise: "not needed");
  where it falls without bound (a reading fitted exactly, `_unbounded_at_zero`) the sd
  collapsed: the status is "not converged" with the reason "likelihood unbounded".
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from greybox._compile import jit
from greybox._estimate import noise_starts
from greybox._estimate import problem as _problem
from greybox._estimate.identifiability import analyse
from greybox._estimate.metrics import fit_percent
from greybox._estimate.noise_models import DIFFUSE_SD, ProcessNoise
from greybox._estimate.starts import run_starts
from greybox._model.freeparams import apply_raw, as_leaves
from greybox._simulate.simulate import as_arrays, require_x64
from greybox.stochastic._kalman import FilterGrid
from greybox.stochastic._sde_device import (
    _NOISE_FIELDS,
    NoiseStructure,
    StochasticDevice,
    _record_loglik,
    _run_arrays,
    _t0,
    stacked_lengths,
    stacked_records,
    stochastic_device,
)

MAX_STEPS = 500  # damped Newton steps per start
DECREMENT_TOL = _problem.DECREMENT_TOL  # Newton decrement at which a start has converged
MAX_RAW_STEP = 2.0  # largest raw step per iteration (a factor e^2 on a log parameter)
NOT_NEEDED_DROP = 1e-2  # a noise intensity below this fraction of its start has vanished
NOT_NEEDED_LR = 2.71  # 2 x log L lost at zero below which zero is not rejected (5 %, boundary)
NOT_NEEDED_FALL = 0.1  # ... for an intensity that fell below this fraction of its start
ZERO_PROBE = 1e-3  # a vanished intensity is raised to this fraction of its start to probe zero
ZERO_PROBE_FALL = 1e-9  # ... and a cost fall beyond this there means zero is no minimum
COLLAPSE_DROP = 1e-3  # a measurement sd below this fraction of its data-based start collapsed
SD_ZERO = 1e-9  # the fraction of its start that stands for a measurement sd of zero
INDEFINITE_TOL = 1e-6  # relative negative eigenvalue of the Hessian that counts as indefinite

_VANISHING = ("process", "output_walk", "input_walk")  # paths whose zero means "not needed"


@dataclasses.dataclass(frozen=True)
class RunDiagnostics:
    """One run at the fitted parameters (q outputs), every number labelled by its horizon.

    - `log_likelihood` (as scored by the fit: the first frame conditioned on when the initial
      state is known); `whiteness`: per output, the chi-square Ljung-Box of this run's
      standardised innovations alone (a per-run figure; the fit's verdict on whiteness is
      its `residuals`, the residual test every fit uses, on the innovations);
    - `one_step_fit_percent`, `simulation_fit_percent`, `k_step_fit_percent` (per output, %;
      the k-step-ahead prediction `k_step` frames ahead);
    - `y_one_step`, `y_simulation`, `y_k_step` (N, q) readings [SI], with their sds
      `y_one_step_sd`, `y_simulation_sd` (process noise), `y_k_step_sd`.
    """

    name: str
    role: str
    log_likelihood: float
    whiteness: tuple
    one_step_fit_percent: tuple
    simulation_fit_percent: tuple
    k_step: int
    k_step_fit_percent: tuple
    y_one_step: np.ndarray
    y_simulation: np.ndarray
    y_k_step: np.ndarray
    y_simulation_sd: np.ndarray
    standardised_innovation: np.ndarray
    y_one_step_sd: np.ndarray | None = None
    y_k_step_sd: np.ndarray | None = None

    @property
    def horizons(self) -> tuple:
        """((label, predictions (N, q), fit % per output), ...): simulation, one-step and
        k-step prediction, each labelled."""
        return (
            ("simulation", self.y_simulation, self.simulation_fit_percent),
            ("one-step prediction", self.y_one_step, self.one_step_fit_percent),
            (f"{self.k_step}-step prediction", self.y_k_step, self.k_step_fit_percent),
        )


class _Objective(eqx.Module):
    """-log L + priors over the raw vector (shared first, then per run)."""

    model: StochasticDevice
    grids: FilterGrid  # the runs' grids stacked (leading run axis E; `stacked_records`)
    t_s: jnp.ndarray  # (E, N)
    t0: jnp.ndarray  # (E,)
    y: jnp.ndarray  # (E, N, q), NaN past a run's own frames
    settings: jnp.ndarray  # (E, K)
    shared: tuple  # FreeParameters with array numbers (`as_leaves`): inputs, not structure
    per_exp: tuple
    setting_paths: tuple = eqx.field(static=True)
    n_exp: int = eqx.field(static=True)

    @property
    def flat(self) -> list:
        return _problem.flat_free(self.shared, self.per_exp, self.n_exp)

    def run_model(self, raw, i: int):
        ns, npr = len(self.shared), len(self.per_exp)
        base = apply_raw(self.model, self.shared, raw)
        return _problem.run_model(
            base,
            self.setting_paths,
            self.settings[i],
            self.per_exp,
            raw[ns + i * npr : ns + (i + 1) * npr],
        )

    def data_nll(self, raw):
        """-log L of every run: one filter mapped over the stacked runs (`lax.map`: compiled
        once whatever their number; one after another, so a Van Loan step's doubling branch
        stays a branch, which vmapping would run for every step)."""
        ns, npr = len(self.shared), len(self.per_exp)
        base = apply_raw(self.model, self.shared, raw)
        per = raw[ns:].reshape(self.n_exp, npr)

        def one(run):
            settings, per_row, grid, t_s, t0, y = run
            m = _problem.run_model(base, self.setting_paths, settings, self.per_exp, per_row)
            return _record_loglik(m, grid, t_s, t0, y)

        runs = (self.settings, per, self.grids, self.t_s, self.t0, self.y)
        if self.n_exp == 1:  # no loop around a single run's filter
            return -one(jax.tree.map(lambda x: x[0], runs))
        return -jnp.sum(jax.lax.map(one, runs))

    def prior_nll(self, raw):
        rows = [p.prior_residual(p.to_value(raw[k])) for k, p in _problem.prior_index(self.flat)]
        if not rows:
            return jnp.zeros((), raw.dtype)
        return 0.5 * jnp.sum(jnp.stack(rows) ** 2)

    def total(self, raw):
        return self.data_nll(raw) + self.prior_nll(raw)


def _eig_parts(H):
    w, V = jnp.linalg.eigh(0.5 * (H + H.T))
    scale = jnp.maximum(jnp.max(jnp.abs(w)), 1e-300)
    return w, V, jnp.maximum(jnp.abs(w), 1e-12 * scale), scale


# The Hessian is central differences of the exact (reverse-mode) gradient: 2 P gradient
# evaluations, so no second derivative of the filter is compiled. A raw step of 1e-4 makes it
# accurate to ~1e-8 relative (4.7e-9 against forward-over-forward AD on the TCLab case,
# `benchmarks/kalman.py --coverage-device`), far below what standard errors need. The Newton
# iterations between the first Hessian and the last steer by forward differences (P gradient
# evaluations, accurate to ~1e-4 relative: enough to aim a step); every start ends on a central
# one, which decides convergence and gives the covariance.
_FD_STEP = 1e-4


_HALVINGS = 30  # backtracking line search: a = 1, 1/2, ..., 2^-30, then the search has failed
# phases of the optimiser's state machine (int32, the type of its loop counters)
_INIT, _BFGS, _NEWTON, _HESSIAN, _DONE = (np.int32(i) for i in range(5))


def _cap(p):
    return p * jnp.minimum(1.0, MAX_RAW_STEP / jnp.maximum(jnp.max(jnp.abs(p)), 1e-300))


def _select(pred, new: dict, old: dict) -> dict:
    """`old` with the entries of `new` where `pred` holds (a branch-free state update)."""
    return {k: jnp.where(pred, new[k], old[k]) if k in new else old[k] for k in old}


def _decrement(g, H):
    _, V, wabs, _ = _eig_parts(H)
    gt = V.T @ g
    return jnp.sum(gt**2 / wabs)


def _newton_direction(g, H):
    _, V, wabs, _ = _eig_parts(H)
    return _cap(-V @ ((V.T @ g) / wabs))


@jit
def _newton(obj: _Objective, raw0, max_steps):
    """Maximise the likelihood from `raw0`; one compiled program for every start.

    BFGS (backtracking Armijo line search, steps capped at `MAX_RAW_STEP` raw units) until its
    own estimate of the Newton decrement is below `DECREMENT_TOL`, then Newton steps on the
    Hessian (finite differences of the exact gradient, negative curvature mirrored) until the
    Newton decrement g^T |H|^-1 g is below `DECREMENT_TOL`; the Hessian at the end point,
    always central differences, is returned for the covariance. The Hessians in between are
    forward differences (P probes, not 2 P: a start that needs Newton iterations is mostly
    Hessian probes; `experiments/heating_system`'s second start, 30 iterations, 496 -> 272
    probes, 69 -> 41 s, the same iterations and end point to ~1e-11 in -log L; a forward
    Hessian that says "converged" is checked by a central one at the same point).
    `max_steps` bounds each phase. Returns a dict: raw, cost, data_nll, gradient, hessian
    (total), prior_hessian, steps, converged, ran_out, stalled.

    Written as a state machine of one `lax.while_loop` whose pass evaluates the value and
    gradient of -log L at one point: the start, a line-search trial of either phase (an
    accepted trial needs no second evaluation) or one of the P or 2 P probes of a Hessian. The
    filter and its gradient are therefore traced and compiled once (compiling them was most
    of a small fit's time), the points evaluated are those of the plain form (a BFGS loop,
    then a Newton loop whose Hessians are `lax.map`s of the gradient), and in a vmapped
    batch every pass evaluates one point for every member, whatever phase each is in.
    """

    def value_and_data(r):
        d = obj.data_nll(r)
        return d + obj.prior_nll(r), d

    vg = jax.value_and_grad(value_and_data, has_aux=True)
    n = raw0.shape[0]
    dtype = raw0.dtype
    eye = jnp.eye(n, dtype=dtype)
    probes = jnp.concatenate([eye, -eye]) * _FD_STEP  # the Hessian's central differences
    zero = jnp.zeros((), dtype)
    max_steps = jnp.asarray(max_steps)

    def bfgs_direction(g, Hi):
        p = -Hi @ g
        descent = g @ p < 0
        return jnp.where(descent, Hi, eye), _cap(jnp.where(descent, p, -g))

    def new_search(s, p):  # a line search along `p` from the current point
        return dict(s, p=p, slope=s["g"] @ p, a=jnp.ones((), dtype), k=np.int32(0))

    def to_hessian(s, forward=False):  # probe the Hessian at the current point next
        return dict(s, phase=_HESSIAN, j=np.int32(0), fwd=jnp.asarray(forward))

    def end(s):  # stop here, on a central Hessian: a forward one is probed again centrally
        return _select(s["fwd"], to_hessian(s), dict(s, phase=_DONE))

    def step(s):
        hessian = s["phase"] == _HESSIAN
        x = jnp.where(hessian, s["raw"] + probes[s["j"]], s["raw"] + s["a"] * s["p"])
        (vt, dt), gt = vg(x)
        armijo = jnp.isfinite(vt) & (vt <= s["v"] + 1e-4 * s["a"] * s["slope"])
        ended = armijo | (s["k"] >= _HALVINGS)  # the line search is over (accepted or failed)
        halved = dict(s, a=s["a"] * 0.5, k=s["k"] + 1)
        moved = _select(armijo, dict(raw=x, v=vt, d=dt, g=gt), s)

        def start():  # the start: BFGS from the identity (or no BFGS step at all)
            s0 = dict(s, raw=x, v=vt, d=dt, g=gt)
            Hi, p = bfgs_direction(gt, eye)
            s1 = new_search(dict(s0, Hi=Hi, phase=_BFGS), p)
            return _select(max_steps <= 0, to_hessian(s0), s1)

        def bfgs():  # a BFGS line search has ended: update; the phase ends when it fails
            dx = s["a"] * s["p"]
            yv = moved["g"] - s["g"]
            sy = dx @ yv
            Hi = s["Hi"]
            # first update: scale the identity to the curvature seen (Nocedal & Wright 6.20)
            Hi = jnp.where((s["it1"] == 0) & (sy > 0), Hi * sy / jnp.maximum(yv @ yv, 1e-300), Hi)
            rho = 1.0 / jnp.where(sy > 1e-300, sy, 1.0)
            E = eye - rho * jnp.outer(dx, yv)
            Hi = jnp.where(armijo & (sy > 1e-300), E @ Hi @ E.T + rho * jnp.outer(dx, dx), Hi)
            dec = moved["g"] @ Hi @ moved["g"]
            it1 = s["it1"] + 1
            over = (armijo & (dec < DECREMENT_TOL) & (dec >= 0)) | ~armijo | (it1 >= max_steps)
            Hi_next, p = bfgs_direction(moved["g"], Hi)
            searching = new_search(dict(moved, Hi=Hi_next, it1=it1), p)
            after = _select(over, to_hessian(dict(moved, it1=it1)), searching)
            return _select(ended, after, halved)

        def newton():  # a Newton line search has ended: the Hessian at the new point, or stop
            moved2 = dict(moved, it2=s["it2"] + 1)
            after = _select(armijo, to_hessian(moved2, forward=True), end(moved2))
            return _select(ended, after, halved)

        def probe():  # one column of the Hessian; after the last, the next Newton search
            G = s["G"].at[s["j"]].set(gt)
            central = (G[:n] - G[n:]).T / (2 * _FD_STEP)
            forward = (G[:n] - s["g"]).T / _FD_STEP
            H = jnp.where(s["fwd"], forward, central)
            H = 0.5 * (H + H.T)
            finish = (_decrement(s["g"], H) < DECREMENT_TOL) | (s["it2"] >= max_steps)
            searching = new_search(dict(s, G=G, H=H, phase=_NEWTON), _newton_direction(s["g"], H))
            last = s["j"] + 1 == jnp.where(s["fwd"], n, 2 * n)
            probed = _select(finish, end(dict(s, G=G, H=H)), searching)
            return _select(last, probed, dict(s, G=G, j=s["j"] + 1))

        return jax.lax.switch(s["phase"], [start, bfgs, newton, probe])

    init = dict(
        raw=raw0, v=zero, d=zero, g=jnp.zeros_like(raw0), Hi=eye, H=eye,
        G=jnp.zeros((2 * n, n), dtype), p=jnp.zeros_like(raw0), slope=zero,
        a=jnp.ones((), dtype), k=np.int32(0), j=np.int32(0),
        it1=np.int32(0), it2=np.int32(0), phase=_INIT, fwd=jnp.asarray(False),
    )  # fmt: skip
    s = jax.lax.while_loop(lambda s: s["phase"] != _DONE, step, init)
    raw, g, H, it1, it2 = s["raw"], s["g"], s["H"], s["it1"], s["it2"]
    converged = _decrement(g, H) < DECREMENT_TOL
    return dict(
        raw=raw,
        cost=s["v"],
        data_nll=s["d"],
        gradient=g,
        hessian=H,
        prior_hessian=jax.hessian(obj.prior_nll)(raw),
        steps=it1 + it2,
        converged=converged,
        ran_out=(~converged) & ((it1 >= max_steps) | (it2 >= max_steps)),
        stalled=~converged & (it2 < max_steps) & (it1 < max_steps),
    )


@jit
def _totals_jit(obj: _Objective, raws):
    return jax.vmap(obj.total)(raws)


def totals_at(obj: _Objective, raws) -> np.ndarray:
    """-log L + priors of `obj` at each row of `raws` (what `revive` probes zero with)."""
    return np.asarray(jax.device_get(_totals_jit(obj, jnp.asarray(raws))))


@jit
def _data_nll_jit(obj: _Objective, raw):
    return obj.data_nll(raw)


def _nll_at_zero(obj: _Objective, raw, k: int, start: float, below: float = 1.0) -> float:
    """-log L with noise level `k` at its zero, the others at `raw`: an intensity at 0, a
    measurement sd at `SD_ZERO` x `below` x its `start` (at exactly 0 a reading the filter
    conditions on is 0 / 0). NaN or +inf where zero is infeasible."""
    p = obj.flat[k]
    at_zero = np.asarray(raw, dtype=float).copy()
    if p.path.startswith("measurement."):
        at_zero[k] = float(p.to_raw(SD_ZERO * below * start))
    else:
        at_zero[k] = -np.inf  # value = lower bound (0) for a log or logit coordinate
    return float(_data_nll_jit(obj, jnp.asarray(at_zero)))


def _unbounded_at_zero(obj: _Objective, raw, k: int, start: float) -> bool:
    """Whether -log L still falls without bound as measurement sd `k` goes to zero (a reading
    fitted exactly: log sd -> -inf), rather than levelling off (readings with no measurement
    noise beyond the process noise): 1e3 x closer to zero lowers it by more than one."""
    far, near = _nll_at_zero(obj, raw, k, start), _nll_at_zero(obj, raw, k, start, 1e-3)
    return not (np.isfinite(far) and np.isfinite(near)) or near < far - 1.0


def _zero_suffices(obj: _Objective, raw, k: int, nll_hat: float, start: float) -> bool:
    """Whether noise level `k` (an intensity, or a measurement sd where the likelihood is
    bounded at zero), which fell towards zero (below `NOT_NEEDED_FALL` of its `start` value:
    the caller's test), is "not needed": setting it to zero (the others at the estimate)
    costs less than the boundary likelihood-ratio test's 5 % critical value (`NOT_NEEDED_LR`:
    2 x log L, half a chi-square(1) at a boundary), so the data do not reject "no such
    noise"."""
    nll0 = _nll_at_zero(obj, raw, k, start)
    return bool(np.isfinite(nll0) and 2.0 * (nll0 - nll_hat) < NOT_NEEDED_LR)


def _gone(flat, raw0, raw) -> list[int]:
    """Coordinates of the noise intensities that vanished (fell below `NOT_NEEDED_DROP` of
    their start) at `raw`."""
    raw = np.asarray(raw, dtype=float)
    return [
        k
        for k, p in enumerate(flat)
        if _vanishing(p.path)
        and np.isfinite(raw[k])
        and float(p.to_value(raw[k])) < NOT_NEEDED_DROP * float(p.to_value(raw0[k]))
    ]


def _descends_from_zero(flat, raw0, raw, gone, totals) -> list[int]:
    """Those of the vanished intensities `gone` from whose zero the cost still falls.

    At the end point the other coordinates are stationary, so the intensity's zero is a
    minimum of the bound-constrained problem (its Karush-Kuhn-Tucker point) unless raising
    that intensity alone lowers -log L + priors: the one-sided derivative at zero, which the
    log coordinate hides (its gradient there is the intensity times that derivative). It is
    read off `totals(raws)` at zero (all `gone` at zero) and at `ZERO_PROBE` of each one's
    start value; a fall of more than `ZERO_PROBE_FALL` (first order: 1e-6 over the whole way
    to the start value, the gain a restart must bring to be kept) is a descent."""
    at_zero = np.asarray(raw, dtype=float).copy()
    at_zero[gone] = -np.inf  # value = lower bound (0) for a log or logit coordinate
    probes = [at_zero]
    for k in gone:
        probe = at_zero.copy()
        probe[k] = float(flat[k].to_raw(ZERO_PROBE * float(flat[k].to_value(raw0[k]))))
        probes.append(probe)
    c = np.asarray(totals(np.stack(probes)), dtype=float)
    if not np.isfinite(c[0]):
        return list(gone)  # zero itself is infeasible here: restart all of them, as before
    return [k for k, ck in zip(gone, c[1:]) if ck < c[0] - ZERO_PROBE_FALL]


def revive(outs, flats, raw0s, solve, totals, say, labels) -> list[dict]:
    """Solver outputs `outs` (one per item) after reviving vanished noise intensities.

    While a noise intensity has vanished (log coordinate driven towards -inf, where its
    gradient vanishes too: a stationary point at infinity that need not be a minimum of
    -log L) and the cost still falls when it is raised from zero (`_descends_from_zero`), the
    solve is repeated with those intensities back at their starting values, keeping the
    better end point (at most twice). A zero intensity that survives this is a real answer
    ("not needed"). `solve([(item, raw), ...])` returns one output per pair and
    `totals(item, raws)` the cost at each of `raws`, so one device's starts (`fit`) and many
    devices' (`fit_batch`) share this rule; `labels[item]` names an item in the progress
    line."""
    outs = [dict(o) for o in outs]
    steps = [int(o["steps"]) for o in outs]
    active = list(range(len(outs)))
    for _ in range(2):
        trials = []
        for i in active:
            gone = _gone(flats[i], raw0s[i], outs[i]["raw"])
            if gone:
                gone = _descends_from_zero(
                    flats[i], raw0s[i], outs[i]["raw"], gone, lambda r, i=i: totals(i, r)
                )
            if gone:
                trial = np.asarray(outs[i]["raw"], dtype=float).copy()
                trial[gone] = np.asarray(raw0s[i])[gone]
                trials.append((i, trial, gone))
        if not trials:
            break
        again = solve([(i, t) for i, t, _ in trials])
        active = []
        for (i, _, gone), new in zip(trials, again):
            steps[i] += int(new["steps"])
            if float(new["cost"]) < float(outs[i]["cost"]) - 1e-6:
                names = ", ".join(flats[i][k].path for k in gone)
                say(
                    f"{labels[i]}: {names} had vanished; restarted from its start value, "
                    f"-log L + priors {float(outs[i]['cost']):.6g} -> {float(new['cost']):.6g}"
                )
                outs[i] = dict(new)
                active.append(i)
    for o, n in zip(outs, steps):
        o["steps"] = n
    return outs


def _structure_model(model, noise: ProcessNoise) -> StochasticDevice:
    """The `StochasticDevice` the fit filters: `model` itself, or a device wrapped with
    `noise.structure`; `noise.filter` written into its structure."""
    if isinstance(model, StochasticDevice):
        if noise.structure not in (NoiseStructure(), model.structure):
            raise ValueError(
                "noise: ProcessNoise.structure differs from the StochasticDevice's own "
                "structure; give one of them (or the same)"
            )
        sd = model
    else:
        sd = stochastic_device(model, noise.structure)
    if noise.filter is not None:
        structure = ProcessNoise(
            sd.structure, noise.filter, noise.initial_state
        ).structure_with_filter()
        sd = stochastic_device(
            sd.device,
            structure,
            outputs=sd.measurement.names,
            inputs=_input_names(sd),
            values=_noise_values(sd),
        )
    return sd


def _input_names(sd: StochasticDevice):
    if sd.input_walk.names:
        return sd.input_walk.names
    return None


def _noise_values(sd: StochasticDevice) -> dict:
    return {
        f"{f}.{nm}": float(v)
        for f in _NOISE_FIELDS
        for nm, v in zip(getattr(sd, f).names, getattr(sd, f).values)
    }


def _with_initial_state(sd: StochasticDevice, noise: ProcessNoise, experiments):
    """`sd` with the initial state's spread and the first-frame rule of `noise.initial_state`."""
    init = noise.initial_state
    n = sd.n_device_states
    if init.diffuse:
        spread = np.nanmax([np.nanstd(e.y) for e in experiments])
        sd0 = np.full(n, DIFFUSE_SD * max(float(spread), 1e-12))
    elif isinstance(init.sd, tuple):
        if len(init.sd) != n:
            raise ValueError(
                f"initial_state: {len(init.sd)} sds given for the device's {n} states"
            )
        sd0 = np.asarray(init.sd, dtype=float)
    else:
        sd0 = np.full(n, float(init.sd))
    return StochasticDevice(
        device=sd.device,
        process=sd.process,
        measurement=sd.measurement,
        output_walk=sd.output_walk,
        input_walk=sd.input_walk,
        structure=sd.structure,
        initial_sd=jnp.asarray(sd0),
        score_first=init.scores_first_reading,
    )


def _build(model, experiments, free, pad: bool = False):
    """The objective over `experiments`, its runs stacked (`stacked_records`: padded to the
    longest, the same log-likelihood) and, with `pad`, their lengths bucketed: runs of
    similar lengths then share one compiled solver, at the cost of the padded steps in
    every evaluation."""
    setting_paths, settings = _problem.settings_matrix(model, experiments, free)
    shared, per_exp = _problem.split(free)
    grid, t_s, y = stacked_records(experiments, bucket=pad)
    return _Objective(
        model=as_arrays(model),
        grids=jax.tree.map(jnp.asarray, grid),
        t_s=jnp.asarray(t_s),
        t0=jnp.asarray([_t0(e) for e in experiments]),
        y=jnp.asarray(y),
        settings=jnp.asarray(settings),
        setting_paths=setting_paths,
        shared=as_leaves(shared),
        per_exp=as_leaves(per_exp),
        n_exp=len(experiments),
    )


def _vanishing(path: str) -> bool:
    return path.partition(".")[0] in _VANISHING


def _diagnose(model, e, role: str, lags: int, k_step: int, settings_applied=False, lengths=None):
    """`RunDiagnostics` of run `e` (`lengths`: what its filter is padded to, `_run_arrays`)."""
    from greybox._estimate.stochastic_fit import ljung_box

    m = model if settings_applied else e.apply_settings(model)
    m = as_arrays(m)
    _, yp, sd1, ys, sds, _, yk, sdk, ll = _run_arrays(m, e, k_step, lengths)
    ll = float(ll)
    y = np.asarray(e.y)
    yp, ys, yk = np.asarray(yp), np.asarray(ys), np.asarray(yk)
    z = (y - yp) / np.asarray(sd1)
    q = y.shape[1]
    return RunDiagnostics(
        name=e.name,
        role=role,
        log_likelihood=ll,
        whiteness=tuple(ljung_box(z[:, j], lags) for j in range(q)),
        one_step_fit_percent=tuple(fit_percent(y[:, j], yp[:, j]) for j in range(q)),
        simulation_fit_percent=tuple(fit_percent(y[:, j], ys[:, j]) for j in range(q)),
        k_step=int(k_step),
        k_step_fit_percent=tuple(fit_percent(y[:, j], yk[:, j]) for j in range(q)),
        y_one_step=yp,
        y_simulation=ys,
        y_k_step=yk,
        y_simulation_sd=np.asarray(sds),
        standardised_innovation=z,
        y_one_step_sd=np.asarray(sd1),
        y_k_step_sd=np.asarray(sdk),
    )


def _indefinite_note(H, labels) -> str | None:
    """None when `H` is positive definite (to `INDEFINITE_TOL`), else the direction of its
    most negative curvature in words."""
    w, V = np.linalg.eigh(0.5 * (H + H.T))
    scale = max(float(np.max(np.abs(w))), 1e-300)
    if w[0] >= -INDEFINITE_TOL * scale:
        return None
    v = V[:, 0]
    order = np.argsort(-np.abs(v))[:3]
    combo = " ".join(f"{v[k]:+.2f} {labels[k]}" for k in order if abs(v[k]) > 0.1)
    return (
        f"the Hessian of -log L is not positive definite at the end point (curvature "
        f"{w[0]:.3g} along {combo}): not a maximum"
    )


@dataclasses.dataclass
class Setup:
    """One device's likelihood problem, ready to solve: the filtered `StochasticDevice` `sd`,
    the checked `free` list (noise starts and scales applied), the objective `obj`, the raw
    start `raw0` and the multi-start points `starts`; `bucketed`: its runs' lengths rounded
    up (`_build(pad=True)`), and so its diagnostics' too."""

    sd: StochasticDevice
    free: tuple
    obj: _Objective
    raw0: np.ndarray
    starts: list
    budget: int
    noise: ProcessNoise
    experiments: tuple
    bucketed: bool = False

    @property
    def flat(self) -> list:
        return self.obj.flat

    @property
    def label(self) -> str:
        filt = "extended Kalman filter" if self.sd.use_ekf else "Kalman filter"
        return (
            f"maximum likelihood ({filt}, BFGS + Newton, {self.raw0.size} parameters, "
            f"{len(self.experiments)} runs)"
        )


def setup(
    model,
    experiments,
    free,
    noise: ProcessNoise,
    *,
    n_starts: int | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    start_values=None,
    pad_records: bool = True,
) -> Setup:
    """The `Setup` of one device (what `fit_likelihood` solves; `fit_batch` stacks many);
    `pad_records`: its runs padded to bucketed lengths (`_build`; at most an eighth longer,
    `schedules.fine_bucket_length`), as the output-error fit pads its runs: records of
    similar lengths (the devices of a wafer, a few frames longer or shorter) then share one
    compiled solver and one batch group, not one each (a new length cost 2-2.5 s of
    compiling). The padded steps are exact identities (the same estimates to the bit) that
    every evaluation pays for. False keeps each record's own length."""
    from greybox._estimate import fit as _fit

    experiments = tuple(experiments)
    if not experiments:
        raise ValueError("experiments: zero runs in the estimation set; give at least one")
    sd = _structure_model(model, noise)
    sd = _with_initial_state(sd, noise, experiments)
    free = _problem.check_free(sd, free)
    free = _fit.apply_start_values(start_values, sd, free, experiments)
    if noise.start_noise:
        sd = noise_starts.start_noise(sd, experiments, free)
    free = _problem.with_scales(free, sd)
    obj = _build(sd, experiments, free, pad=pad_records)
    raw0 = _problem.initial_raw(obj.flat, sd)
    n_start = _problem.n_starts_for(n_starts, obj.shared)
    rng = np.random.default_rng(seed)
    starts = [raw0] + [_problem.perturbed(obj.shared, raw0, rng) for _ in range(n_start - 1)]
    budget = MAX_STEPS if max_steps is None else int(max_steps)
    return Setup(sd, free, obj, raw0, starts, budget, noise, experiments, pad_records)


def start_state(out) -> str:
    """A solver output's ending in words."""
    if out["converged"]:
        return "converged"
    return "ran out of steps" if out["ran_out"] else "stalled"


def fit_likelihood(
    model,
    experiments,
    free,
    noise: ProcessNoise,
    *,
    progress: Callable[[str], None] | None = None,
    **options,
):
    """The likelihood back end of `greybox.fit` (see the module docstring); a `FitResult`.
    `options`: those of `setup` (n_starts, seed, max_steps, start_values)."""
    require_x64("fit")
    say = progress or (lambda _m: None)
    su = setup(model, experiments, free, noise, **options)

    def one(raw):
        return jax.device_get(_newton(su.obj, jnp.asarray(raw), jnp.asarray(su.budget)))

    n = len(su.starts)
    labels = [f"start {i + 1}/{n}" for i in range(n)]
    runs = [None] * n

    def report(i, out):  # in start order, on this thread: a vanished intensity revived here
        out = revive(
            [out],
            [su.flat],
            [su.raw0],
            lambda items: [one(r) for _, r in items],
            lambda _item, raws: totals_at(su.obj, raws),
            say,
            [labels[i]],
        )[0]
        runs[i] = out
        say(
            f"{labels[i]}: -log L + priors {float(out['cost']):.6g}, {start_state(out)} "
            f"after {int(out['steps'])} steps"
        )

    # the starts side by side on a CPU's cores (`starts.run_starts`), as least squares runs
    # them: each the same compiled solve, so the estimates are those of one after another
    run_starts(one, su.starts, lambda i: say(f"{labels[i]}: {su.label}"), report, solve_bytes(su))
    return assemble(su, runs, say)


def solve_bytes(su: Setup) -> float:
    """Working bytes of one likelihood solve of `su` (`memory.solve_bytes`, the one memory
    model of every fit: the filter's steps as its intervals, times the local linearisations
    of each step for the extended filter; 26 MB measured by XLA for the TCLab board's
    12-parameter fit, 31 MB estimated)."""
    from greybox._estimate import memory

    steps = int(np.shape(su.obj.grids.dt_s)[-1])  # per run, padded to the longest
    if su.sd.use_ekf:
        steps *= int(su.sd.ekf_substeps)
    return memory.solve_bytes(
        runs=int(su.obj.n_exp),
        frames=int(np.shape(su.obj.t_s)[-1]),
        states=int(su.sd.n_states),
        outputs=int(su.sd.n_outputs),
        inputs=int(su.sd.n_inputs),
        raw=int(np.size(su.raw0)),
        intervals=steps,
    )


def assemble(su: Setup, runs, say):
    """The `FitResult` of one device from its solver outputs `runs` (one per start)."""
    return assemble_many([(su, runs)], say)[0]


def assemble_many(items, say) -> list:
    """`assemble` of each (setup, runs) of `items` (the devices of a batch), as one call each
    gives, with the residual tests of every run of every device in one vectorised pass
    (`residuals.analyse_many`: their shuffles shared)."""
    from greybox._estimate import fit as _fit
    from greybox._estimate.residuals import analyse_many

    parts = [_assembled(su, runs, say) for su, runs in items]
    tests = analyse_many([innovations for _, innovations in parts])
    return [_fit.FitResult(**fields, residuals=t) for (fields, _), t in zip(parts, tests)]


def _assembled(su: Setup, runs, say) -> tuple[dict, list]:
    """(the `FitResult` fields of one device but its residual tests, its innovations as
    `residuals.analyse` takes them)."""
    from greybox._estimate import fit as _fit

    sd, free, obj, raw0, noise, experiments = (
        su.sd, su.free, su.obj, su.raw0, su.noise, su.experiments
    )
    flat = obj.flat
    best_index = _problem.best_start(runs)
    best = runs[best_index]
    raw = np.asarray(best["raw"], dtype=float)
    ok_finite = bool(_problem.finite_starts(runs))
    names, owners = _problem.labels(obj.shared, obj.per_exp, experiments)

    # verdicts per coordinate: at bound (raw scale), not needed (a vanishing noise intensity)
    H = np.asarray(best["hessian"], dtype=float)
    H_data = H - np.asarray(best["prior_hessian"], dtype=float)
    bounds, unbounded = [], set()  # unbounded: measurement sds whose zero has no upper bound
    for k, p in enumerate(flat):
        hit = p.bound_hit(raw[k], raw0[k]) if ok_finite else None
        start = float(p.to_value(raw0[k]))
        measured = p.path.startswith("measurement.")
        if ok_finite and (_vanishing(p.path) or measured):
            fell = float(p.to_value(raw[k])) < NOT_NEEDED_FALL * start
            if measured and fell and _unbounded_at_zero(obj, raw, k, start):
                unbounded.add(k)
            elif fell and _zero_suffices(obj, raw, k, float(best["data_nll"]), start):
                hit = "not needed"
            if hit == "lower":  # far below its start, yet not at zero: the data reject
                hit = None  # zero (interior) or the likelihood is unbounded there (`collapsed`)
        bounds.append(hit)
    if ok_finite and np.all(np.isfinite(H_data)):
        vals, vecs = np.linalg.eigh(0.5 * (H_data + H_data.T))
        jac_data = np.sqrt(np.clip(vals, 0, None))[:, None] * vecs.T
    else:
        jac_data = np.full((raw.size, raw.size), np.nan)
    jac_prior = _prior_jacobian(flat, raw)
    report = analyse(jac_data, jac_prior, flat, raw, names, bounds)
    params = _fit.parameter_estimates(flat, raw, report, names, owners)
    params = tuple(dataclasses.replace(p, se_method="inverse Hessian") for p in params)

    # why a start did not converge, in words
    keep = [k for k, b in enumerate(bounds) if b is None]
    reason = None
    if ok_finite and keep:
        reason = _indefinite_note(H[np.ix_(keep, keep)], [names[k] for k in keep])
    collapsed = [  # a measurement sd that fell to where the likelihood has no upper bound
        (names[k], float(p.to_value(raw[k])))
        for k, p in enumerate(flat)
        if k in unbounded and float(p.to_value(raw[k])) < COLLAPSE_DROP * float(p.to_value(raw0[k]))
    ]
    if collapsed:
        where = ", ".join(f"{n} = {v:.3g}" for n, v in collapsed)
        reason = (
            f"likelihood unbounded: the measurement sd collapsed ({where}); the readings are "
            "fitted exactly, most often the first reading against an initial state read off "
            "it: condition on it (InitialState(sd=0), the default), give the initial state a "
            "spread, or put a prior on the measurement sd"
        )
    if reason is None and not bool(best["converged"]) and bool(best["stalled"]):
        reason = "no step decreases -log L (the search stalled before the Newton decrement met"
        reason += f" its tolerance {DECREMENT_TOL:g})"
    pinned = [
        (names[k], b, float(p.lower if b == "lower" else p.upper))
        for k, (p, b) in enumerate(zip(flat, bounds))
        if b in ("lower", "upper")
    ]
    unidentified = _fit.unidentified_with_reasons(params, report)
    costs = [float(r["cost"]) for r in runs]
    status, message, at_best = _fit.fit_status(
        finite=ok_finite,
        solved=True,
        optimiser_ok=bool(best["converged"]) and reason is None,
        pinned=pinned,
        costs=costs,
        best_index=best_index,
        unidentified=unidentified,
        ran_out=bool(best["ran_out"]) and reason is None,
        reason=reason,
        start_converged=[bool(r["converged"]) for r in runs],
        optimiser="the BFGS / Newton search",
    )
    not_needed = [names[k] for k, b in enumerate(bounds) if b == "not needed"]
    if not_needed:
        message += (
            f"; not needed (went to zero; no such noise in these data): {', '.join(not_needed)}"
        )

    base = apply_raw(obj.model, obj.shared, jnp.asarray(raw))
    run_models = tuple(obj.run_model(jnp.asarray(raw), i) for i in range(len(experiments)))
    say("filtering every run at the estimate: one-step, k-step and simulation predictions")
    # every run's filter padded to the objective's stacked (bucketed) length: one compile
    # for all, shared with other records of similar lengths
    stacked = stacked_lengths(experiments, noise.k_step, su.bucketed)
    diags = tuple(
        _diagnose(
            m_i,
            e,
            "estimation",
            noise.whiteness_lags,
            noise.k_step,
            settings_applied=True,
            lengths=stacked,
        )
        for m_i, e in zip(run_models, experiments)
    )
    n_obs = sum(_scored_readings(e, sd.score_first) for e in experiments)
    data_nll = float(best["data_nll"])
    k = raw.size
    sigma = np.asarray([float(v) for v in base.measurement.values])
    measured_free = any(p.path.startswith("measurement.") for p in free)
    innovations = [
        (e.name, e.t_s, e.y - d.y_one_step, e.mask, e.frame_inputs())
        for e, d in zip(experiments, diags)
    ]
    report_cov = np.asarray(report.covariance_raw)
    fields = dict(
        model=base,
        experiment_models=run_models,
        experiments=experiments,
        free=tuple(free),
        parameters=params,
        raw=raw,
        covariance_raw=report_cov,
        correlation=_fit.correlation(report),
        sigma=sigma,
        cost=float(best["cost"]),
        n_data=n_obs,
        converged=bool(best["converged"]) and ok_finite,
        message=message,
        n_steps=int(best["steps"]),
        fit_percent={d.name: np.asarray(d.simulation_fit_percent) for d in diags},
        fit_percent_robust={d.name: np.asarray(d.simulation_fit_percent) for d in diags},
        n_outliers={d.name: 0 for d in diags},
        identifiability=report,
        loss="gaussian",
        method="zoh" if not sd.use_ekf else "adaptive",
        multistart_costs=tuple((float(r["cost"]), bool(r["converged"])) for r in runs),
        status=status,
        valid=status in _fit.VALID_STATUSES,
        noise_ceiling={d.name: np.full(len(sigma), np.nan) for d in diags},
        covariance_gauss_newton_raw=report_cov,
        covariance_hac_raw=np.full_like(report_cov, np.nan),
        se_method="inverse Hessian",
        hac_bandwidth=0,
        sigma_source="estimated" if measured_free else "declared",
        goodness_of_fit=None,
        best_start=int(best_index),
        n_starts_at_best=len(at_best),
        horizon="simulation",
        noise=noise,
        log_likelihood=-data_nll,
        aic=2 * data_nll + 2 * k,
        bic=2 * data_nll + k * float(np.log(max(n_obs, 1))),
        n_observations=n_obs,
        predictions={
            d.name: {"simulation": d.y_simulation, "one-step": d.y_one_step, "k-step": d.y_k_step}
            for d in diags
        },
        prediction_sd={
            d.name: {
                "simulation": d.y_simulation_sd,
                "one-step": d.y_one_step_sd,
                "k-step": d.y_k_step_sd,
            }
            for d in diags
        },
        whiteness={d.name: d.whiteness for d in diags},
        runs=diags,
    )
    return fields, innovations


def _scored_readings(e, score_first: bool) -> int:
    n = int(np.isfinite(e.y).sum())
    return n if score_first else n - int(np.isfinite(e.y[0]).sum())


def _prior_jacobian(flat, raw) -> np.ndarray:
    rows = []
    for k, p in _problem.prior_index(flat):
        row = np.zeros(raw.size)
        value = float(p.to_value(raw[k]))
        row[k] = p.value_derivative(raw[k]) / value / p.prior_log_sd
        rows.append(row)
    return np.asarray(rows).reshape(-1, raw.size)


def validate_runs(result, experiments) -> tuple:
    """`RunDiagnostics` (role "validation") of new runs at the fitted shared parameters;
    per-run free parameters, if any, are re-fitted on each run (physics and noise fixed)."""
    noise = result.noise
    per = tuple(p for p in result.free if p.per_experiment)
    # the lengths the fit's own diagnostics were compiled at (its runs bucketed, `setup`)
    estimation = None if per else stacked_lengths(result.experiments, noise.k_step, True)
    out = []
    for e in experiments:
        if per:
            # a small fit per run, its runs padded to bucketed lengths as every fit's are:
            # runs of similar lengths re-fit with one compiled solver, not one per length
            sub = fit_likelihood(
                result.model,
                [e],
                per,
                dataclasses.replace(noise, start_noise=False),
                n_starts=1,
            )
            out.append((dataclasses.replace(sub.runs[0], role="validation"), sub.parameters))
            continue
        # the estimation runs' compiled filter serves a validation run that fits within
        # their lengths; a longer one is padded to bucketed lengths (shared with its kind)
        fit_in = all(o <= f for o, f in zip(stacked_lengths([e], noise.k_step), estimation))
        d = _diagnose(
            result.model,
            e,
            "validation",
            noise.whiteness_lags,
            noise.k_step,
            lengths=estimation if fit_in else None,
        )
        out.append((d, ()))
    return tuple(out)
