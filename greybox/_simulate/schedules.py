"""Simulation schedules: the data-only plan of each run, built once, stacked for `jax.vmap`.

A run's frames `t_s` (N,) expand to N q evaluation instants t + offsets (the readout's
exposure quadrature, frame-major). The ZOH path steps a grid of intervals: the sorted
distinct instants, the run's start and the input's switching times between them, each
interval at the input level of its left end (right-continuous), `eval_index` pointing each
instant at its grid state. The adaptive path uses the instants sorted (`eval_t`, `unsort`
back to frame order), the input's breakpoints and levels and its jump times.

Every run of a call is built in the same few numpy calls: the sorts row by row of (runs,
longest) arrays padded with +inf, the rest over the runs' values concatenated, so a batch of
512 six-run devices does not pay a dozen small calls a run. The result is padded for
`jax.vmap` (`bucket_length` rounds each length up, so similar data share one compilation; the
padding is inert: zero-length intervals, the last instant repeated, breakpoints and jump times
past the end). tests/test_schedules.py checks it against a per-run reference implementation.
"""

from __future__ import annotations

import jax
import numpy as np

from greybox._model.data import check_times


def bucket_length(n: int) -> int:
    """Round a length up so similar data share one compilation: to a power of two up to 256,
    then to a multiple of 256 (padding costs scan steps, so large records are padded less)."""
    n = max(int(n), 1)
    if n <= 256:
        return max(16, 1 << (n - 1).bit_length())
    return -(-n // 256) * 256


def fine_bucket_length(n: int) -> int:
    """Round a length up to the next m * 2^e with m in 8..16 (at least 16): eight lengths per
    doubling, so the padding adds at most an eighth. For the Kalman filter's records, whose
    padded steps every evaluation pays for (a 400-frame record: 416, not 512; 600: 640, not
    768), while records a few frames apart still share one compiled filter."""
    n = max(int(n), 16)
    e = max(n.bit_length() - 4, 0)
    return -(-n // (1 << e)) << e  # ceil(n / 2^e) * 2^e


def schedule_for(model, inputs, t_s, *, t_start_s: float = 0.0, on_device: bool = True) -> dict:
    """`model_schedules` of one run (`inputs`, frame times `t_s`, start `t_start_s`)."""
    return model_schedules(model, [(inputs, t_s, t_start_s)], on_device=on_device)


def schedule_row(model, inputs, t_s, *, t_start_s: float = 0.0) -> dict:
    """`schedule_for`'s arrays of the one run, unstacked, in numpy: what one simulation takes
    as its input (taken row by row from device arrays, each key was an operation of its own
    to compile and dispatch: ten small programs compiled at a first `greybox.simulate`)."""
    sched = schedule_for(model, inputs, t_s, t_start_s=t_start_s, on_device=False)
    return {k: v[0] for k, v in sched.items()}


def schedules_for(model, experiments, *, on_device: bool = True) -> dict:
    """`model_schedules` of experiments (anything with `inputs`, `t_s`, `t_start_s`)."""
    return stacked_schedules(schedule_runs(model, experiments), on_device=on_device)


def model_schedules(model, runs, *, on_device: bool = True) -> dict:
    """`stacked_schedules` of runs ((inputs, t_s, t_start_s) each) of `model`."""
    return stacked_schedules(_of_model(model, runs), on_device=on_device)


def schedule_runs(model, experiments) -> list:
    """The runs of experiments of `model` as `stacked_schedules` takes them (for a caller that
    stacks the runs of many models at once)."""
    return _of_model(model, [(e.inputs, e.t_s, e.t_start_s) for e in experiments])


def _of_model(model, runs) -> list:
    """Runs ((inputs, t_s, t_start_s) each) with `model`'s readout quadrature and input
    channels."""
    offsets, _ = model.readout.quadrature()
    return [(*r, offsets, model.n_inputs) for r in runs]


def stacked_schedules(runs, *, on_device: bool = True, widths: dict | None = None) -> dict:
    """The padded schedule arrays of runs ((inputs, t_s, t_start_s, quadrature offsets [s],
    input channels the device takes or None) each; every run's quadrature of one size),
    one row a run: `t_s`, `t_start`, `dt`, `u_grid`, `eval_index`, `eval_t`, `unsort`,
    `breaks`, `levels`, `jump_ts` (see the module docstring). `on_device=False` keeps numpy
    arrays (for callers that stack many before one transfer). `widths`: pad to these
    (`schedule_widths` of runs that include these), so that runs stacked in parts get the
    rows, to the bit, that stacking them all at once gives."""
    out = _stacked(*_checked(runs), widths)
    return jax.device_put(out) if on_device else out


def schedule_widths(runs) -> dict:
    """The padded widths `stacked_schedules(runs)` gives (`frames`, `intervals`, `breaks`,
    `jumps`), after the same checks, without building its arrays: a batch sets its compiled
    shapes from every device's runs at once in a fraction of the time, then stacks each
    block of devices to them (`widths=`) beside the solves of the blocks before."""
    t, breaks, levels, offsets, t_start_s = _checked(runs)
    g = _Grid(t, breaks, levels, offsets, t_start_s)
    v = np.sort(g.rows(), axis=1)
    distinct = np.isfinite(v)
    distinct[:, 1:] &= v[:, 1:] != v[:, :-1]
    n_l = distinct.sum(axis=1) - 1  # intervals between a run's distinct grid points
    return _widths(g, int(n_l.max(initial=0)))


def _checked(runs) -> tuple:
    """(frame times, breakpoints, levels, quadrature offsets (runs, q), starts) of runs, each
    checked: refused with the fault named unless they stack."""
    if not runs:
        raise ValueError("runs: none given; a schedule needs at least one run")
    t = _frame_times([r[1] for r in runs])
    pw = [r[0].to_piecewise() for r in runs]
    levels = [p.values.reshape(len(p.times_s), -1) for p in pw]
    for lv, r in zip(levels, runs):
        if r[4] is not None and lv.shape[1] != r[4]:
            raise ValueError(
                f"inputs: the device takes {r[4]} input channel(s) but the waveform has "
                f"{lv.shape[1]}"
            )
    if len({lv.shape[1] for lv in levels}) > 1:
        raise ValueError("inputs: the runs' waveforms have different numbers of channels")
    offsets = [np.asarray(r[3], dtype=float).reshape(-1) for r in runs]
    if len({o.size for o in offsets}) > 1:
        raise ValueError("schedules: their exposure quadratures differ; stack them apart")
    return (
        t,
        [p.times_s for p in pw],
        levels,
        np.stack(offsets),
        np.array([float(r[2]) for r in runs]),
    )


def _frame_times(times) -> list[np.ndarray]:
    """Each run's frame times as a float array, refused (`check_times`) unless finite and
    strictly increasing: checked over all runs at once, a run at a time only to name the
    fault."""
    t = [np.asarray(x, dtype=float).reshape(-1) for x in times]
    flat = np.concatenate(t)
    sizes = np.array([x.size for x in t])
    if sizes.min() == 0:
        return [check_times(x) for x in t]  # raises for the first empty run
    step = np.diff(flat)
    step[np.cumsum(sizes)[:-1] - 1] = 1.0  # from one run to the next: no order asked
    if not np.all(np.isfinite(flat)) or np.any(step <= 0):
        return [check_times(x) for x in t]  # raises for the first bad run
    return t


def _run_ids(sizes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(the run of each element of runs of `sizes` concatenated, each run's first element)."""
    first = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.intp)
    return np.repeat(np.arange(sizes.size), sizes), first


def _padded(values, sizes, width: int, after) -> np.ndarray:
    """(runs, `width`, ...) of the concatenated `values` (..., trailing shape) of runs of
    `sizes`, one row a run, the rest of each row from `after` (broadcast to that shape)."""
    values = np.asarray(values)
    shape = (sizes.size, width, *values.shape[1:])
    out = np.array(np.broadcast_to(after, shape), dtype=values.dtype)
    if values.ndim == 1:  # a mask fills row by row, in the concatenated order: 6x the scatter
        out[np.arange(width) < sizes[:, None]] = values
        return out
    run_of, first = _run_ids(sizes)
    out[run_of, np.arange(run_of.size) - first[run_of]] = values
    return out


def _stable_order(rows) -> np.ndarray:
    """Each row's stable sort order (ties keep their column order)."""
    return np.argsort(rows, axis=1, kind="stable")


class _Grid:
    """What both `_stacked` and `schedule_widths` take from checked runs: the instants, each
    run's start, last instant and switching times inside, and the counts of each."""

    def __init__(self, t, breaks, levels, offsets, t_start_s):
        self.n_runs, self.q = len(t), offsets.shape[1]
        self.n_f = np.array([x.size for x in t])
        self.n_q = self.n_f * self.q
        rid_f, self.f0 = _run_ids(self.n_f)
        _, self.q0 = _run_ids(self.n_q)
        self.quad = (np.concatenate(t)[:, None] + offsets[rid_f]).reshape(-1)
        self.n_b = np.array([b.size for b in breaks])
        rid_b, self.b0 = _run_ids(self.n_b)
        self.b_all, self.lv_all = np.concatenate(breaks), np.concatenate(levels)
        b0 = self.b0
        self.start = np.minimum(
            np.minimum(t_start_s, np.minimum.reduceat(self.quad, self.q0)), self.b_all[b0]
        )
        self.last = np.maximum.reduceat(self.quad, self.q0)
        # a level switches where it differs from the one before (0 before the first breakpoint)
        previous = np.empty_like(self.lv_all)
        previous[1:] = self.lv_all[:-1]
        previous[b0] = 0.0
        switch = np.any(self.lv_all != previous, axis=1)
        edges, rid_e = self.b_all[switch], rid_b[switch]
        inside = (edges > self.start[rid_e]) & (edges < self.last[rid_e])
        self.edges, rid_e = edges[inside], rid_e[inside]
        self.n_e = np.bincount(rid_e, minlength=self.n_runs)
        self.n_qmax, self.n_emax = int(self.n_q.max()), int(self.n_e.max(initial=0))
        self.q_rows = _padded(self.quad, self.n_q, self.n_qmax, np.inf)

    def rows(self) -> np.ndarray:
        """Each run's start, edges and instants in one row, padded with +inf (sorts last)."""
        edge_rows = _padded(self.edges, self.n_e, self.n_emax, np.inf)
        return np.concatenate([self.start[:, None], edge_rows, self.q_rows], axis=1)


def _widths(g: _Grid, n_lmax: int) -> dict:
    """The padded widths of runs `g` whose longest grid has `n_lmax` intervals."""
    return {
        "frames": bucket_length(g.n_f.max()),
        "intervals": bucket_length(n_lmax),
        "breaks": bucket_length(g.n_b.max()),
        "jumps": bucket_length(g.n_emax),
    }


def _stacked(t, breaks, levels, offsets, t_start_s, widths=None) -> dict:
    """`stacked_schedules` of checked runs: frame times `t`, input breakpoints `breaks` and
    `levels` (of one channel count), quadrature `offsets` (runs, q), starts `t_start_s`,
    padded to `widths` (None: their own). Per run exactly as one run alone would give:
    instants t + offsets, the start min(t_start_s, first instant, first breakpoint), the
    switching times inside (start, last instant)."""
    g = _Grid(t, breaks, levels, offsets, t_start_s)
    n_runs, q, n_f, n_q, f0, q0 = g.n_runs, g.q, g.n_f, g.n_q, g.f0, g.q0
    n_b, b0, b_all, lv_all, start, last = g.n_b, g.b0, g.b_all, g.lv_all, g.start, g.last
    edges, n_e, n_qmax, n_emax, q_rows = g.edges, g.n_e, g.n_qmax, g.n_emax, g.q_rows

    # the grid: each run's start, edges and instants in one row, sorted, repeats dropped
    rows = g.rows()
    order = _stable_order(rows)
    v = np.take_along_axis(rows, order, axis=1)
    distinct = np.isfinite(v)
    distinct[:, 1:] &= v[:, 1:] != v[:, :-1]
    rank = np.empty(v.shape, dtype=np.intp)  # each value's place among its row's distinct ones
    np.put_along_axis(rank, order, np.cumsum(distinct, axis=1) - 1, axis=1)
    real_q = np.arange(n_qmax) < n_q[:, None]  # the instants, not the padding
    eval_index = rank[:, 1 + n_emax :][real_q]
    grid, rid_g = v[distinct], np.nonzero(distinct)[0]
    within = rid_g[1:] == rid_g[:-1]  # consecutive grid points of one run: an interval
    dt, left, rid_l = (grid[1:] - grid[:-1])[within], grid[:-1][within], rid_g[:-1][within]
    n_l = np.bincount(rid_l, minlength=n_runs)

    # each interval's level: the run's breakpoints at or before its left end, counted by
    # sorting them with the left ends (breakpoints in the first columns: first where tied)
    n_bmax, n_lmax = int(n_b.max()), int(n_l.max(initial=0))
    b_rows, l_rows = _padded(b_all, n_b, n_bmax, np.inf), _padded(left, n_l, n_lmax, np.inf)
    merged = np.concatenate([b_rows, l_rows], axis=1)
    is_break = (np.arange(n_bmax + n_lmax) < n_bmax) & np.isfinite(merged)
    order = _stable_order(merged)
    counted = np.empty(merged.shape, dtype=np.intp)
    np.put_along_axis(
        counted, order, np.cumsum(np.take_along_axis(is_break, order, axis=1), axis=1), axis=1
    )
    idx = counted[:, n_bmax:][np.arange(n_lmax) < n_l[:, None]] - 1
    u_grid = np.where((idx >= 0)[:, None], lv_all[b0[rid_l] + np.clip(idx, 0, None)], 0.0)

    # the instants sorted (stable: ties keep frame order) and back
    sorted_q = _stable_order(q_rows)
    eval_t = np.take_along_axis(q_rows, sorted_q, axis=1)[real_q]
    unsort = np.empty_like(sorted_q)
    np.put_along_axis(unsort, sorted_q, np.arange(n_qmax)[None, :], axis=1)

    # padded for vmap: frames and instants repeat their run's last, intervals are empty,
    # breakpoints and jump times lie past the run's end (`last`, its latest instant)
    own = _widths(g, n_lmax)
    if widths is not None:
        if any(widths[k] < own[k] for k in own):
            raise ValueError(f"widths: {widths} are narrower than these runs need ({own})")
        own = widths
    n_frames, n_int = own["frames"], own["intervals"]
    n_breaks, n_jumps = own["breaks"], own["jumps"]
    t_all = np.concatenate(t)

    def past(width, sizes):  # t_end + 1, t_end + 2, ... after each run's own entries
        return (last + 1.0)[:, None] + (np.arange(width)[None, :] - sizes[:, None])

    return {
        "t_s": _padded(t_all, n_f, n_frames, t_all[f0 + n_f - 1][:, None]),
        "t_start": start,
        "dt": _padded(dt, n_l, n_int, 0.0),
        "u_grid": _padded(u_grid, n_l, n_int, 0.0),
        "eval_index": _padded(eval_index, n_q, n_frames * q, eval_index[q0 + n_q - 1][:, None]),
        "eval_t": _padded(eval_t, n_q, n_frames * q, last[:, None]),
        "unsort": _padded(unsort[real_q], n_q, n_frames * q, (n_q - 1)[:, None]),
        "breaks": _padded(b_all, n_b, n_breaks, past(n_breaks, n_b)),
        "levels": _padded(lv_all, n_b, n_breaks, lv_all[b0 + n_b - 1][:, None, :]),
        "jump_ts": _padded(edges, n_e, n_jumps, past(n_jumps, n_e)),
    }
