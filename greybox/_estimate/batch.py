"""Batched fits: many devices, one compiled solver (issue 19).

`fit_batch(devices, free)` fits every device exactly as `greybox.fit` would fit it alone, but
runs the Levenberg-Marquardt solves of all devices through ONE compiled function over chunks
of devices (vmapped on an accelerator, one solve after another on a CPU: `map_over_items`):

- devices are grouped by their problem structure (the same free parameters and transforms,
  the same number of runs, the same settings paths, method and loss); within a group every
  run's schedule is padded to widths found jointly (`schedule_widths`: frames, ZOH intervals,
  breakpoints and jump times rounded up to shared bucket sizes; padded frames carry zero
  weight, so they add zero residuals and zero Jacobian rows). Devices with a different number
  of runs form a different group (a padded run would add per-run parameters the data do not
  touch);
- every solve (each start of each device, then the re-fit at the re-estimated noise scale) is
  an item; items are cut into chunks of one fixed size (the last chunk is padded with copies
  of its last item), so every chunk of a group reuses the same compiled function. The chunk
  size is chosen from a memory budget (`bytes_per_item`), by default a share of the device's
  own memory (`device_budget`: the accelerator's limit, or the CPU's physical memory). On a
  CPU the padding items are skipped (`map_over_items`), so the chunk is the largest the
  budget allows whatever the batch's size, and a batch of any size reuses the compiled
  solver of an earlier one (a batch of 5 chevrons after one of 64, 4 starts each: 1.9 s with
  a compile for its own chunk size, 0.07 s without); on an accelerator, where a padding item
  costs a solve, chunks are sized to the work. A wave's problems (a wave: the devices whose
  solves fill one chunk) are gathered from the group's stack and sent to the device once,
  for its starts, its re-fits and its fitted models alike (`_Rows`: each item names its
  row), not once per call;
- the noise handling is `fit`'s, per device: a declared `sigma` (one for every device, or one
  per device name), per-frame `Experiment.sigma`, or estimated: a first solve at the
  frame-difference guess, the robust (MAD) scale of its residuals, then the re-fit from that
  estimate at that scale. Multi-start points are `fit`'s (same seed, same perturbations);
- each device's result is assembled by `fit`'s own `_assemble` (covariance, verdicts,
  fit % per run and output), so a `FitResult` per device is what `fit` would return, to
  rounding (the padding changes only the number of zero rows); the residual tests of the
  devices of a wave run in one vectorised pass
  (`_residuals.analyse_many`: the same statistics and the same seeded shuffles as one
  `analyse` per device, the shuffle orders drawn once and cached);
- the host work (residual tests, assembly) of a solved wave runs in one host thread while
  the compiled solves of the next wave run (`_fit_output_error`).

Pure: no printing, plotting or files; `progress` receives short text lines.
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import math
import os
from collections.abc import Callable, Mapping, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import NamedTuple

import equinox as eqx
import jax
import jax.tree_util as jtu
import numpy as np

from greybox._collector import collect_young, collector_paused
from greybox._compile import jit
from greybox._estimate import fit as _fit
from greybox._estimate.blas import small_blas
from greybox._estimate.problem import best_start, n_starts_for
from greybox._estimate.problem import solve_bytes as bytes_per_item
from greybox._estimate.residuals import analyse_many as analyse_residuals
from greybox._model.data import Experiment
from greybox._model.device import check_method
from greybox._model.freeparams import FreeParameter
from greybox._model.parameters import get_value
from greybox._platform import default_device, map_over_items, on_accelerator
from greybox._simulate.schedules import schedule_runs, schedule_widths, stacked_schedules
from greybox._simulate.simulate import require_x64

MAX_CHUNK = 64  # solves per compiled call on a CPU (one after another there, `map_over_items`):
# more saves little dispatch, and smaller waves overlap the host work better
MAX_CHUNK_ACCELERATOR = 65536  # on a GPU/TPU the memory budget is what limits a chunk
ACCELERATOR_MEMORY_SHARE = 0.5  # of the accelerator memory not in use, for one chunk
CPU_MEMORY_SHARE = 0.25  # of the physical memory, for one chunk
TAPER_MIN = 16  # devices in a batch's last wave from which it is split (`_tapered`)


def device_budget(device=None) -> tuple[float, int]:
    """(bytes one chunk may allocate, most solves per compiled call) on `device` (default:
    the device computations go to, `jax.default_device` honoured, as the chunk solver's own
    CPU/accelerator choice is): from the accelerator's own memory limit (`memory_stats`)
    or, on a CPU, from the physical memory, never a fixed constant."""
    device = device or default_device()
    stats = device.memory_stats() if device.platform != "cpu" else None
    if stats and stats.get("bytes_limit"):
        free = stats["bytes_limit"] - stats.get("bytes_in_use", 0)
        return ACCELERATOR_MEMORY_SHARE * free, MAX_CHUNK_ACCELERATOR
    physical = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    return CPU_MEMORY_SHARE * physical, MAX_CHUNK


@dataclasses.dataclass(frozen=True)
class Device:
    """One device to fit: `name`, its `model` at starting values, its estimation `experiments`
    and, optionally, its own declared noise `sigma` [SI per output] (None: as the batch says)
    and its own `free` list (None: the batch's; a device's list differs from another's only
    by starting values, e.g. per-run offsets started at that device's rest reading, see
    `device_from_spec`)."""

    name: str
    model: object
    experiments: tuple
    sigma: object = None
    free: tuple | None = None

    def __post_init__(self):
        object.__setattr__(self, "experiments", tuple(self.experiments))
        if not self.experiments:
            raise ValueError(f"{self.name}: zero runs; give at least one Experiment")
        for e in self.experiments:
            if not isinstance(e, Experiment):
                raise ValueError(f"{self.name}: experiments must be greybox.Experiment objects")


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """Per-device `FitResult`s (`results`, in the order given) and how the batch ran.

    - `groups`: number of compiled problem structures; `chunk_size`: items per compiled call;
    - `n_calls`: compiled calls made; `bytes_per_item`: the memory estimate that chose it;
    - `worker_s`: on a cluster (`fit_distributed`), the seconds each task spent on its worker.
    """

    results: dict
    groups: int
    chunk_size: int
    n_calls: int
    bytes_per_item: int
    worker_s: tuple = ()

    @property
    def names(self) -> list:
        return list(self.results)

    def __getitem__(self, name):
        return self.results[name]

    def table(self) -> list[dict]:
        return batch_table(self.results)


def batch_table(results: Mapping) -> list[dict]:
    """One row per device: status, what was minimised (`objective`), cost, noise sigma, each
    shared parameter's value, standard error and verdict, per-run parameters by run, and the
    simulation fit % per output (mean over the device's runs, and the worst run)."""
    rows = []
    for name, r in results.items():
        row = {
            "device": name,
            "status": r.status,
            "valid": bool(r.valid),
            "objective": "-log L (one-step prediction errors)"
            if getattr(r, "process_noise", False)
            else "least squares (free-run simulation error)",
            "cost": float(r.cost),
            "n_steps": int(r.n_steps),
        }
        for j, s in enumerate(np.atleast_1d(r.sigma)):
            row[f"sigma[{j}]"] = float(s)
        for p in r.parameters:
            row[f"{p.name}"] = p.value
            row[f"{p.name}:se"] = p.se
            row[f"{p.name}:verdict"] = p.verdict
        fits = np.array([np.atleast_1d(v) for v in r.fit_percent.values()], dtype=float)
        for j in range(fits.shape[1]):
            row[f"fit%[{j}]:mean"] = float(np.nanmean(fits[:, j]))
            row[f"fit%[{j}]:min"] = float(np.nanmin(fits[:, j]))
        rows.append(row)
    return rows


def chunk_size_for(
    bytes_item: int, budget: float, n_items: int, max_chunk=MAX_CHUNK, padding_free=False
) -> int:
    """Chunk size within `budget` bytes (at least 1, at most `max_chunk`).

    Where padding is free (`padding_free`: a CPU, whose chunk skips its padding items,
    `map_over_items`) the largest power of two within both, whatever the work: every batch
    of a structure, of any size, reuses one compiled solver. Elsewhere (vmapped on an
    accelerator, a padding item costs a solve) at most the work, evened out over the chunks
    it needs: the last chunk is padded to the same size (one compiled function), so 32,768
    solves in chunks of 29,000 would pad 25,232 copies; in two chunks of 16,384 none."""
    fit_in = max(1, int(budget // max(bytes_item, 1)))
    if padding_free:
        return 1 << (min(fit_in, int(max_chunk)).bit_length() - 1)
    largest = int(max(1, min(fit_in, max_chunk, n_items)))
    n_chunks = math.ceil(max(int(n_items), 1) / largest)
    return int(math.ceil(max(int(n_items), 1) / n_chunks))


@jit(fast_compile=False)
def _solve_many(rows, index, static, raw, sigma, rtol, atol, max_steps, bound, active=None):
    """`_fit._solve` over a chunk of items (one compiled function; vmapped on an accelerator,
    one solve after another on a CPU: `map_over_items`, which skips the items that `active`
    marks as padding): item k solves the problem at row `index[k]` of `rows` (`_Rows`: the
    stacked problems of the devices of a wave, sent to the device once for all its calls)
    from `raw[k]` at noise `sigma[k]`; `rtol`, `atol`, `max_steps`, `bound`:
    `_fit.solver_settings`."""

    def one(k, r, s):
        # the item's problem sliced once, before the solve's loops (without the barrier XLA
        # slices it again inside them: the re-fits of a wave ran ~40 % slower)
        mine = jax.lax.optimization_barrier(jtu.tree_map(lambda x: x[k], rows))
        return _fit._solve(eqx.combine(mine, static), r, s, rtol, atol, max_steps, bound)

    return map_over_items(one, index, raw, sigma, active=active)


@jit
def _models_many(rows, index, static, raw):
    """`_fit._fitted_models` vmapped over a chunk: item k at row `index[k]` of `rows`, at its
    raw vector `raw[k]`."""

    def one(k, r):
        return _fit._fitted_models(eqx.combine(jtu.tree_map(lambda x: x[k], rows), static), r)

    return eqx.filter_vmap(one)(index, raw)


class _Rows(NamedTuple):
    """The stacked problems of some devices of one group on the device (`leaves`, padded to
    a chunk with copies of the last device's) and each device's row in them (`row_of`)."""

    leaves: object
    row_of: dict


def _rows_of(prepared, devices, chunk) -> _Rows:
    """`_Rows` of `devices` (indices into `prepared`, all of one group, at most `chunk`): one
    gather of the group's stacked leaves and one transfer."""
    padded = devices + [devices[-1]] * (chunk - len(devices))
    leaves = prepared[devices[0]].group.rows([prepared[i].row for i in padded])
    return _Rows(leaves, {i: k for k, i in enumerate(devices)})


def _rows_for(prepared, devices, chunk, rows) -> _Rows:
    """`rows` where they hold every one of `devices` (indices into `prepared`, repeats
    allowed), else the `_Rows` of those devices."""
    devices = list(dict.fromkeys(devices))
    if rows is not None and all(i in rows.row_of for i in devices):
        return rows
    return _rows_of(prepared, devices, chunk)


class _Models(Mapping):
    """{member: (shared model, per-run models)} as the compiled calls returned them (numpy
    leaves, one row a member): a member's own models are unflattened when asked for, by the
    thread that assembles its result."""

    def __init__(self):
        self._at = {}  # member -> (leaves of its chunk, tree, its row)

    def add(self, leaves, tree, row_of):
        for i, k in row_of.items():
            self._at[i] = (leaves, tree, k)

    def __getitem__(self, i):
        leaves, tree, k = self._at[i]
        return jtu.tree_unflatten(tree, [x[k] if isinstance(x, np.ndarray) else x for x in leaves])

    def __iter__(self):
        return iter(self._at)

    def __len__(self):
        return len(self._at)


def _fitted_models(prepared, members, raws, chunk, rows) -> _Models:
    """{member: (shared model, per-run models)} at each member's raw vector (`_Models`), in
    chunks of `chunk` (the last padded, so every chunk reuses one compiled call), from the
    members' `rows` (`_Rows`; a chunk of members they do not hold gathers its own)."""
    static = prepared[members[0]].group.static
    out = _Models()
    for c in range(0, len(members), chunk):
        part = members[c : c + chunk]
        padded = part + [part[-1]] * (chunk - len(part))
        have = _rows_for(prepared, part, chunk, rows)
        index, raw = jax.device_put(
            (np.array([have.row_of[i] for i in padded]), np.stack([raws[i] for i in padded]))
        )
        leaves, tree = jtu.tree_flatten(
            jax.device_get(_models_many(have.leaves, index, static, raw))
        )
        out.add(leaves, tree, {i: k for k, i in enumerate(part)})
    return out


@dataclasses.dataclass
class _Group:
    """Devices of one problem structure: their common static part and their array leaves
    stacked once (numpy, leading axis = member), from which every chunk gathers its rows."""

    members: list
    static: object
    stacked: object
    key: object  # the structure: (tree, which leaves are arrays) of a member's problem
    on_device: object = None  # `stacked` sent to the device ahead (`_build_ahead`), or None

    def rows(self, positions) -> object:
        """The stacked leaves of members at `positions` on the device, in one transfer (a
        `jax.device_put` of the whole tree, not one per leaf); all of them in order: the
        stack sent ahead, where it was."""
        idx = np.asarray(positions)
        if self.on_device is not None and np.array_equal(idx, np.arange(len(self.members))):
            return self.on_device
        if idx.size and np.array_equal(idx, np.arange(idx[0], idx[0] + idx.size)):
            rows = slice(int(idx[0]), int(idx[0]) + idx.size)  # a wave's own rows: views
            return jax.device_put(jtu.tree_map(lambda x: x[rows], self.stacked))
        return jax.device_put(jtu.tree_map(lambda x: np.take(x, idx, axis=0), self.stacked))

    def member(self, row: int) -> object:
        """The problem of the member at stack position `row` (numpy views of its rows): one
        unflatten of the group's flattened problem, its array leaves indexed."""
        leaves, tree, is_array = self._flat
        return jtu.tree_unflatten(tree, [x[row] if a else x for x, a in zip(leaves, is_array)])

    @functools.cached_property
    def _flat(self) -> tuple:
        """(leaves of the whole problem, its tree, which leaves are stacked arrays: all its
        arrays, as `_prepare` partitioned them)."""
        leaves, tree = jtu.tree_flatten(eqx.combine(self.stacked, self.static))
        return leaves, tree, [eqx.is_array(x) for x in leaves]


@dataclasses.dataclass
class _Prepared:
    device: Device
    group: _Group
    row: int  # position in the group's stack
    free: tuple
    source: str
    raw0: np.ndarray
    starts: list
    sigma0: np.ndarray

    @functools.cached_property
    def problem(self):
        """This device's `_fit._Problem` (padded to its group's shapes; numpy views)."""
        return self.group.member(self.row)


def _check(device: Device, free, method):
    """The device's simulation method; a clear error for a misspelt or repeated path."""
    method = check_method(device.model, method)
    paths = [p.path for p in free]
    if len(set(paths)) != len(paths):
        raise ValueError(f"{device.name}: free: a parameter is listed twice ({paths})")
    for p in free:
        get_value(device.model, p.path)
    return method


def _prepare(devices, free, method, loss, huber_c, student_nu, sigma, n_starts, seed, solver):
    """Per-device problems (padded jointly), start points and first noise scales: `_plan`
    then `_build` of every device at once."""
    plan = _plan(devices, free, method, loss, sigma, n_starts)
    part, groups = _build(plan, range(len(plan)), loss, huber_c, student_nu, n_starts, seed, solver)
    return [part[i] for i in range(len(plan))], groups


def _plan(devices, free, method, loss, sigma=None, n_starts=None) -> list:
    """The first part of `_prepare`, for every device at once: the checks
    (`checked_devices`: a bad device late in a large batch is refused before any solve, not
    when its block is built), each device's free parameters (scaled from its start), its
    simulation method, its noise, its runs and the widths their schedules are padded to.
    Returns a `_Planned` per device.

    The widths set the compiled shapes (`schedule_widths` buckets the lengths: one compiled
    solver per structure), so they are found here over all devices, and the problems
    `_build` makes from any subset of them have the shapes they would have had together.
    The schedules themselves are stacked by `_build`, block by block, beside the solves of
    the blocks before: everything here precedes the first solve (2026-11-29, 512 six-run
    devices: 103 -> 73 ms, when this stacked every schedule). Padding is inert: a structure
    whose runs are shorter than another's only carries more zero-weight frames."""
    # the widths of each family of devices whose schedules stack (same input channels and
    # readout quadrature size), from all their runs at once; each block's schedules are
    # stacked to them when `_build` makes its problems
    checked, families = [], {}
    settled = checked_devices(devices, free, method, loss, sigma, n_starts)
    for d, (f, m, noise) in zip(devices, settled):
        runs = schedule_runs(d.model, d.experiments)
        families.setdefault(_family(runs), []).append(len(checked))
        checked.append((d, f, m, noise, runs))
    widths = [None] * len(checked)
    for members in families.values():
        joint = schedule_widths([r for i in members for r in checked[i][4]])
        for i in members:
            widths[i] = joint
    return [
        _Planned(d, f, m, *noise, runs, w) for (d, f, m, noise, runs), w in zip(checked, widths)
    ]


def _family(runs) -> tuple:
    """(input channels, quadrature nodes) of a device's runs: devices of one family stack."""
    _, _, _, offsets, n_u = runs[0]
    return n_u, np.size(offsets)


def _schedules(plan, indices) -> dict:
    """{index: the padded schedules of its runs} for the devices of `plan` at `indices`: one
    stack per family, to the widths `_plan` set from every device of the batch."""
    families = {}
    for i in indices:
        families.setdefault(_family(plan[i].runs), []).append(i)
    out = {}
    for members in families.values():
        joint = stacked_schedules(
            [r for i in members for r in plan[i].runs],
            on_device=False,
            widths=plan[members[0]].widths,
        )
        start = 0
        for i in members:
            n_e = len(plan[i].runs)
            out[i] = {k: v[start : start + n_e] for k, v in joint.items()}
            start += n_e
    return out


def checked_devices(devices, free, method=None, loss="huber", sigma=None, n_starts=None):
    """(free parameters scaled from the device's start, simulation method, (noise source,
    declared sigma)) of every device, after every check of the batch's settings and of each
    device's input that `fit` makes before it solves (`_fit._checked_data`): a bad device is
    refused, by name, before any is solved (`_plan`, and `fit_distributed` before it starts
    a cluster)."""
    if loss not in _fit.LOSSES:
        raise ValueError(f"loss: {loss!r} is unknown; use one of {_fit.LOSSES}")
    paths = [p.path for p in free]
    if len(set(paths)) != len(paths):
        raise ValueError(f"free: a parameter is listed twice ({paths})")
    check_names(devices)
    n_starts_for(n_starts, ())  # refuses a count below 1
    out = []
    for d in devices:
        f = tuple(d.free) if d.free is not None else tuple(free)
        sig_d = d.sigma if d.sigma is not None else _device_sigma(sigma, d.name)
        with _naming(d.name):
            m = _check(d, f, method)
            f = tuple(p.with_scale_from(v) for p, v in zip(f, _fit._start_values(f, d.model)))
            source = _fit._checked_data(d.model, d.experiments, f, sig_d)
        out.append((f, m, (source, sig_d)))
    return out


def check_names(devices) -> None:
    """Refuses a batch where two devices share a name (results are keyed by name)."""
    names = [d.name for d in devices]
    if len(set(names)) != len(names):
        raise ValueError("devices: two devices share a name; names must be unique")


class _Planned(NamedTuple):
    """One device as `_plan` leaves it for `_build`: checked, its free parameters scaled,
    its noise settled, its schedules' widths set with the others'."""

    device: Device
    free: tuple
    method: str
    source: str  # `_fit._noise_source`
    sigma: object  # the declared noise [SI per output], else None
    runs: list  # `schedule_runs` of its experiments
    widths: dict  # `schedule_widths` of its family's runs in the whole batch


@contextlib.contextmanager
def _naming(name: str):
    """A plain ValueError raised inside says it is about device `name` (said once; an
    `InputError` keeps its own type and words)."""
    try:
        yield
    except ValueError as e:
        if type(e) is not ValueError or str(e).startswith(f"{name}: "):
            raise
        raise ValueError(f"{name}: {e}") from e


def _build(plan, indices, loss, huber_c, student_nu, n_starts, seed, solver) -> tuple:
    """The rest of `_prepare`, for the devices of `plan` at `indices` (checked by `_plan`):
    their problems, grouped by structure (each group's array leaves stacked once), start
    points and first noise scales. Returns ({index: `_Prepared`}, groups); a device's entry
    does not depend on which others are built with it."""
    built, scheds = [], _schedules(plan, indices)
    for i in indices:
        d, f, m, source, sig_d, _, _ = plan[i]
        prob = _fit._Problem.build(
            d.model,
            d.experiments,
            f,
            m,
            loss,
            huber_c,
            student_nu,
            *solver,
            padded=scheds[i],
            on_device=False,
        )
        raw0 = _fit._initial_raw(prob, d.model)
        # the starting values live in raw0; `FreeParameter.initial` takes no part in the static
        # part's equality, so every device of the same structure shares one compiled solver
        built.append((i, d, prob, f, source, sig_d, raw0))

    # group by structure (static fields), each group's array leaves stacked once
    # (one flatten per device: its tree and where its array leaves sit are its structure)
    groups: dict = {}
    flat = [jtu.tree_flatten(prob) for _, _, prob, *_rest in built]
    for k, (leaves, tree) in enumerate(flat):
        key = (tree, tuple(eqx.is_array(x) for x in leaves))
        groups.setdefault(key, []).append(k)
    prepared: dict = {}
    out_groups = []
    for key, rows in groups.items():
        dyn, static = eqx.partition(built[rows[0]][2], eqx.is_array)
        columns = [c for c, a in enumerate(key[1]) if a]  # dyn's leaves, in flatten order
        stacked = jtu.tree_unflatten(
            jtu.tree_structure(dyn),
            [np.stack([np.asarray(flat[k][0][c]) for k in rows]) for c in columns],
        )
        group = _Group([built[k][0] for k in rows], static, stacked, key)
        out_groups.append(group)
        for row, k in enumerate(rows):
            i, d, prob, f, source, sig_d, raw0 = built[k]
            rng = np.random.default_rng(seed)
            n = n_starts_for(n_starts, prob.shared)
            starts = [raw0] + [_fit._perturbed(prob, raw0, rng) for _ in range(n - 1)]
            n_y = prob.y.shape[-1]
            if source == "estimated":
                sig = np.full(n_y, _fit._initial_sigma_guess(d.experiments))
            elif source == "declared":
                sig = np.broadcast_to(np.asarray(sig_d, dtype=float), (n_y,)).copy()
            else:
                sig = np.ones(n_y)
            prepared[i] = _Prepared(d, group, row, f, source, raw0, starts, sig)
    return prepared, out_groups


def _fit_process(devices, free, noise, sigma, n_starts, seed, max_steps, chunk_size, say):
    """The process-noise branch of `fit_batch` (`greybox._estimate.likelihood_batch`)."""
    from greybox._estimate import likelihood as _lik
    from greybox._estimate.likelihood_batch import fit_likelihood_batch

    check_names(devices)
    if sigma is not None or any(d.sigma is not None for d in devices):
        raise ValueError(
            "sigma: a ProcessNoise fit estimates the measurement sd (free measurement.* "
            "parameters) or takes it from the stochastic device; give no sigma"
        )
    setups = []  # every device set up (and so checked) before any is solved
    for d in devices:
        f = tuple(d.free) if d.free is not None else free
        with _naming(d.name):
            setup = _lik.setup(
                d.model, d.experiments, f, noise, n_starts=n_starts, seed=seed,
                max_steps=max_steps,
            )  # fmt: skip
        setups.append((d.name, setup))
    results, groups, chunk, calls = fit_likelihood_batch(
        setups, chunk_size=chunk_size, progress=say
    )
    ordered = {d.name: results[d.name] for d in devices}
    return BatchResult(ordered, groups, chunk, calls, 0)


def device_from_spec(
    spec, name: str, experiments, *, model=None, options=None, free=None, sigma=None
) -> Device:
    """A `Device` for `spec`: `model` (default `spec.model(options)`), `free` (default the
    spec's standard free list) with the spec's `start_values` hook applied to these
    experiments, as `greybox fit` does (e.g. per-run camera offsets started at the rest
    reading)."""
    model = spec.model(options) if model is None else model
    free = tuple(spec.free_parameters(options) if free is None else free)
    experiments = tuple(experiments)
    if spec.start_values is not None:
        free = tuple(spec.start_values(model, free, experiments))
    return Device(name, model, experiments, sigma=sigma, free=free)


def _device_sigma(sigma, name):
    if isinstance(sigma, Mapping):
        return sigma.get(name)
    return sigma


def _run_items(prepared, items, chunk, rtol, atol, max_steps, say, label, counter, rows=None):
    """Solve `items` ((device index, raw start, sigma), all of one group) in fixed-size chunks,
    from the devices' `rows` (`_Rows`) where given; returns one host-side output dict per
    item."""
    outputs = []
    n_chunks = math.ceil(len(items) / chunk)
    static = prepared[items[0][0]].group.static
    settings = _fit.solver_settings(rtol, atol, max_steps)
    for c in range(n_chunks):
        part = items[c * chunk : (c + 1) * chunk]
        padded = part + [part[-1]] * (chunk - len(part))
        have = _rows_for(prepared, [i for i, _, _ in part], chunk, rows)
        index, raw, sig, active = jax.device_put(
            (
                np.array([have.row_of[i] for i, _, _ in padded]),
                np.stack([r for _, r, _ in padded]),
                np.stack([s for _, _, s in padded]),
                np.arange(chunk) < len(part),
            )
        )
        out = _solve_many(have.leaves, index, static, raw, sig, *settings, active)
        out = jax.device_get(out)
        counter[0] += 1
        for j in range(len(part)):
            outputs.append({k: v[j] for k, v in out.items()})
        say(f"{label}: chunk {c + 1}/{n_chunks} done ({len(part)} solves)")
    return outputs


def fit_batch(
    devices: Sequence[Device],
    free: Sequence[FreeParameter],
    *,
    method: str | None = None,
    loss: str = "huber",
    huber_c: float = 1.5,
    student_nu: float = 4.0,
    sigma=None,
    n_starts: int | None = None,
    seed: int = 0,
    max_steps: int | None = None,
    rtol: float = 1e-6,
    atol: float = 1e-6,
    solver_rtol: float = 1e-8,
    solver_atol: float = 1e-10,
    solver_max_steps: int = 16384,
    chunk_size: int | None = None,
    memory_budget_bytes: float | None = None,
    progress: Callable[[str], None] | None = None,
    noise=None,
) -> BatchResult:
    """Fit every device of `devices` (each as `greybox.fit(device.model, device.experiments,
    free, ...)` would) with one compiled, vmapped solver per problem structure.

    **Main arguments:**
    - `devices`: `Device`s (unique names).
    - `free`: the `FreeParameter`s, the same for every device (shared across a device's runs
      or per run, as in `fit`).

    **Other arguments:** those of `greybox.fit` (`method`, `loss`, `huber_c`, `student_nu`,
    `n_starts`, `seed`, `max_steps`, `rtol`, `atol`, `solver_*`), applied to every device;
    `sigma` is one declared noise level for all devices, a {device name: sigma} mapping, or
    None (estimated per device, as `fit` does; a device's own `Device.sigma` wins);
    `chunk_size`: solves per compiled call (None: from `memory_budget_bytes` and
    `bytes_per_item`); `memory_budget_bytes`: bytes one call may allocate (None: from the
    device's memory, `device_budget`); `progress`: called with a text line after each chunk.
    `noise`: None or `OutputError(loss, sigma)` (least squares, as above; `max_steps`
    default 200) or `ProcessNoise(...)`: maximum likelihood per device, the likelihood
    back end's compiled BFGS / Newton solver vmapped over devices
    (`greybox._estimate.likelihood_batch`; `max_steps` default that of `fit`; `method`,
    `loss`, `sigma` and the solver tolerances do not apply).

    **Returns:** a `BatchResult` whose `results[name]` is that device's `FitResult`.

    **Raises:** `ValueError` naming the device whose input a `fit` of it would refuse (an
    unknown path, mixed or non-positive noise, fewer readings than parameters), before any
    device is solved.
    """
    require_x64("fit_batch")
    devices = list(devices)
    free = tuple(free)
    if not devices:
        raise ValueError("devices: none given")
    if not free:
        raise ValueError("free: no free parameters; list at least one FreeParameter")
    say = progress or (lambda _msg: None)
    from greybox._estimate import noise_models as nm

    if isinstance(noise, nm.ProcessNoise):
        with collector_paused():  # the results' objects: `greybox._collector`
            return _fit_process(
                devices, free, noise, sigma, n_starts, seed, max_steps, chunk_size, say
            )
    if isinstance(noise, nm.OutputError):
        loss, sigma, huber_c, student_nu = output_error_settings(
            noise, loss, sigma, huber_c, student_nu
        )
    elif noise is not None:
        raise ValueError(
            f"noise: {noise!r} is not a noise model; use greybox.OutputError(...) or "
            "greybox.ProcessNoise(...)"
        )
    # one BLAS thread while a device's problem is small (`blas.small_blas`, as `fit` does)
    largest = max(_fit.jacobian_size_bound(d.experiments, len(d.free or free)) for d in devices)
    with small_blas(largest), collector_paused():
        return _fit_output_error(
            devices, free, method, loss, huber_c, student_nu, sigma, n_starts, seed, max_steps,
            rtol, atol, (solver_rtol, solver_atol, solver_max_steps), chunk_size,
            memory_budget_bytes, say,
        )


def output_error_settings(noise, loss, sigma, huber_c, student_nu) -> tuple:
    """(loss, sigma, huber_c, student_nu) of a least-squares batch: those an `OutputError`
    `noise` carries, else the arguments as given."""
    from greybox._estimate import noise_models as nm

    if not isinstance(noise, nm.OutputError):
        return loss, sigma, huber_c, student_nu
    return (
        noise.loss.name,
        noise.sigma,
        getattr(noise.loss, "c", huber_c),
        getattr(noise.loss, "nu", student_nu),
    )


def _fit_output_error(
    devices, free, method, loss, huber_c, student_nu, sigma, n_starts, seed, max_steps, rtol,
    atol, solver, chunk_size, memory_budget_bytes, say,
) -> BatchResult:
    """`fit_batch` of output-error (least-squares) problems, block by block of devices and,
    within a block's group of one structure, wave by wave (a wave: the devices whose solves
    fill one chunk). This thread runs the compiled calls of each wave (its starts, its
    re-fits at the re-estimated noise, its fitted models) back to back, while one host
    thread builds the blocks' problems ahead of them and then assembles the waves already
    solved (residual tests and `_fit._assemble`): a compiled call releases the interpreter,
    so on two or more cores the host work overlaps the solves instead of preceding or
    following all of them. Only the first block is built before the first solve
    (`_build_blocks`), so progress starts sooner; the wall time is set by the interpreter's
    work either way (DEVELOPING.md, "The core API in one screen": the batch's host work)."""
    max_steps = 200 if max_steps is None else int(max_steps)
    plan = _plan(devices, free, method, loss, sigma, n_starts)
    opts = (float(rtol), float(atol), int(max_steps))
    budget, max_chunk = device_budget()
    if memory_budget_bytes is not None:
        budget = float(memory_budget_bytes)
    padding_free = not on_accelerator()
    counter = [0]
    # chunk size per structure: on a CPU the same for all its blocks; elsewhere there is
    # one block, whose group is the whole structure (what `chunk_size_for` sizes)
    results, item_bytes, chunks = {}, 0, {}
    prepared, solved_devices = [None] * len(plan), 0
    host = ThreadPoolExecutor(max_workers=1, thread_name_prefix="greybox-assemble")
    try:
        blocks = [
            host.submit(
                _build_ahead if padding_free else _build,
                plan, block, loss, huber_c, student_nu, n_starts, seed, solver,
            )  # fmt: skip
            for block in _build_blocks(len(plan), max(max_chunk, chunk_size or 0), padding_free)
        ]
        assembled = []
        for block in blocks:
            part, groups = block.result()
            for i, p in part.items():
                prepared[i] = p
            for group in groups:
                members = group.members
                if group.key not in chunks:  # a structure's first group sizes its chunks
                    n_items = sum(len(prepared[i].starts) for i in members)
                    b = bytes_per_item(prepared[members[0]].problem)
                    chunks[group.key] = (
                        int(chunk_size)
                        if chunk_size
                        else chunk_size_for(b, budget, n_items, max_chunk, padding_free)
                    )
                    item_bytes = max(item_bytes, b)
                    say(
                        f"structure {len(chunks)}: chunks of {chunks[group.key]} solves "
                        f"(~{b * chunks[group.key] / 1e6:.0f} MB each)"
                    )
                chunk = chunks[group.key]
                waves = _waves(members, [len(prepared[i].starts) for i in members], chunk)
                if padding_free and len(blocks) > 1 and block is blocks[-1] and group is groups[-1]:
                    waves = _tapered(waves)
                for wave in waves:
                    label = (
                        f"devices {solved_devices + 1}-{solved_devices + len(wave)} "
                        f"of {len(plan)}"
                    )
                    solved = _solve_wave(prepared, wave, chunk, opts, say, label, counter)
                    solved_devices += len(wave)
                    assembled.append(host.submit(_assemble_wave, prepared, wave, *solved))
                group.on_device = None  # its waves are solved: no second copy kept to the end
        say(f"{len(plan)} devices solved")
        for future in assembled:
            results.update(future.result())
    finally:  # an error or an interrupt: drop the work not yet done, do not wait on it
        host.shutdown(wait=True, cancel_futures=True)
    say(f"{len(results)} devices assembled")
    ordered = {d.name: results[d.name] for d in devices}
    return BatchResult(ordered, len(chunks), max(chunks.values()), counter[0], item_bytes)


def _build_ahead(*args) -> tuple:
    """`_build`, each group's stack then sent to the device by this (the host) thread: on a
    CPU a block is a group and its group one wave, whose solves then take the stack as it is
    instead of the main thread sending it between two compiled calls (~9 ms a wave)."""
    part, groups = _build(*args)
    for group in groups:
        group.on_device = jax.device_put(group.stacked)
    return part, groups


def _build_blocks(n: int, size: int, padding_free: bool) -> list:
    """The devices' indices in the blocks `_build` makes one after another: where a chunk's
    padding is free (a CPU) blocks of `size` devices (the most solves of a chunk, so a
    block of one-start devices fills one), the first of them split in a quarter and the
    rest: the first wave solves while the others are built, and a quarter's build is all
    that precedes it (512 devices: solve_share +0.01); elsewhere one block (an
    accelerator's chunk is sized from the whole group's number of solves, which must be
    known first)."""
    if not padding_free:
        return [range(n)]
    blocks = [range(a, min(a + size, n)) for a in range(0, n, size)]
    first = blocks[0]
    if len(first) >= TAPER_MIN:
        cut = first.start + len(first) // 4
        blocks[:1] = [range(first.start, cut), range(cut, first.stop)]
    return blocks


def _waves(members, n_starts, chunk) -> list:
    """`members` in consecutive waves of at most `chunk` solves (at least one device each)."""
    waves, wave, size = [], [], 0
    for i, k in zip(members, n_starts):
        if wave and size + k > chunk:
            waves.append(wave)
            wave, size = [], 0
        wave.append(i)
        size += k
    return waves + [wave] if wave else waves


def _tapered(waves) -> list:
    """`waves` with the last one split in halves and its second half again (64 devices: 32,
    16, 16): nothing solves while the host thread assembles the last wave, so a shorter one
    ends the batch sooner. For the last block of a batch of several, where a chunk's padding
    is free (a CPU); a wave of fewer than TAPER_MIN devices stays whole (each wave's calls
    cost more than its share of the tail)."""
    if not waves or len(waves[-1]) < TAPER_MIN:
        return waves
    last = waves[-1]
    half, quarter = len(last) // 2, len(last) * 3 // 4
    return [*waves[:-1], last[:half], last[half:quarter], last[quarter:]]


def _solve_wave(prepared, wave, chunk, opts, say, label, counter) -> tuple:
    """The compiled work of one wave: every start, the best start's re-fit at the robust
    noise estimate where the noise is estimated, the fitted models. Returns (runs per device,
    (best index, best solve, sigma, steps) per device, fitted models per device)."""
    rows = _rows_of(prepared, wave, chunk)  # sent once, for every call below
    items = [(i, s, prepared[i].sigma0) for i in wave for s in prepared[i].starts]
    outs = _run_items(prepared, items, chunk, *opts, say, f"{label} starts", counter, rows)
    runs_of, k = {}, 0
    for i in wave:
        n = len(prepared[i].starts)
        runs_of[i] = outs[k : k + n]
        k += n
    best_of, noisy = {}, []
    for i in wave:
        runs = runs_of[i]
        bi = best_start(runs)
        best_of[i] = (bi, runs[bi], prepared[i].sigma0, int(runs[bi]["steps"]))
        if prepared[i].source == "estimated" and np.all(np.isfinite(runs[bi]["raw"])):
            noisy.append(i)
    refit = []
    if noisy:  # their noise from their residuals, in one stacked pass (weights without
        # building their problems here)
        sigmas = _fit._robust_sigmas(
            np.stack([best_of[i][1]["data_residuals"] for i in noisy]),
            np.stack([prepared[i].group.stacked.w[prepared[i].row] for i in noisy]),
            np.stack([prepared[i].sigma0 for i in noisy]),
        )
        refit = [(i, np.asarray(best_of[i][1]["raw"]), sig) for i, sig in zip(noisy, sigmas)]
    if refit:
        outs = _run_items(prepared, refit, chunk, *opts, say, f"{label} refit", counter, rows)
        for (i, _, sig), out in zip(refit, outs):
            bi, _, _, steps = best_of[i]
            best_of[i] = (bi, out, sig, steps + int(out["steps"]))
    raws = {i: np.asarray(best_of[i][1]["raw"]) for i in wave}
    models = _fitted_models(prepared, wave, raws, chunk, rows)
    return runs_of, best_of, models


def _assemble_wave(prepared, wave, runs_of, best_of, models) -> dict:
    """{device name: FitResult} of one solved wave: the residual tests of all its devices in
    one vectorised pass (their shuffles shared), the meats of their sandwich covariances in
    another (`_fit._sandwich_meats`), their runs' scores in a third (`_fit._scored_runs_many`),
    then `_fit._assemble` per device."""
    preds = {i: _fit._predictions(best_of[i][1], prepared[i].device.experiments) for i in wave}
    tests = analyse_residuals(
        [_fit._residual_runs(prepared[i].device.experiments, preds[i]) for i in wave]
    )
    scores = _fit._scored_runs_many(
        [
            (
                prepared[i].device.experiments,
                preds[i],
                _fit._output_sigma(
                    prepared[i].device.experiments,
                    prepared[i].problem.y.shape[-1],
                    prepared[i].source,
                    best_of[i][2],
                ),
            )
            for i in wave
        ]
    )
    finite = [
        (i, (prepared[i].problem, best_of[i][1], prepared[i].device.experiments, r.max_lag))
        for i, r in zip(wave, tests)
        if _fit._finite(best_of[i][1])
    ]
    hac = dict(zip([i for i, _ in finite], _fit._sandwich_meats([f for _, f in finite])))
    out = {}
    for i, residuals, score in zip(wave, tests, scores):
        p = prepared[i]
        bi, best, sig, steps = best_of[i]
        out[p.device.name] = _fit._assemble(
            p.problem,
            best,
            sig,
            steps,
            runs_of[i],
            bi,
            p.raw0,
            p.device.experiments,
            p.free,
            p.source,
            lambda _msg: None,
            models=models[i],
            residuals=residuals,
            hac=hac.get(i),
            scores=score,
        )
    collect_young()  # this wave's objects examined here, beside the next wave's solves
    return out
