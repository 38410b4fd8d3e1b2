"""The vectorised residual kernels against plain loops written from their definitions.

Truth: double loops over slots and lags (the definitions of the lagged sums and of the
permutation p-value), and the documented random stream of the shuffles: for run `i` and
output `j` of `analyse(..., seed=s)`, `np.random.default_rng([s, i, j])`, one
`rng.random(n)` row per shuffle, ranked (`argsort`) to give the permutation.
"""

import numpy as np
import pytest

from greybox._estimate import residuals as _residuals
from greybox._estimate import sandwich as _sandwich
from greybox._estimate.residuals import analyse, analyse_run, lag_products, lagged_sums


def naive_lagged_sums(a, oa, b, ob, lags):
    s = a.size
    sums, pairs = [], []
    for k in lags:
        ts = [t for t in range(s) if 0 <= t - k < s]
        sums.append(sum(a[t] * b[t - k] for t in ts))
        pairs.append(sum(float(oa[t] and ob[t - k]) for t in ts))
    return np.array(sums), np.array(pairs)


@pytest.mark.parametrize("s", [1, 7, 60, _residuals.CORRELATE_MAX + 3])
def test_lagged_sums_match_the_double_loop(s):
    rng = np.random.default_rng(s)
    oa, ob = rng.random(s) > 0.2, rng.random(s) > 0.1
    a, b = np.where(oa, rng.normal(size=s), 0.0), np.where(ob, rng.normal(size=s), 0.0)
    lags = np.array([-s - 2, -s, -3, -1, 0, 1, 2, 5, s - 1, s + 4])
    sums, pairs = lagged_sums(a, oa, b, ob, lags)
    want_s, want_p = naive_lagged_sums(a, oa, b, ob, lags)
    np.testing.assert_allclose(sums, want_s, rtol=1e-12, atol=1e-12 * s)
    np.testing.assert_array_equal(pairs, want_p)
    rows = lag_products(np.stack([a, 2 * a]), b, lags)
    np.testing.assert_allclose(rows[1], 2 * want_s, rtol=1e-12, atol=1e-12 * s)


def naive_p_value(t, e, valid, seed, h, b):
    """Permutation p-value of the gapped, bias-corrected Ljung-Box Q of one run, one output,
    written out from the module docstring (no outliers in these data): the share of the
    first 99 shuffles reaching Q where at least 10 of them do, else of all `b`. Also: was
    it settled by the first 99."""
    grid = _residuals.FrameGrid.build(t)
    n = int(valid.sum())
    x = np.where(valid, e - e[valid].mean(), 0.0)
    g = np.zeros(grid.n_slots)
    occ = np.zeros(grid.n_slots, bool)
    g[grid.slots], occ[grid.slots] = x, valid
    slots = np.flatnonzero(occ)
    vals = g[slots]
    c0 = vals @ vals / n

    def q_of(series):
        q = 0.0
        for k in range(1, h + 1):
            pairs = sum(occ[t] and occ[t - k] for t in range(k, g.size))
            r = sum(series[t] * series[t - k] for t in range(k, g.size)) / pairs / c0
            r += 1.0 / (n - 1)
            q += r**2 * pairs * (1 + 2 / n)
        return q

    rng = np.random.default_rng([*seed, 0])
    q0 = q_of(g)
    beyond = 0
    for i in range(b):
        shuffled = np.zeros_like(g)
        shuffled[slots] = vals[rng.random(vals.size).argsort()]
        beyond += q_of(shuffled) >= q0
        if i + 1 == 99 and beyond >= 10:
            return q0, (1 + beyond) / 100, True
    return q0, (1 + beyond) / (b + 1), False


