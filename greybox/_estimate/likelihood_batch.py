"""`fit_batch(..., noise=ProcessNoise(...))`: many devices of one structure fitted by maximum
likelihood with the likelihood back end's one compiled optimiser, over chunks of devices.

- Each device is set up exactly as `greybox.fit` sets it up alone (`likelihood.setup`: the
  filtered `StochasticDevice`, data-based noise starts, scales, multi-start points).
- Devices whose objectives have the same static part (device class and structural fields,
  free list, noise structure) and the same array shapes (frames, filter steps, runs) form a
  group. Each device's records are padded to bucketed lengths (`likelihood.setup`:
  `FilterGrid.padded`, steps of zero length that leave the state and the likelihood exactly
  as they were, frames unread), so devices whose records differ by a few frames are one
  group.
- Every start of every device of a group is an item; items run in chunks of one size through
  `likelihood._newton`, one after another on a CPU and vmapped on an accelerator
  (`map_over_items`; vmapped, its `lax.while_loop` runs until the last item of a chunk has
  converged, each pass evaluating one point for every item whatever phase it is in; an
  item that is done keeps its state, so each item's result is the one the unbatched solve
  gives, to rounding). The last chunk is padded with copies of its last item,
  so a group compiles once; chunks are sized as the output-error batch sizes them
  (`batch.chunk_size_for`, within the device's memory by `likelihood.solve_bytes`): on a CPU
  the padding items are skipped, so every chunk there has one size (`MAX_CHUNK` unless memory
  allows fewer) and a batch of any size reuses an earlier batch's compiled solver.
  Reviving vanished noise intensities (`likelihood.revive`) reuses the same compiled chunk.
- Each device's `FitResult` is assembled as `fit` assembles it (`likelihood.assemble_many`:
  verdicts, covariance, per-run diagnostics host-side and per device; the residual tests of
  a chunk's devices in one vectorised pass, their shuffles shared), in a host thread while
  the next chunk solves (`_Assembler`).
"""

from __future__ import annotations

import math
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np

from greybox._compile import jit
from greybox._estimate import likelihood as _lik
from greybox._estimate.batch import chunk_size_for, device_budget
from greybox._platform import map_over_items, on_accelerator

MAX_CHUNK = 64  # likelihood solves per compiled call (each carries its own Hessian work)


@jit
def _newton_many(dynamic, static, raws, budget, active):
    """`likelihood._newton` over a chunk of stacked objectives and start points (vmapped on
    an accelerator, one after another on a CPU: `map_over_items`, which skips the items that
    `active` marks as padding)."""

    def one(dyn, raw):
        return _lik._newton(eqx.combine(dyn, static), raw, budget)

    return map_over_items(one, dynamic, raws, active=active)


def _key(obj) -> tuple:
    dyn, static = eqx.partition(obj, eqx.is_array)
    leaves, tree = jtu.tree_flatten(dyn)
    return (tree, jtu.tree_structure(static), static, tuple((x.shape, x.dtype) for x in leaves))


