"""The stacked schedule builder (`greybox._simulate.schedules.stacked_schedules`, every run of a
call in one pass) against a per-run reference written plainly below: the ZOH grid by
`np.unique`, the levels and instants by `np.searchsorted`, each run padded in a loop. They
must agree exactly (every array, shape and dtype) on random runs: irregular frames, one to
three quadrature nodes, breakpoints before, between and on the instants, repeated levels,
starts before or at the first instant, one or two channels, runs of different lengths
stacked together. This reference was greybox's own implementation up to 2026-11-28.

A batch stacks its devices' runs block by block to the widths of all of them
(`schedule_widths`, `widths=`): every part must give, to the bit, the rows of stacking all at
once, and the widths must be the joint stack's own."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from greybox._model.waveforms import PiecewiseConstant
from greybox._simulate.schedules import bucket_length, schedule_widths, stacked_schedules


def reference_run(inputs, t, offsets, t_start_s):
    levels = inputs.values.reshape(len(inputs.times_s), -1)
    quad_t = (t[:, None] + offsets[None, :]).reshape(-1)
    t_start = float(min(t_start_s, quad_t.min(), inputs.times_s[0]))
    edges = inputs.switch_times()
    edges = edges[(edges > t_start) & (edges < quad_t.max())]
    eval_order = np.argsort(quad_t, kind="stable")
    grid = np.unique(np.concatenate([[t_start], edges, quad_t]))
    idx = np.searchsorted(inputs.times_s, grid[:-1], side="right") - 1
    return dict(
        t_s=t,
        t_start=t_start,
        dt=np.diff(grid),
        u_grid=np.where((idx >= 0)[:, None], levels[np.clip(idx, 0, None)], 0.0),
        eval_index=np.searchsorted(grid, quad_t),
        eval_t=quad_t[eval_order],
        eval_order=eval_order,
        breaks=inputs.times_s.copy(),
        levels=levels,
        jump_ts=edges,
    )


def reference(runs, offsets):
    s = [reference_run(w, t, offsets, t0) for w, t, t0 in runs]
    q, r = offsets.size, len(s)
    n_frames = bucket_length(max(x["t_s"].size for x in s))
    n_int = bucket_length(max(x["dt"].size for x in s))
    n_breaks = bucket_length(max(x["breaks"].size for x in s))
    n_jumps = bucket_length(max(x["jump_ts"].size for x in s))
    n_u = s[0]["levels"].shape[1]
    out = {
        "t_s": np.empty((r, n_frames)),
        "t_start": np.array([x["t_start"] for x in s]),
        "dt": np.zeros((r, n_int)),
        "u_grid": np.zeros((r, n_int, n_u)),
        "eval_index": np.empty((r, n_frames * q), dtype=np.intp),
        "eval_t": np.empty((r, n_frames * q)),
        "unsort": np.empty((r, n_frames * q), dtype=np.intp),
        "breaks": np.empty((r, n_breaks)),
        "levels": np.empty((r, n_breaks, n_u)),
        "jump_ts": np.empty((r, n_jumps)),
    }
    for i, x in enumerate(s):
        n_f, n_e, n_l = x["t_s"].size, x["eval_t"].size, x["dt"].size
        n_b, n_j = x["breaks"].size, x["jump_ts"].size
        t_end = x["eval_t"][-1]
        out["t_s"][i, :n_f], out["t_s"][i, n_f:] = x["t_s"], x["t_s"][-1]
        out["dt"][i, :n_l] = x["dt"]
        out["u_grid"][i, :n_l] = x["u_grid"]
        out["eval_index"][i, :n_e] = x["eval_index"]
        out["eval_index"][i, n_e:] = x["eval_index"][-1]
        out["eval_t"][i, :n_e], out["eval_t"][i, n_e:] = x["eval_t"], t_end
        out["unsort"][i, x["eval_order"]] = np.arange(n_e)
        out["unsort"][i, n_e:] = n_e - 1
        out["breaks"][i, :n_b] = x["breaks"]
        out["breaks"][i, n_b:] = t_end + 1.0 + np.arange(n_breaks - n_b)
        out["levels"][i, :n_b], out["levels"][i, n_b:] = x["levels"], x["levels"][-1]
        out["jump_ts"][i, :n_j] = x["jump_ts"]
        out["jump_ts"][i, n_j:] = t_end + 1.0 + np.arange(n_jumps - n_j)
    return out


OFFSETS = [np.array([0.0]), np.array([-0.02, -0.01, 0.0]), np.array([-0.013, -0.004])]


@st.composite
def runs(draw):
    """(runs, offsets, channels): 1-6 runs on a 10 ms lattice (ties with breakpoints happen)."""
    offsets = OFFSETS[draw(st.integers(0, len(OFFSETS) - 1))]
    n_u = draw(st.integers(1, 2))
    out = []
    for _ in range(draw(st.integers(1, 6))):
        frames = draw(st.lists(st.integers(0, 300), min_size=1, max_size=40, unique=True))
        t = np.sort(np.array(frames)) * 0.01 + draw(st.sampled_from([0.0, -0.5, 0.37]))
        ticks = draw(st.lists(st.integers(-60, 320), min_size=1, max_size=12, unique=True))
        breaks = np.sort(np.array(ticks)) * 0.01
        if draw(st.booleans()):  # a breakpoint exactly on a frame or an instant
            breaks = np.unique(np.append(breaks, t[0] + offsets[0]))
        size = breaks.size * n_u
        levels = st.lists(st.sampled_from([0.0, 1.0, 2.5]), min_size=size, max_size=size)
        levels = np.array(draw(levels)).reshape(breaks.size, n_u)
        wave = PiecewiseConstant(breaks, levels, float(breaks[-1]) + 3.0)
        t0 = draw(st.sampled_from([0.0, -1.0, float(t[0]), float(t[0] + offsets[0])]))
        out.append((wave, t, t0))
    return out, offsets, n_u


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(runs())
def test_stacked_schedules_equal_the_per_run_reference(case):
    rs, offsets, n_u = case
    got = stacked_schedules([(w, t, t0, offsets, n_u) for w, t, t0 in rs], on_device=False)
    want = reference(rs, offsets)
    assert got.keys() == want.keys()
    for key in want:
        assert got[key].shape == want[key].shape, key
        assert got[key].dtype == want[key].dtype, key
        np.testing.assert_array_equal(got[key], want[key], err_msg=key)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(runs(), st.integers(1, 3))
def test_runs_stacked_in_parts_to_joint_widths_equal_the_joint_stack(case, n_parts):
    rs, offsets, n_u = case
    runs_ = [(w, t, t0, offsets, n_u) for w, t, t0 in rs]
    joint = stacked_schedules(runs_, on_device=False)
    widths = schedule_widths(runs_)
    assert widths == {
        "frames": joint["t_s"].shape[1],
        "intervals": joint["dt"].shape[1],
        "breaks": joint["breaks"].shape[1],
        "jumps": joint["jump_ts"].shape[1],
    }
    cuts = np.linspace(0, len(runs_), n_parts + 1).astype(int)
    for a, b in zip(cuts[:-1], cuts[1:]):
        if a == b:
            continue
        part = stacked_schedules(runs_[a:b], on_device=False, widths=widths)
        for key in joint:
            assert part[key].dtype == joint[key].dtype, key
            np.testing.assert_array_equal(part[key], joint[key][a:b], err_msg=key)


def test_bad_runs_are_refused_by_name():
    wave = PiecewiseConstant(np.array([0.0]), np.array([1.0]), 1.0)
    good = (wave, np.array([0.1, 0.2]), 0.0, OFFSETS[0], 1)
    with pytest.raises(ValueError, match=r"frame 1 at 0.1 s follows 0.2 s"):
        stacked_schedules([good, (wave, np.array([0.2, 0.1]), 0.0, OFFSETS[0], 1)])
    with pytest.raises(ValueError, match="NaN"):
        stacked_schedules([good, (wave, np.array([0.1, np.nan]), 0.0, OFFSETS[0], 1)])
    with pytest.raises(ValueError, match="none given"):
        stacked_schedules([])
    with pytest.raises(ValueError, match="takes 2 input channel"):
        stacked_schedules([(wave, np.array([0.1]), 0.0, OFFSETS[0], 2)])
    with pytest.raises(ValueError, match="takes 2 input channel"):  # the widths check as much
        schedule_widths([good, (wave, np.array([0.1]), 0.0, OFFSETS[0], 2)])