@pytest.mark.parametrize("colour", [0.25, 0.45], ids=["settled-by-99", "all-199"])
@pytest.mark.parametrize("compiled", [False, True], ids=["numpy", "compiled"])
@pytest.mark.parametrize("cached", [True, False])
def test_permutation_p_value_matches_the_loop_with_the_documented_stream(
    monkeypatch, cached, compiled, colour
):
    """Both ways of drawing the shuffles (cached orders, or drawn block by block for a long
    run) are the documented stream, in numpy's blocks (a CPU) and in the compiled kernel (an
    accelerator; here forced on the CPU), in both stages: a mildly coloured run whose first
    99 shuffles settle its p-value, and a more coloured one that takes all 199."""
    if not cached:
        monkeypatch.setattr(_residuals, "ORDER_CACHE_ELEMENTS", 0)
    monkeypatch.setattr(_residuals, "_compiled_shuffles", lambda *_: compiled)
    rng = np.random.default_rng(4)
    n = 90
    t = np.cumsum(rng.uniform(0.9, 1.1, n) * np.where(rng.random(n) < 0.05, 3, 1))
    e = rng.normal(size=n)
    e[1:] += colour * e[:-1]  # coloured: a p-value away from both ends
    valid = rng.random(n) > 0.08
    q0, p0, settled = naive_p_value(t, e, valid, (3, 1), 6, 199)
    assert settled == (colour < 0.3)
    monkeypatch.setattr(_residuals, "LAG_BLOCK", 7 * 128)  # several blocks of shuffles
    r = analyse_run("a", t, e[:, None], valid[:, None], None, 6, 6, permutations=199, seed=(3, 1))
    assert 0.01 < p0 < 0.99
    np.testing.assert_allclose(r.q[0], q0, rtol=1e-12)
    assert r.p_value[0] == p0


def coloured_run(rng, name, n, n_y, colour, inputs):
    """A run as `analyse` takes it: `n` frames at 30 fps (5 % of the intervals doubled, a
    dropped timestamp), AR(1) residuals of coefficient `colour` in `n_y` outputs, 5 % of the
    readings invalid, and with `inputs` one input column."""
    t = np.cumsum(np.where(rng.random(n) < 0.05, 2.0, 1.0)) / 30.0
    e = rng.normal(size=(n, n_y))
    e[1:] += colour * e[:-1]
    valid = rng.random((n, n_y)) > 0.05
    return (name, t, e, valid, rng.normal(size=(n, 1)) if inputs else None)


def test_analyse_many_is_one_analyse_per_fit():
    """Fits of different run lengths (so different lags) and gaps, analysed together, give
    what one `analyse` each gives: the same shuffles (a row padded to a longer one's length
    sums in another order: rounding), the same statistics and p-values. Both ways of holding
    the shuffles meet here: one array for all runs (a fit alone: one test lag) and an array
    per run (the fits together: test lags differ)."""
    rng = np.random.default_rng(9)
    fits = []
    for n_runs, n in [(2, 60), (3, 140), (1, 45)]:
        fits.append([coloured_run(rng, f"r{i}", n, 1, 0.3, True) for i in range(n_runs)])
    together = _residuals.analyse_many(fits, permutations=299)  # both stages
    for runs, got in zip(fits, together):
        alone = analyse(runs, permutations=299)
        assert got.test_lag == alone.test_lag
        np.testing.assert_array_equal(got.q, alone.q)
        np.testing.assert_array_equal(got.p_value, alone.p_value)
        for a, b in zip(got.runs, alone.runs):
            np.testing.assert_array_equal(a.p_value, b.p_value)
    assert len({a.test_lag for a in together}) > 1  # the fits really had different lags


def test_shuffles_in_two_stages_keep_every_small_p_value_and_verdict(monkeypatch):
    """The sequential rule (module docstring) against both single-stage tests it is made of:
    a p-value (per run and pooled) is the 99-shuffle one where at least 10 of the 99 reach
    the observed Q (p >= 0.11), else the 999-shuffle one; so every p-value the 999 put
    below 0.011 is theirs, bit for bit, and so is every verdict. White and coloured runs,
    two outputs, several runs a fit."""
    rng = np.random.default_rng(5)
    fits = []
    for k in range(12):  # from white to clearly coloured
        fits.append(
            [coloured_run(rng, f"r{i}", int(rng.integers(50, 120)), 2, 0.05 * k, False)
             for i in range(3)]
        )  # fmt: skip
    staged = _residuals.analyse_many(fits)
    first = _residuals.analyse_many(fits, permutations=99)
    monkeypatch.setattr(_residuals, "FIRST_SHUFFLES", 999)
    full = _residuals.analyse_many(fits)

    def expected(p99, p999):
        return np.where(p99 >= 0.11, p99, p999)

    small = settled = 0
    for s_, f99, f999 in zip(staged, first, full):
        np.testing.assert_array_equal(s_.p_value, expected(f99.p_value, f999.p_value))
        for a, b, c in zip(s_.runs, f99.runs, f999.runs):
            np.testing.assert_array_equal(a.p_value, expected(b.p_value, c.p_value))
        np.testing.assert_array_equal(s_.white, f999.white)
        assert s_.verdict.split("(")[0] == f999.verdict.split("(")[0]
        small += int(np.sum(f999.p_value < 0.011))
        settled += int(np.sum(f99.p_value >= 0.11))
    assert small >= 4 and settled >= 4  # both stages were exercised