def fit_likelihood_batch(
    named_setups, *, chunk_size=None, progress=None
) -> tuple[dict, int, int, int]:
    """({name: FitResult}, groups, chunk size, compiled calls) for `named_setups`
    ((name, `likelihood.Setup`), ...). This thread runs the compiled chunks one after
    another while one host thread assembles the devices already solved (`_Assembler`): a
    compiled call releases the interpreter, so on two or more cores the assembly of one
    chunk's devices overlaps the next chunk's solves, as in `fit_batch`'s output-error
    path."""
    say = progress or (lambda _m: None)
    groups: dict = {}
    for i, (_, su) in enumerate(named_setups):
        groups.setdefault(_key(su.obj), []).append(i)
    results, calls, chunk_used = {}, 0, 0
    host = ThreadPoolExecutor(max_workers=1, thread_name_prefix="greybox-assemble")
    try:
        assembled = []
        for g, members in enumerate(groups.values()):
            sus = [named_setups[i][1] for i in members]
            names = [named_setups[i][0] for i in members]
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
            if chunk_size:
                chunk = int(chunk_size)
            else:  # as the output-error batch sizes its chunks (padding skipped on a CPU)
                memory, _ = device_budget()
                item = _lik.solve_bytes(sus[0])
                chunk = chunk_size_for(item, memory, n_items, MAX_CHUNK, not on_accelerator())
            chunk_used = max(chunk_used, chunk)
            label = f"group {g + 1}/{len(groups)}"
            say(f"{label}: {len(sus)} devices, {n_items} likelihood solves, chunks of {chunk}")

            def solve(pairs, stacked=stacked, static=static, budget=budget, chunk=chunk):
                """One solver output per (member, raw start), in chunks of `chunk`."""
                nonlocal calls
                outs = []
                for c in range(0, len(pairs), chunk):
                    part = pairs[c : c + chunk]
                    part = part + [part[-1]] * (chunk - len(part))
                    idx = np.asarray([m for m, _ in part])
                    dyn = jtu.tree_map(lambda x: jnp.asarray(np.take(x, idx, axis=0)), stacked)
                    raws = jnp.asarray(np.stack([np.asarray(r, dtype=float) for _, r in part]))
                    kept = min(chunk, len(pairs) - c)
                    active = jnp.asarray(np.arange(chunk) < kept)
                    out = jax.device_get(_newton_many(dyn, static, raws, budget, active))
                    calls += 1
                    outs += [{k: v[j] for k, v in out.items()} for j in range(kept)]
                return outs

            group = _Assembler(sus, names, items, solve, host, say)
            n_chunks = math.ceil(n_items / chunk)
            for c in range(n_chunks):  # the same chunks as one call of `solve(items)`
                group.solved(solve(items[c * chunk : (c + 1) * chunk]))
                say(f"{label}: chunk {c + 1}/{n_chunks} solved")
            assembled += group.finish()
        for future in assembled:
            results.update(future.result())
    finally:  # an error or an interrupt: drop the devices not yet assembled
        host.shutdown(wait=True, cancel_futures=True)
    say(f"{len(results)} devices assembled")
    return {name: results[name] for name, _ in named_setups}, len(groups), chunk_used, calls


class _Assembler:
    """The devices of one group, assembled as their solves come in: a device whose starts are
    all solved goes to the host thread at once (`likelihood.assemble_many`, the devices of
    one chunk together), unless a noise intensity vanished in one of its starts; those
    devices are revived together at the end (`likelihood.revive`: the same items, in the
    same order, as reviving the whole group at once, so the same re-solves in the same
    chunks) and then assembled."""

    def __init__(self, sus, names, items, solve, host, say):
        self.sus, self.names, self.items = sus, names, items
        self.solve, self.host, self.say = solve, host, say
        ends = np.cumsum([len(su.starts) for su in sus])
        self.spans = [(int(e) - len(su.starts), int(e)) for su, e in zip(sus, ends)]
        self.outs: list = []
        self.next = 0  # the first device not yet handed on
        self.deferred: list = []
        self.futures: list = []

    def solved(self, outs) -> None:
        """Take the next solver outputs (in item order) and hand on the devices now complete."""
        self.outs += outs
        ready = []
        while self.next < len(self.sus) and self.spans[self.next][1] <= len(self.outs):
            m = self.next
            lo, hi = self.spans[m]
            su = self.sus[m]
            if any(_lik._gone(su.flat, su.raw0, self.outs[i]["raw"]) for i in range(lo, hi)):
                self.deferred.append(m)
            else:
                ready.append((m, self.outs[lo:hi]))
            self.next += 1
        self._submit(ready)

    def finish(self) -> list:
        """Revive the deferred devices, hand them on; the futures of every device's result."""
        if self.deferred:
            idx = [i for m in self.deferred for i in range(*self.spans[m])]
            members = [self.items[i][0] for i in idx]
            labels = [f"{self.names[m]} start {k + 1}" for m, k in _start_numbers(members)]
            runs = _lik.revive(
                [self.outs[i] for i in idx],
                [self.sus[m].flat for m in members],
                [self.sus[m].raw0 for m in members],
                lambda pairs: self.solve([(members[j], r) for j, r in pairs]),
                lambda j, raws: _lik.totals_at(self.sus[members[j]].obj, raws),
                self.say,
                labels,
            )
            ready, at = [], 0
            for m in self.deferred:
                n = len(self.sus[m].starts)
                ready.append((m, runs[at : at + n]))
                at += n
            self._submit(ready)
        return self.futures

    def _submit(self, ready) -> None:
        if not ready:
            return
        sus = [(self.sus[m], runs) for m, runs in ready]
        names = [self.names[m] for m, _ in ready]

        def assemble():
            return dict(zip(names, _lik.assemble_many(sus, lambda _m: None)))

        self.futures.append(self.host.submit(assemble))


def _start_numbers(members):
    """(member, start number within the member) of each item's member."""
    seen: dict = {}
    out = []
    for m in members:
        out.append((m, seen.get(m, 0)))
        seen[m] = seen.get(m, 0) + 1
    return out
