"""`fit_batch(..., noise=ProcessNoise(...))`: many devices of one structure fitted by maximum
likelihood with the likelihood back end's one compiled optimiser, over chunks of devices.

- Each device is set up exactly as `greybox.fit` sets it up alone (`likelihood.setup`: the
  filtered `StochasticDevice`, data-based noise starts, scales, multi-start points).
- Devices whose objectives have the same static part (device class and structural fields,
  free list, noise structure) and the same array shapes (frames, filter steps, runs) form a
  group. The filter's step grid is the union of a run's frame times and input switches, so a
  padded run would have to be a run of dummy steps that leave the state and the likelihood
  unchanged, which `FilterGrid` does not offer; runs of different lengths therefore form
  different groups rather than being padded.
- Every start of every device of a group is an item; items run in chunks of one size through
  `likelihood._newton`, one after another on a CPU and vmapped on an accelerator
  (`map_over_items`; vmapped, its `lax.while_loop` runs until the last item of a chunk has
  converged, each pass evaluating one point for every item whatever phase it is in; an
  item that is done keeps its state, so each item's result is the one the unbatched solve
  gives, to rounding). The last chunk is padded with copies of its last item,
  so a group compiles once. Reviving vanished noise intensities (`likelihood.revive`) reuses
  the same compiled chunk.
- Each device's `FitResult` is assembled as `fit` assembles it (`likelihood.assemble_many`:
  verdicts, covariance, per-run diagnostics host-side and per device; the residual tests of
  a group's devices in one vectorised pass, their shuffles shared).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from greybox._compile import jit
from greybox._estimate import likelihood as _lik
from greybox._platform import map_over_items

MAX_CHUNK = 64  # likelihood solves per compiled call (each carries its own Hessian work)


@jit
def _newton_many(dynamic, static, raws, budget):
    """`likelihood._newton` over a chunk of stacked objectives and start points (vmapped on
    an accelerator, one after another on a CPU: `map_over_items`)."""

    def one(dyn, raw):
        return _lik._newton(eqx.combine(dyn, static), raw, budget)

    return map_over_items(one, dynamic, raws)


def _key(obj) -> tuple:
    dyn, static = eqx.partition(obj, eqx.is_array)
    leaves, tree = jtu.tree_flatten(dyn)
    return (tree, jtu.tree_structure(static), static, tuple((x.shape, x.dtype) for x in leaves))


def fit_likelihood_batch(
    named_setups, *, chunk_size=None, progress=None
) -> tuple[dict, int, int, int]:
    """({name: FitResult}, groups, chunk size, compiled calls) for `named_setups`
    ((name, `likelihood.Setup`), ...)."""
    say = progress or (lambda _m: None)
    groups: dict = {}
    for i, (_, su) in enumerate(named_setups):
        groups.setdefault(_key(su.obj), []).append(i)
    results, calls, chunk_used = {}, 0, 0
    for g, members in enumerate(groups.values()):
        sus = [named_setups[i][1] for i in members]
        static = eqx.partition(sus[0].obj, eqx.is_array)[1]
        stacked = jtu.tree_map(
            lambda *xs: np.stack([np.asarray(x) for x in xs]),
            *[eqx.filter(su.obj, eqx.is_array) for su in sus],
        )
        budget = jnp.asarray(max(su.budget for su in sus))
        if len({su.budget for su in sus}) != 1:
            raise ValueError("max_steps: every device of a batch takes the same step budget")
        items = [(m, s) for m, su in enumerate(sus) for s in su.starts]
        n_items = len(items)
        chunk = int(chunk_size) if chunk_size else min(MAX_CHUNK, n_items)
        chunk = max(1, math.ceil(n_items / math.ceil(n_items / chunk)))
        chunk_used = max(chunk_used, chunk)
        label = f"group {g + 1}/{len(groups)}"
        say(f"{label}: {len(sus)} devices, {n_items} likelihood solves, chunks of {chunk}")

        def solve(pairs, label=label, stacked=stacked, static=static, budget=budget):
            """One solver output per (member, raw start), in chunks of `chunk`."""
            nonlocal calls
            outs = []
            for c in range(0, len(pairs), chunk):
                part = pairs[c : c + chunk]
                part = part + [part[-1]] * (chunk - len(part))
                idx = np.asarray([m for m, _ in part])
                dyn = jtu.tree_map(lambda x: jnp.asarray(np.take(x, idx, axis=0)), stacked)
                raws = jnp.asarray(np.stack([np.asarray(r, dtype=float) for _, r in part]))
                out = jax.device_get(_newton_many(dyn, static, raws, budget))
                calls += 1
                kept = min(chunk, len(pairs) - c)
                outs += [{k: v[j] for k, v in out.items()} for j in range(kept)]
            say(f"{label}: {len(pairs)} solves done")
            return outs

        first = solve(items)
        # revive per item: an item's "member" in `revive`'s solve is its own index here
        flats = [sus[m].flat for m, _ in items]
        raw0s = [sus[m].raw0 for m, _ in items]
        names = [f"{named_setups[members[m]][0]} start {k + 1}" for m, k in _start_numbers(items)]
        runs = _lik.revive(
            first,
            flats,
            raw0s,
            lambda pairs: solve([(items[i][0], r) for i, r in pairs]),
            lambda i, raws: _lik.totals_at(sus[items[i][0]].obj, raws),
            say,
            names,
        )
        ends = np.cumsum([len(su.starts) for su in sus])
        per_device = [(su, runs[e - len(su.starts) : e]) for su, e in zip(sus, ends)]
        for m, result in enumerate(_lik.assemble_many(per_device, lambda _m: None)):
            results[named_setups[members[m]][0]] = result
        say(f"{label}: {len(sus)} devices assembled")
    return results, len(groups), chunk_used, calls


def _start_numbers(items):
    """(member, start number within the member) of each item."""
    seen: dict = {}
    out = []
    for m, _ in items:
        out.append((m, seen.get(m, 0)))
        seen[m] = seen.get(m, 0) + 1
    return out