def test_pooled_correlations_are_the_pair_weighted_means_of_the_runs():
    """Pooled over runs (two outputs, two inputs, gaps, missing input levels): each lag's
    autocorrelation and cross-correlation is the mean of the runs' with their pair counts
    as weights (runs where it is undefined left out), the null variance
    sum w^2 v / (sum w)^2, the statistic Q = sum over lags 1..h of r^2 / v; a loop per
    output, input, lag and run from those definitions."""
    rng = np.random.default_rng(21)
    runs = []
    for i, n in enumerate([70, 48, 90]):
        t = np.cumsum(np.where(rng.random(n) < 0.08, 2.0, 1.0)) / 30.0
        e = rng.normal(size=(n, 2))
        e[1:, 0] += 0.4 * e[:-1, 0]
        valid = rng.random((n, 2)) > 0.1
        u = rng.normal(size=(n, 2))
        u[::7, 1] = np.nan  # a missing input level
        runs.append((f"r{i}", t, e, valid, u))
    a = analyse(runs, permutations=19)
    m, h = a.max_lag, a.test_lag
    for j in range(2):
        for k in range(m + 1):
            w = [r.pairs[j, k] for r in a.runs if np.isfinite(r.autocorrelation[j, k])]
            x = [r.autocorrelation[j, k] for r in a.runs if np.isfinite(r.autocorrelation[j, k])]
            v = [r.null_var[j, k] for r in a.runs if np.isfinite(r.autocorrelation[j, k])]
            tot = sum(w)
            assert a.autocorrelation[j, k] == pytest.approx(
                sum(wi * xi for wi, xi in zip(w, x)) / tot, rel=1e-12, abs=1e-15
            )
            if k > 0:
                assert a.null_var[j, k] == pytest.approx(
                    sum(wi**2 * vi for wi, vi in zip(w, v)) / tot**2, rel=1e-12
                )
        for k in range(2 * m + 1):
            assert a.cross_pairs[j, k] == sum(r.cross_pairs[j, k] for r in a.runs)
            for l in range(2):
                terms = [
                    (r.cross_pairs[j, k], r.cross_correlation[j, l, k])
                    for r in a.runs
                    if np.isfinite(r.cross_correlation[j, l, k])
                ]
                want = sum(w * c for w, c in terms) / sum(w for w, _ in terms)
                assert a.cross_correlation[j, l, k] == pytest.approx(want, rel=1e-12, abs=1e-15)
        q = sum(a.autocorrelation[j, k] ** 2 / a.null_var[j, k] for k in range(1, h + 1))
        assert a.q[j] == pytest.approx(q, rel=1e-12)
    assert np.isfinite(a.cross_correlation).all() and np.isfinite(a.q).all()


def test_pooled_analysis_is_reproducible_for_a_seed():
    rng = np.random.default_rng(8)
    runs = [
        (f"r{i}", np.arange(80) / 30.0, rng.normal(size=(80, 2)), np.ones((80, 2), bool), None)
        for i in range(3)
    ]
    a, b = analyse(runs, seed=11), analyse(runs, seed=11)
    np.testing.assert_array_equal(a.p_value, b.p_value)
    assert not np.array_equal(analyse(runs, seed=12).p_value, a.p_value)


