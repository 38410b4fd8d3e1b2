"""The `[noise]` table of experiment.toml (a process-noise fit), checked with located errors.

    [fit]
    noise_model = "process"     # "none" (default): deterministic least squares (free-run)

    [noise]
    process = { heaters = [0, 1] }          # state groups (0-based indices), one fitted
                                            # intensity [state unit^2/s] each; "all": one
                                            # group over every state; leave out for none
    disturbances = ["ambient_random_walk"]  # random-walk disturbance states
    walk_initial_sd = 0.0                   # prior sd of the walks at the start
    filter = "auto"                         # auto | kalman (linear device) | ekf
    substeps = 4                            # EKF local linearisations per step
    state_unit = "K"                        # SI unit of the states (intensities' unit)
    k_step = 10                             # horizon (frames) of the k-step prediction
    initial_state = "known"                 # the initial state's spread: "known" (the first
                                            # reading conditioned on), "diffuse", or
                                            # { sd = 0.5 } / { sd = [0.5, 1, 1] } (state units)
    fixed = { "measurement.T1" = 0.1 }      # noise values held fixed (SI)
    initial = { "process.heaters" = 1e-3 }  # starting values (SI) of fitted noise values
    priors = { "measurement.T2" = { median = 0.093, log_sd = 0.5 } }  # log-normal (SI)

The table is read once, here, into a `NoiseTable` (plain values); `noise_model` maps it once
to the estimation engine's configuration objects. The same reader checks a candidate's own
`noise` table (``[[candidates]]`` ... ``noise = {...}``), with the candidate's field path.
"""

from __future__ import annotations

import dataclasses
import math

NOISE_MODELS = ("none", "process")
NOISE_KEYS = {
    "process",
    "disturbances",
    "walk_initial_sd",
    "filter",
    "substeps",
    "state_unit",
    "k_step",
    "initial_state",
    "fixed",
    "initial",
    "priors",
}
DEFAULT_K_STEP = 10
MAX_K_STEP = 10_000  # frames; longer horizons only cost memory (each run is also checked)
MAX_SUBSTEPS = 64
# how the filter starts: the initial state's spread (its mean is the device's initial state
# with the run's settings; free a per-run initial-state path to estimate it)
INITIAL_STATES = ("known", "diffuse")
# [fit] settings of the least-squares fit that mean nothing for the likelihood fit: refused by
# name (never silently ignored), with what to do instead
REFUSED_WITH_PROCESS = {
    "loss": "the likelihood fit has no robust loss (the innovations are Gaussian); remove "
    "[fit] loss, or use noise_model = \"none\" for a robust least-squares fit",
    "method": "the Kalman filter discretises the device exactly between readings (ZOH "
    "inputs); remove [fit] method",
    "solver_max_steps": "the Kalman filter uses no adaptive ODE solver; remove "
    "[fit] solver_max_steps",
}


@dataclasses.dataclass(frozen=True)
class NoiseTable:
    """What `[noise]` says, checked; SI values. `process_groups`: ((name, (state, ...)), ...);
    `fixed`, `initial`: {noise path: SI}; `priors`: {noise path: (median, log_sd)}."""

    process_groups: tuple = ()
    disturbances: tuple = ()
    walk_initial_sd: float = 0.0
    filter: str = "auto"
    substeps: int | None = None
    state_unit: str | None = None
    k_step: int = DEFAULT_K_STEP
    initial_state: object = "known"  # "known", "diffuse" or the sd: a float or a tuple
    fixed: dict = dataclasses.field(default_factory=dict)
    initial: dict = dataclasses.field(default_factory=dict)
    priors: dict = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        """params.json's `noise_model.structure` (read back by `from_json`)."""
        return {
            "process_groups": {g: list(idx) for g, idx in self.process_groups},
            "disturbances": list(self.disturbances),
            "walk_initial_sd": self.walk_initial_sd,
            "filter": self.filter,
            "substeps": self.substeps,
            "state_unit": self.state_unit,
            "k_step": self.k_step,
            "initial_state": (
                list(self.initial_state)
                if isinstance(self.initial_state, tuple)
                else self.initial_state
            ),
            "fixed": dict(self.fixed),
            "initial": dict(self.initial),
            "priors": {k: {"median": m, "log_sd": s} for k, (m, s) in self.priors.items()},
        }

    @classmethod
    def from_json(cls, doc: dict) -> NoiseTable:
        """The inverse of `to_json` (KeyError/TypeError/ValueError on a malformed entry)."""
        sub = doc.get("substeps")
        return cls(
            process_groups=tuple(
                (str(g), tuple(int(i) for i in idx)) for g, idx in doc["process_groups"].items()
            ),
            disturbances=tuple(str(d) for d in doc["disturbances"]),
            walk_initial_sd=float(doc["walk_initial_sd"]),
            filter=str(doc["filter"]),
            substeps=None if sub is None else int(sub),
            state_unit=doc.get("state_unit"),
            k_step=int(doc.get("k_step") or DEFAULT_K_STEP),
            initial_state=_initial_state_json(doc.get("initial_state", "known")),
            fixed={str(k): float(v) for k, v in (doc.get("fixed") or {}).items()},
            initial={str(k): float(v) for k, v in (doc.get("initial") or {}).items()},
            priors={
                str(k): (float(v["median"]), float(v["log_sd"]))
                for k, v in (doc.get("priors") or {}).items()
            },
        )


