"""The problem both objectives of `greybox.fit` share: which numbers are fitted and how they
map to models.

A fit's raw vector is the shared free parameters' raw coordinates, then one block of the
per-run ones per run (`flat_free`). Known per-run values (`Experiment.settings`) form a
settings matrix (runs x paths), applied before the per-run estimates. Starting values are each
parameter's `initial` or else the model's value (after the device's data-based `start_values`
hook); multi-start points move the log/logit coordinates of the shared parameters. The least
squares back end (`greybox._estimate.fit`) and the likelihood back end
(`greybox._estimate.likelihood`) both build on these functions, so labels, start values,
priors and the raw map agree.
"""

from __future__ import annotations

import numpy as np

from greybox._estimate import memory as _memory
from greybox._model.freeparams import apply_raw
from greybox._model.parameters import get_value, set_values
from greybox._simulate.simulate import zoh_scan_kind

DECREMENT_TOL = 1e-9  # Newton decrement (twice the -log L still to gain) at which a likelihood
# start has converged (least squares settles a stalled start at `fit.SETTLED_DECREMENT`)


def check_free(model, free) -> tuple:
    """`free` as a tuple after the checks every fit makes (nonempty, no repeats, paths exist)."""
    free = tuple(free)
    if not free:
        raise ValueError("free: no free parameters; list at least one FreeParameter")
    paths = [p.path for p in free]
    if len(set(paths)) != len(paths):
        raise ValueError(f"free: a parameter is listed twice ({paths})")
    for p in free:
        get_value(model, p.path)  # a clear error for a misspelt path
    return free


def start_values(free, model) -> list[float]:
    """Each parameter's starting value in SI: its `initial`, else the model's value."""
    return [p.initial if p.initial is not None else float(get_value(model, p.path)) for p in free]


def with_scales(free, model) -> tuple:
    """`free` with each unbounded parameter's `scale` derived from its start when None."""
    return tuple(p.with_scale_from(v) for p, v in zip(free, start_values(free, model)))


def split(free) -> tuple:
    """(shared, per-run) parameters, in the order of `free`."""
    return (
        tuple(p for p in free if not p.per_experiment),
        tuple(p for p in free if p.per_experiment),
    )


def flat_free(shared, per_exp, n_exp: int) -> list:
    """The FreeParameter behind each raw coordinate (shared, then per run)."""
    return [*shared] + [p for _ in range(n_exp) for p in per_exp]


def settings_matrix(model, experiments, free) -> tuple:
    """(paths, (E, K) matrix) of the known per-run values; a path both fitted and given as a
    setting is an error."""
    paths = tuple(sorted({k for e in experiments for k in e.settings}))
    # the model's own value where a run does not set it (looked up once per path; the lookup
    # also rejects a path the model does not have)
    default = {k: np.asarray(get_value(model, k), dtype=float) for k in paths}
    matrix = np.array(
        [[e.settings.get(k, default[k]) for k in paths] for e in experiments],
        dtype=float,
    ).reshape(len(experiments), len(paths))
    clash = {p.path for p in free} & set(paths)
    if clash:
        raise ValueError(
            f"settings: {sorted(clash)} are both fitted and given as known per-run "
            "settings; choose one"
        )
    return paths, matrix


def run_model(base, setting_paths, settings_row, per_exp, per_raw_row):
    """The model of one run: `base` (shared estimates applied), its settings, its per-run
    estimates (jit/vmap-safe; the one raw-to-model map is `apply_raw`)."""
    model = set_values(base, list(setting_paths), list(settings_row))
    return apply_raw(model, per_exp, per_raw_row)


def labels(shared, per_exp, experiments) -> tuple:
    """(display name, owning run or None) of each raw coordinate."""
    names = [p.path for p in shared]
    owners = [None] * len(shared)
    for e in experiments:
        names += [f"{p.path}[{e.name}]" for p in per_exp]
        owners += [e.name] * len(per_exp)
    return names, owners


def initial_raw(flat, model) -> np.ndarray:
    """Raw start vector of the flat parameters (bounds checked)."""
    raw = []
    for p, v in zip(flat, start_values(flat, model)):
        p.check_value(v)
        raw.append(float(p.to_raw(float(v))))
    return np.asarray(raw)


def perturbed(shared, raw0: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A multi-start point: shared log/logit coordinates moved by ~x2, linear ones kept."""
    raw = raw0.copy()
    for k, p in enumerate(shared):
        if p.transform != "linear":
            raw[k] += rng.normal(0.0, 0.7)
    return raw


def prior_index(flat) -> list:
    """(raw index, FreeParameter) of every parameter with a prior."""
    return [(k, p) for k, p in enumerate(flat) if p.has_prior]


AUTO_STARTS = 4  # multi-start count when n_starts=None and more than two shared parameters


def n_starts_for(n_starts, shared) -> int:
    """The number of starts: `n_starts`, or `AUTO_STARTS` with more than two shared free
    parameters (else 1) when None."""
    if n_starts is None:
        return AUTO_STARTS if len(shared) > 2 else 1
    if int(n_starts) < 1:
        raise ValueError(f"n_starts: {n_starts} starts; give at least 1 (or None for auto)")
    return int(n_starts)


def finite_starts(runs) -> list[int]:
    """Indices of the starts (solver outputs with "cost" and "raw") that ended finite."""
    return [
        i for i, r in enumerate(runs) if np.isfinite(r["cost"]) and np.all(np.isfinite(r["raw"]))
    ]


def best_start(runs) -> int:
    """Index of the finite start with the lowest cost (0 when none is finite)."""
    finite = finite_starts(runs)
    return min(finite, key=lambda i: float(runs[i]["cost"])) if finite else 0


def solve_bytes(problem) -> int:
    """Estimated peak working bytes of one solve of `problem` (one device, one start), also
    inside a vmapped chunk: `greybox._estimate.memory.solve_bytes` (the model shared with
    `greybox fit`'s pre-check) at the problem's padded shapes."""
    n_exp, n_frames, n_y = problem.y.shape
    return int(
        _memory.solve_bytes(
            runs=n_exp,
            frames=n_frames,
            states=int(problem.model.n_states),
            outputs=n_y,
            inputs=problem.sched["u_grid"].shape[-1],
            raw=problem.n_raw,
            intervals=problem.sched["dt"].shape[1],
            priors=len(problem.priors),
            associative_scan=zoh_scan_kind(problem.sched["dt"].shape[1]) == "associative",
        )
    )