def test_input_levels_hold_the_last_known_level_across_gaps():
    rng = np.random.default_rng(6)
    n = 120
    t = np.cumsum(np.where(rng.random(n) < 0.1, 3.0, 1.0))  # missing timestamps: empty slots
    u = rng.normal(size=(n, 2))
    u[rng.random((n, 2)) < 0.15] = np.nan  # and unknown levels at some frames
    grid = _residuals.FrameGrid.build(t)
    lags = 4
    got = _sandwich._input_lags(t, grid, u, n, lags)
    # the definition, slot by slot: an empty slot or unknown level holds the one before it
    slot_u = np.zeros((grid.n_slots, 2))
    held = np.zeros(2)
    have = np.zeros(2, bool)
    by_slot = dict(zip(grid.slots.tolist(), u))
    for k in range(grid.n_slots):
        level = by_slot.get(k, np.full(2, np.nan))
        have = have | np.isfinite(level)
        held = np.where(np.isfinite(level), level, held)
        slot_u[k] = np.where(have, held, 0.0)
    want = np.concatenate([slot_u[np.maximum(grid.slots - k, 0)] for k in range(lags)], axis=1)
    np.testing.assert_array_equal(got, want)


def test_stacked_outlier_screen_is_the_median_rule_row_by_row():
    """`_robust_keep_rows` (every output of every run in one sorted pass) keeps what the rule
    gives with np.median on each row alone: valid readings within OUTLIER_SCALES x 1.4826 MAD
    of the median; rows with fewer than 3 valid readings or no spread keep them all."""
    rng = np.random.default_rng(11)
    rows, n = 60, 40
    e = rng.standard_t(3, size=(rows, n)) * rng.uniform(0.1, 10, (rows, 1))
    valid = rng.random((rows, n)) > rng.uniform(0, 0.5, (rows, 1))
    valid[:4, 2:] = False  # 2 valid readings: nothing screened
    e[4:8] = 1.5  # no spread
    e[8, :5] = 1e3  # gross outliers
    e = np.where(valid, e, np.nan)
    got = _residuals._robust_keep_rows(e, valid)
    for i in range(rows):
        vals = e[i, valid[i]]
        want = valid[i].copy()
        if vals.size >= 3:
            med = np.median(vals)
            scale = 1.4826 * np.median(np.abs(vals - med))
            if scale > 0:
                want &= np.abs(e[i] - med) <= _residuals.OUTLIER_SCALES * scale
        np.testing.assert_array_equal(got[i], want, err_msg=f"row {i}")
    assert not got[8, :5].any() and got[:8][valid[:8]].all()


def test_shuffle_blocks_in_threads_give_the_same_p_values(monkeypatch):
    """On a machine with cores to spare the shuffle blocks run in threads
    (`shuffle_threads`); every statistic and p-value is the one the serial loop gives."""
    rng = np.random.default_rng(12)
    fits = []
    for _ in range(6):
        fits.append(
            [coloured_run(rng, f"r{i}", int(rng.integers(40, 90)), 1, 0.3, True) for i in range(3)]
        )
    monkeypatch.setattr(_residuals, "LAG_BLOCK", 4096)  # many blocks
    monkeypatch.setattr(_residuals, "shuffle_threads", lambda: 1)
    serial = _residuals.analyse_many(fits, permutations=199)
    monkeypatch.setattr(_residuals, "shuffle_threads", lambda: 4)
    threaded = _residuals.analyse_many(fits, permutations=199)
    for a, b in zip(serial, threaded):
        np.testing.assert_array_equal(a.p_value, b.p_value)
        np.testing.assert_array_equal(a.q, b.q)
        for ra, rb in zip(a.runs, b.runs):
            np.testing.assert_array_equal(ra.p_value, rb.p_value)