def check_fit_settings(doc, fitopt: dict, *where) -> None:
    """Refuse, by name, each [fit] setting that does not apply to a process-noise fit."""
    for key, why in REFUSED_WITH_PROCESS.items():
        if key in fitopt:
            raise doc.error(f"does not apply with noise_model = \"process\": {why}", *where, key)


def parse_noise(doc, table, model, spec, *where) -> NoiseTable:
    """`table` (the [noise] table, or a candidate's `noise`, at TOML path `where`) checked
    against `model` (the configured device): a `NoiseTable`, or the first problem as a
    located `InputError`."""
    from greybox._model.device import AbstractLinearDevice, AbstractODEDevice

    where = where or ("noise",)
    if table is None:
        table = {}
    if not isinstance(table, dict):
        raise doc.error("must be a table", *where)
    doc.check_keys(table, NOISE_KEYS, *where)
    if not isinstance(model, AbstractODEDevice):
        raise doc.error(
            f"{spec.name} is not a state-space device (AbstractODEDevice); a process-noise "
            'fit needs one: use noise_model = "none"',
            *where,
        )
    groups = _process_groups(doc, table, int(model.n_states), spec.name, where)
    disturbances = _disturbances(doc, table, where)
    walk_sd = doc.number(table, "walk_initial_sd", *where, default=0.0, nonneg=True)
    filt = doc.string(table, "filter", *where, default="auto", choices=_filters())
    if filt == "kalman" and not isinstance(model, AbstractLinearDevice):
        raise doc.error(
            f"'kalman' needs a linear device and {type(model).__name__} is not linear (with "
            "these [model] options); use 'ekf' or 'auto'",
            *where,
            "filter",
        )
    substeps = None
    if "substeps" in table:
        substeps = doc.integer(table, "substeps", *where, minimum=1)
        if substeps > MAX_SUBSTEPS:
            raise doc.error(
                f"{substeps} is more than {MAX_SUBSTEPS}; 1-8 is usual", *where, "substeps"
            )
    state_unit = doc.string(table, "state_unit", *where, default=None)
    k_step = doc.integer(
        table, "k_step", *where, default=DEFAULT_K_STEP, minimum=1, maximum=MAX_K_STEP
    )
    initial_state = _initial_state(doc, table, int(model.n_states), where)
    fixed = _positive_values(doc, table, "fixed", where)
    initial = _positive_values(doc, table, "initial", where)
    priors = _priors(doc, table, where)
    for a, b, what in (
        (fixed, initial, "both fixed and given an initial value"),
        (fixed, priors, "both fixed and given a prior"),
    ):
        both = sorted(set(a) & set(b))
        if both:
            raise doc.error(f"{both} are {what}", *where)
    noise = NoiseTable(
        process_groups=tuple(groups),
        disturbances=tuple(disturbances),
        walk_initial_sd=float(walk_sd),
        filter=filt,
        substeps=substeps,
        state_unit=state_unit,
        k_step=int(k_step),
        initial_state=initial_state,
        fixed=fixed,
        initial=initial,
        priors=priors,
    )
    try:  # the structure's own rules (a state in two groups, two ambient walks, ...)
        structure(noise)
    except ValueError as err:
        field, _, msg = str(err).partition(": ")
        raise doc.error(msg or field, *where, *([field] if msg else [])) from None
    names = set(noise_paths(noise, model, spec))
    for key, values in (("fixed", fixed), ("initial", initial), ("priors", priors)):
        for path in values:
            if path not in names:
                raise doc.error(
                    "not a noise parameter of this structure; they are: "
                    + ", ".join(sorted(names)),
                    *where,
                    key,
                    path,
                )
    return noise


def _initial_state_json(v):
    if isinstance(v, str):
        return v
    if isinstance(v, list):
        return tuple(float(x) for x in v)
    return float(v)


def _initial_state(doc, table, n: int, where):
    """ "known" | "diffuse" | { sd = x or [x per state] } (state units, >= 0)."""
    v = table.get("initial_state", "known")
    at = (*where, "initial_state")
    if isinstance(v, str):
        if v not in INITIAL_STATES:
            raise doc.error(
                f'{v!r}: give "known", "diffuse" or {{ sd = ... }} (state units)', *at
            )
        return v
    if not isinstance(v, dict) or set(v) != {"sd"}:
        raise doc.error('give "known", "diffuse" or { sd = 0.5 } / { sd = [per state] }', *at)
    sd = v["sd"]
    if isinstance(sd, list):
        if len(sd) != n:
            raise doc.error(f"give one sd per state: the device has {n} states", *at, "sd")
        vals = sd
    else:
        vals = [sd]
    for x in vals:
        if isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x) or x < 0:
            raise doc.error(f"{x!r} must be a finite number >= 0 (state units)", *at, "sd")
    return tuple(float(x) for x in sd) if isinstance(sd, list) else float(sd)


def _filters():
    from greybox.stochastic._sde_device import FILTERS

    return FILTERS


def _process_groups(doc, table, n: int, device: str, where) -> list:
    proc = table.get("process")
    if proc is None:
        return []
    if proc == "all":
        return [("states", tuple(range(n)))]
    if not isinstance(proc, dict):
        raise doc.error(
            'give a table of groups, e.g. { heaters = [0, 1] }, or "all" (one group)',
            *where,
            "process",
        )
    groups = []
    for name, idx in proc.items():
        at = (*where, "process", name)
        if not str(name).isidentifier():
            raise doc.error("a group name: letters, digits and _ only", *at)
        if (
            not isinstance(idx, list)
            or not idx
            or not all(isinstance(i, int) and not isinstance(i, bool) for i in idx)
        ):
            raise doc.error(
                f"give a list of 0-based state indices, e.g. [0, 1] (the device has {n} states)",
                *at,
            )
        bad = [i for i in idx if not 0 <= i < n]
        if bad:
            raise doc.error(
                f"state(s) {bad} do not exist: {device} has {n} states (0 to {n - 1})", *at
            )
        groups.append((str(name), tuple(idx)))
    return groups


def _disturbances(doc, table, where) -> list:
    from greybox.stochastic._sde_device import DISTURBANCES

    dist = table.get("disturbances", [])
    if not isinstance(dist, list) or not all(isinstance(d, str) for d in dist):
        raise doc.error(f"give a list of names from {list(DISTURBANCES)}", *where, "disturbances")
    for i, d in enumerate(dist):
        if d not in DISTURBANCES:
            raise doc.error(
                f"{d!r} is unknown; use any of {', '.join(DISTURBANCES)}", *where, "disturbances", i
            )
    return dist


def _positive_values(doc, table, key: str, where) -> dict:
    sub = table.get(key, {})
    if not isinstance(sub, dict):
        raise doc.error('give a table { "path" = value }', *where, key)
    out = {}
    for path, v in sub.items():
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            raise doc.error("must be a finite number (SI)", *where, key, path)
        if not v > 0:
            raise doc.error(f"{v} must be > 0 (an sd or an intensity)", *where, key, path)
        out[str(path)] = float(v)
    return out


def _priors(doc, table, where) -> dict:
    """priors: { "path" = { median = .., log_sd = .. } } (SI), log-normal, as a free
    parameter's prior_median / prior_log_sd: what the data cannot pin down."""
    sub = table.get("priors", {})
    if not isinstance(sub, dict):
        raise doc.error('give a table { "path" = { median = .., log_sd = .. } }', *where, "priors")
    out = {}
    for path, prior in sub.items():
        at = (*where, "priors", path)
        if not isinstance(prior, dict) or set(prior) != {"median", "log_sd"}:
            raise doc.error("give { median = .., log_sd = .. } (SI, log-normal)", *at)
        median = doc.number(prior, "median", *at, positive=True)
        log_sd = doc.number(prior, "log_sd", *at, positive=True)
        out[str(path)] = (float(median), float(log_sd))
    return out