@pytest.mark.parametrize("calls", ["one", "several"])
def test_compiled_shuffle_kernel_gives_numpys_statistics_on_a_batch(monkeypatch, calls):
    """The shuffle pass as the compiled kernel (what an accelerator runs) against numpy's
    blocks, on fits of different run lengths, lags, gaps and dropped readings analysed
    together: every shuffled r(k) to single precision, every p-value and Q the same; also
    when the kernel's memory bound splits the runs over several calls."""
    from greybox._estimate import shuffle_kernel

    if calls == "several":  # order tables of at most 2 streams a call
        monkeypatch.setattr(shuffle_kernel, "CALL_ELEMENTS", 199 * 256 * 2)
    rng = np.random.default_rng(21)
    fits = []
    for n_runs, n in [(2, 60), (3, 140), (1, 45), (2, 33)]:
        fits.append([coloured_run(rng, f"r{i}", n, 2, 0.3, False) for i in range(n_runs)])
    shuffled, real_p_values = {}, _residuals._run_p_values

    def keep(way):  # the runs' shuffled r(k), as their p-values read them (both stages)
        def p_values(runs, stacked, rows):
            shuffled.setdefault(way, []).extend(
                r.permuted_autocorrelation[:, :rows].copy() for r in runs
            )
            return real_p_values(runs, stacked, rows)

        return p_values

    out = {}
    for way, compiled in (("numpy", False), ("compiled", True)):
        monkeypatch.setattr(_residuals, "_compiled_shuffles", lambda *_, c=compiled: c)
        monkeypatch.setattr(_residuals, "_run_p_values", keep(way))
        out[way] = _residuals.analyse_many(fits, permutations=199)
    assert len(shuffled["numpy"]) == len(shuffled["compiled"]) > sum(map(len, fits))
    for a, b in zip(shuffled["numpy"], shuffled["compiled"]):
        assert np.array_equal(np.isnan(a), np.isnan(b))
        np.testing.assert_allclose(b, a, rtol=0, atol=2e-6)
    for a, b in zip(out["numpy"], out["compiled"]):
        np.testing.assert_array_equal(a.q, b.q)
        np.testing.assert_array_equal(a.p_value, b.p_value)
        for ra, rb in zip(a.runs, b.runs):
            np.testing.assert_array_equal(ra.p_value, rb.p_value)
    assert len({a.test_lag for a in out["numpy"]}) > 1


def test_an_accelerator_compiles_a_batchs_shuffles_not_a_single_fits(monkeypatch):
    """The kernel serves batches on an accelerator; a single fit's few runs (numpy: ~10 ms)
    would pay its compile, and a CPU runs numpy's faster blocks whatever the size."""
    from greybox import _platform

    class Job:
        def __init__(self, slots):
            self.g = np.zeros(slots)

    single = [Job(400)] * 6  # the chevron demo's six runs of ~330 frames
    wave = [Job(50)] * 64 * 6  # a batch's wave: 64 devices of six ~50-frame runs
    b = _residuals.PERMUTATIONS
    for accelerator, want in ((False, (False, False)), (True, (False, True))):
        monkeypatch.setattr(_platform, "on_accelerator", lambda a=accelerator: a)
        got = (_residuals._compiled_shuffles(single, b), _residuals._compiled_shuffles(wave, b))
        assert got == want


def plain_p_values(perm_r, null_var, dof):
    """The permutation p-value from its definition, one row of shuffles at a time: Q of a
    row is the sum over the usable lags (r(k) of the observed row and of this row finite,
    null variance positive) of r(k)^2 / v(k), added lag after lag."""
    b = perm_r.shape[-2] - 1
    out = np.full(perm_r.shape[:-2], np.nan)
    for idx in np.ndindex(out.shape):
        r, v = perm_r[idx], null_var[idx]
        use = np.isfinite(r[0]) & (v > 0)
        if not use.any():
            continue
        q = np.array([
            sum((row[k] ** 2 / v[k] for k in range(v.size) if use[k] and np.isfinite(row[k])), 0.0)
            for row in r
        ])  # fmt: skip
        beyond = int(np.sum(q[1:] >= q[0]))
        tail = _residuals.chi2_sf(q[0], dof)
        out[idx] = (1 + beyond) / (b + 1) if beyond else min(tail, 1 / (b + 1))
    return out


@pytest.mark.parametrize("h", [1, 3, 7, 8, 11])
def test_p_values_are_the_definition_with_gaps_and_unusable_lags(h):
    """`_p_values` (stacked, unmasked passes) gives the p-values of the plain per-row
    definition exactly, with lags that have no pairs (NaN r), null variances that are zero
    or NaN, a run with no usable lag at all, and shuffles that tie the observed row."""
    rng = np.random.default_rng(h)
    r = 0.1 * rng.standard_normal((5, 2, 60, h))
    r[0, 1, :, 0] = np.nan  # a lag without pairs
    r[1, 0, 7:9] = np.nan  # shuffles with an undefined r(k)
    r[2, 1, 5] = r[2, 1, 0]  # a tie with the observed row
    v = 0.01 + 0.01 * rng.random((5, 2, h))
    v[3, 0, -1] = 0.0
    v[3, 1] = np.nan  # nothing usable: NaN
    got = _residuals._p_values(r, v, h)
    np.testing.assert_array_equal(got, plain_p_values(r, v, h))
    assert np.isnan(got[3, 1]) and np.isfinite(got[1:3]).all()