# --------------------------------------------------------------------------------------------
# NoiseTable -> the estimation engine's objects (the only place that knows both)


def structure(noise: NoiseTable):
    """The engine's noise structure (raises ValueError "field: problem")."""
    from greybox.stochastic._sde_device import NoiseStructure

    return NoiseStructure(
        process_groups=noise.process_groups,
        disturbances=noise.disturbances,
        walk_initial_sd=noise.walk_initial_sd,
        filter=noise.filter,
        substeps=noise.substeps,
    )


def _process_unit(state_unit, states) -> str:
    """The unit of one process-noise intensity on `states`: their shared unit^2/s, where
    `state_unit` (one unit, or one per state) declares it; else "(state unit)^2/s"."""
    shared = {state_unit} if isinstance(state_unit, str) else set()
    if not shared and state_unit and all(i < len(state_unit) for i in states):
        shared = {state_unit[i] for i in states}
    if len(shared) != 1:
        return "(state unit)^2/s"
    unit = shared.pop()
    return f"({unit})^2/s" if any(c in unit for c in "/* ") else f"{unit}^2/s"


def noise_units(spec, noise: NoiseTable) -> dict:
    """Display units of the noise parameters: measurement sd in the output's SI unit, walk
    intensities in (channel unit)^2/s, process intensities in (state unit)^2/s."""
    units = {}
    su = noise.state_unit or spec.state_unit
    for g, states in noise.process_groups:
        units[f"process.{g}"] = _process_unit(su, states)
    for c in spec.outputs:
        units[f"measurement.{c.name}"] = c.si_unit
        units[f"output_walk.{c.name}"] = f"{c.si_unit}^2/s"
    units["output_walk.shared"] = f"{spec.outputs[0].si_unit}^2/s"
    for c in spec.inputs:
        units[f"input_walk.{c.name}"] = f"{c.si_unit}^2/s"
    return units


def _stochastic(noise: NoiseTable, model, spec):
    from greybox.stochastic._sde_device import stochastic_device

    return stochastic_device(model, structure(noise), outputs=spec.outputs, inputs=spec.inputs)


def noise_paths(noise: NoiseTable, model, spec) -> list[str]:
    """Every noise parameter path of this structure on `model` (fixed or fitted)."""
    from greybox.stochastic._sde_device import noise_parameters

    return [p.path for p in noise_parameters(_stochastic(noise, model, spec))]


def initial_state(noise: NoiseTable):
    """The engine's `InitialState` of `noise.initial_state`."""
    from greybox._estimate.noise_models import InitialState

    if noise.initial_state == "known":
        return InitialState()
    if noise.initial_state == "diffuse":
        return InitialState(diffuse=True)
    return InitialState(sd=noise.initial_state)


def noise_model(noise: NoiseTable, model, spec):
    """(stochastic model with the fixed noise values set, `ProcessNoise`, the fitted noise
    `FreeParameter`s with their starting values and priors): what the likelihood fit takes
    beside the device's own free parameters."""
    from greybox._estimate.noise_models import ProcessNoise
    from greybox._model.parameters import set_values
    from greybox.stochastic._sde_device import noise_parameters

    sd = _stochastic(noise, model, spec)
    free = noise_parameters(sd, noise_units(spec, noise))
    sd = set_values(sd, list(noise.fixed), list(noise.fixed.values()))
    out = []
    for p in free:
        if p.path in noise.fixed:
            continue
        kw = {"initial": noise.initial.get(p.path)}
        if p.path in noise.priors:
            kw["prior_median"], kw["prior_log_sd"] = noise.priors[p.path]
        out.append(dataclasses.replace(p, **kw))
    from greybox._estimate.noise_models import ExtendedKalmanFilter, KalmanFilter

    filt = {"auto": None, "kalman": KalmanFilter(), "ekf": ExtendedKalmanFilter(noise.substeps)}
    config = ProcessNoise(
        structure=sd.structure,
        filter=filt[noise.filter],
        initial_state=initial_state(noise),
        k_step=noise.k_step,
    )
    return sd, config, out
