"""Residual analysis of a fit: is what the model leaves over white noise? (pure numpy)

For every run and output, as MATLAB `resid` does for a simulation-error model:

- the autocorrelation r(k) of the residuals e = y - y_model for lags k = 0..M frames, with
  the 99 % band of white noise;
- the cross-correlation of the residuals with each input u(t - k), k = -M..M (positive k:
  the input leads), with the same band (valid when the residuals are white);
- a portmanteau (Ljung-Box) statistic Q with its chi-square p-value, per run and pooled over
  the runs, and a one-line verdict: "residuals consistent with white noise" or "residuals
  not white: structure the model misses at lags ...".

A model that captures the dynamics leaves measurement noise; a model that misses a time
constant leaves a slow, autocorrelated misfit however small the noise estimate makes it look.

**Frame times, dropped frames and outliers.** Camera frames are near-uniform (jitter of a
few ms at tens of ms per frame), so lags are counted in frames: each run's frames are placed
on a uniform grid at its median frame interval dt (each interval between consecutive frames
counts as max(1, round(interval / dt)) slots, so timing jitter does not accumulate). A
dropped frame (NaN reading) or a missing timestamp leaves its slot empty, and every
correlation uses only the pairs of slots that both hold a valid reading (the
amplitude-modulated estimator of Parzen 1963): r(k) = [sum over pairs e_t e_(t+k) / n_k] /
[sum e_t^2 / n]. Jitter within half an interval is ignored; a run whose intervals spread (10th
to 90th percentile) by more than half the median, where a frame may land one slot off, gets a
note. Readings further than `OUTLIER_SCALES` robust scales (1.4826 MAD of that run's
residuals, not the fitted sigma) from the median residual are treated as missing too: a
burst of corrupted frames is not a dynamic the model misses, while a misfit that is large
against a known noise level stays in (it moves the MAD with it).

**The test.** Each r(k) is corrected for the mean removal (white noise with its sample mean
taken out has E r(k) = -1/(n - 1), a bias that pooling runs would not average away) and
weighted by the inverse of its null variance 1 / (n_k (1 + 2/n)): without gaps this is the
Ljung-Box statistic N (N + 2) sum_k r_b(k)^2 / (N - k) of the usual (biased) autocorrelation
r_b, bias-corrected. Pooled over runs, r(k) is the pair-weighted mean of the runs' r(k) with
its null variance, so a structure shared by the runs adds up. Q sums lags 1..h with
h = min(`TEST_LAG`, n / 5) (the usual Ljung-Box rule; correlations are still shown up to
`MAX_LAG`). Its p-value comes from `PERMUTATIONS` shuffles of each run's residuals among its
occupied slots (the gaps stay put; seeded, so reproducible): exact for exchangeable noise,
whatever the gaps, the run lengths and the pooling. The chi-square reference with h degrees
of freedom is liberal at these sizes (fitted one-node chevron residuals, two runs of ~120
frames, 2000 replicates: 1.6 % of rejections at the 1 % level, 5.6 % at 5 %; with the
shuffles 1.15 % and 5.15 %), so it is used only beyond the shuffles' resolution (a Q larger
than every shuffled one: p < 1 / (B + 1)), where it orders the evidence. The shuffles are
drawn in two stages (sequential Monte Carlo p-values, Besag and Clifford 1991): every test
gets the first `FIRST_SHUFFLES` = 99, and one where `DECIDED_EXCEEDANCES` = 10 of them already
reach the observed Q (p >= 0.11: clearly white) keeps the p-value of those 99; the others get
the rest of the `PERMUTATIONS` = 999 of the same stream. The first 99 are among the 999, so a
test that stops has at least 10 of the 999 reaching its Q: every p-value that all 999 put
below 0.011, and with it every verdict (p < 0.01 / n_y), is exactly the one they give; only a
clearly white test's p-value is the coarser estimate of 99 shuffles. Most runs of a right
structure stop there, which makes the shuffles about a third of their cost. The verdict rejects
whiteness of an output when p < `ALPHA` / n_y (Bonferroni over outputs); the degrees of
freedom are not reduced by the fitted parameters (an output-error fit of a few physical
parameters barely whitens its residuals). `benchmarks/whiteness.py` measures the false-alarm
rate on fitted residuals.

Also here: the goodness-of-fit test against a known noise level (chi-square of the residuals
in units of the known sigma). The HAC "meat" of the sandwich covariance (model-error removal,
Andrews-Monahan prewhitening, Newey-West) is `greybox._estimate.sandwich`.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import itertools
import threading
from concurrent.futures import ThreadPoolExecutor
from statistics import NormalDist

import numpy as np

CONFIDENCE = 0.99  # bands and test level (as MATLAB `resid`)
ALPHA = 1.0 - CONFIDENCE
MAX_LAG = 25  # lags shown, in frames (MATLAB `resid` default), fewer for short runs
TEST_LAG = 10  # lags the portmanteau test uses: min(10, n / 5), the usual Ljung-Box rule
PERMUTATIONS = 999  # within-run shuffles of the residuals that give the test's null
# shuffles in two stages (module docstring): every test gets the first FIRST_SHUFFLES, and
# one that DECIDED_EXCEEDANCES of them reach (p >= 0.11) keeps their p-value; the others get
# all PERMUTATIONS of the same stream
FIRST_SHUFFLES = 99
DECIDED_EXCEEDANCES = 10
SHUFFLES_TEXT = (  # how a p-value was drawn, as the reports and params.json say it
    f"{PERMUTATIONS} within-run shuffles of the residuals (the first {FIRST_SHUFFLES} alone "
    f"where {DECIDED_EXCEEDANCES} of them reach the observed statistic: "
    f"p >= {(1 + DECIDED_EXCEEDANCES) / (1 + FIRST_SHUFFLES):g})"
)
OUTLIER_SCALES = 5.0
IRREGULAR_SPREAD = 0.5  # 10-90 % spread of frame intervals (x median) that earns a note


def chi2_sf(q, dof):
    """Upper tail P(X > q) of a chi-square with `dof` degrees of freedom (array-friendly)."""
    from scipy.special import chdtrc  # scipy is a core dependency; imported where needed

    return chdtrc(np.asarray(dof, dtype=float), np.asarray(q, dtype=float))


class _Cache:
    """Least-recently-used results of pure functions, bounded in bytes (not in entries: a
    batch of 512 devices x 6 runs must not evict its own grids between the residual pass and
    the per-device assembly, and a long run's entries are large). Thread-safe."""

    def __init__(self, max_bytes: int):
        self.max_bytes, self.bytes = int(max_bytes), 0
        self.items: collections.OrderedDict = collections.OrderedDict()
        self.lock = threading.Lock()

    def get(self, key, make, size):
        """The value for `key`, made by `make()` on a miss; `size(value)` its bytes."""
        with self.lock:
            if key in self.items:
                self.items.move_to_end(key)
                return self.items[key][0]
        value = make()
        nbytes = int(size(value))
        with self.lock:
            if key not in self.items:
                self.items[key] = (value, nbytes)
                self.bytes += nbytes
            while len(self.items) > 1 and self.bytes > self.max_bytes:
                self.bytes -= self.items.popitem(last=False)[1][1]
        return value


_grids = _Cache(64 << 20)  # frame grids by frame times (`FrameGrid.build`)


# ------------------------------------------------------------------------------- frame grid


@dataclasses.dataclass(frozen=True)
class FrameGrid:
    """Frames of one run on a uniform grid: frame i sits in slot `slots[i]`; `dt_s` is the
    median frame interval. Each interval between consecutive frames counts as
    max(1, round(interval / dt_s)) slots, so jitter never accumulates and a gap of missing
    timestamps leaves empty slots."""

    slots: np.ndarray
    n_slots: int
    dt_s: float
    spread: float  # (90th - 10th percentile of the intervals) / median

    @staticmethod
    def build(t_s) -> FrameGrid:
        t = np.asarray(t_s, dtype=float).reshape(-1)
        key = t.tobytes()
        return _grids.get(key, lambda: _frame_grid(key), lambda g: 2 * len(key) + 200)


def _frame_grid(t_bytes: bytes) -> FrameGrid:
    """`FrameGrid.build` of the frame times in `t_bytes` (float64), cached (`_grids`): a
    fit's residual analysis, its model-error residuals and its HAC meat all place the same
    runs."""
    t = np.frombuffer(t_bytes, dtype=float)
    if t.size < 2:
        slots = np.zeros(t.size, dtype=int)
        slots.setflags(write=False)
        return FrameGrid(slots, t.size, float("nan"), 0.0)
    dts = np.diff(t)
    dt = float(np.median(dts))
    p10, p90 = np.percentile(dts, [10, 90])
    spread = float((p90 - p10) / dt)
    steps = np.maximum(1, np.rint(dts / dt)).astype(int)
    slots = np.concatenate([[0], np.cumsum(steps)])
    slots.setflags(write=False)  # shared by every caller of the cache
    return FrameGrid(slots, int(slots[-1]) + 1, dt, spread)


LAG_BLOCK = 1 << 18  # elements of one block of rows of `_permuted_autocorrelation` (2 MB:
# it stays in cache; 32 MB blocks were 25 % slower on a batch of 128 devices x 6 runs)
COMPILED_SHUFFLES_MIN = 1 << 24  # shuffle elements from which an accelerator runs the kernel
SHUFFLE_THREADS_MAX = 8  # the block products are memory-bound: more threads add little
MAX_SLICES = 64  # a shuffled row with more runs of occupied slots is scattered column-wise
# The shuffles multiply in single precision: half the memory traffic, twice the speed on long
# runs (the chevron fit's 6 runs of ~330 frames: the residual analysis 19-21 -> 10 ms). A
# p-value counts shuffles whose Q reaches the observed one (double precision, as are the
# reported correlations and Q); a shuffle's rounding, ~1e-6 of its Q, could move it across
# only within ~1e-6 of a tie, far inside the 1 / (B + 1) resolution.
SHUFFLE_DTYPE = np.float32
CORRELATE_MAX = 4096  # 1-D series up to this length: all lags from one np.correlate call


def lag_products(a: np.ndarray, b: np.ndarray, lags) -> np.ndarray:
    """(..., K) sums over t of a[..., t] b[..., t - k] for each lag k of `lags` (zero beyond
    the ends): one vectorised product per lag over every leading row at once."""
    a = np.asarray(a, dtype=float)
    b = np.broadcast_to(np.asarray(b, dtype=float), a.shape)
    s = a.shape[-1]
    lags = np.asarray(lags, dtype=int).reshape(-1)
    out = np.zeros((*a.shape[:-1], lags.size))
    for i, k in enumerate(lags):
        if abs(k) >= s:
            continue
        if k >= 0:
            out[..., i] = np.einsum("...t,...t->...", a[..., k:], b[..., : s - k])
        else:
            out[..., i] = np.einsum("...t,...t->...", a[..., : s + k], b[..., -k:])
    return out


def lagged_sums(a, occ_a, b, occ_b, lags) -> tuple[np.ndarray, np.ndarray]:
    """For each lag k: (sum over slots t with both occupied of a[t] b[t - k], pair count).

    `a`, `b`: (S,) zero where unoccupied; negative lags pair a[t] with b[t + |k|]. The one
    lagged-product kernel of a single series (`ljung_box`, `greybox.blackbox.residual_test`);
    the stacked residual analysis calls `lag_products` on all its rows at once. Short
    series take every lag from one `np.correlate` (direct sums); long ones one product per
    lag (`lag_products`)."""
    a = np.asarray(a, dtype=float).reshape(-1)
    b = np.asarray(b, dtype=float).reshape(-1)
    oa = np.asarray(occ_a, dtype=float).reshape(-1)
    ob = np.asarray(occ_b, dtype=float).reshape(-1)
    lags = np.asarray(lags, dtype=int).reshape(-1)
    s = a.size
    if s > CORRELATE_MAX:
        both = lag_products(np.stack([a, oa]), np.stack([b, ob]), lags)
        return both[0], both[1]
    # np.correlate(x, y, "full")[s - 1 + k] = sum_t x[t + k] y[t] = sum_t x[t] y[t - k]
    inside = np.abs(lags) < s
    at = np.where(inside, s - 1 + lags, 0)
    sums = np.where(inside, np.correlate(a, b, "full")[at], 0.0)
    pairs = np.where(inside, np.correlate(oa, ob, "full")[at], 0.0)
    return sums, pairs


def white_null_variance(pairs, n) -> np.ndarray:
    """Variance of the pair-normalised autocorrelation r(k) = [sum of pairs / pairs] / c0 of
    n white readings with `pairs` pairs at lag k: 1 / (pairs (1 + 2 / n)); with these weights
    the portmanteau statistic is Ljung-Box's."""
    pairs = np.asarray(pairs, dtype=float)
    with np.errstate(divide="ignore"):
        return np.where(pairs > 0, 1.0 / (pairs * (1.0 + 2.0 / n)), np.nan)


def portmanteau(r, null_var, axis: int = -1) -> np.ndarray:
    """Q = sum over the finite lags of r(k)^2 / null_var(k): Ljung-Box with
    `white_null_variance`, Box-Pierce with the biased r and null_var = 1 / N."""
    r = np.asarray(r, dtype=float)
    v = np.broadcast_to(np.asarray(null_var, dtype=float), r.shape)
    use = np.isfinite(r) & np.isfinite(v) & (v > 0)
    return np.sum(np.where(use, r**2 / np.where(use, v, 1.0), 0.0), axis=axis)


@dataclasses.dataclass(frozen=True)
class LjungBox:
    """Ljung-Box portmanteau test: Q = n (n + 2) sum_{k=1}^{h} r_k^2 / (n - k) ~ chi2(h - dof).

    `p_value` small (say < 0.01) means the series is autocorrelated, i.e. not white.
    """

    statistic: float
    p_value: float
    lags: int
    n: int


def ljung_box(x, lags: int = 20, dof: int = 0) -> LjungBox:
    """Ljung-Box test of a 1-D series; NaN entries are dropped (the rest kept in order).

    **Arguments:** `x` the series (N,); `lags` h, capped at n - 1; `dof` parameters already
    fitted to the series itself (0 for Kalman innovations). The usual (biased) r_k, no gaps
    and no mean-removal correction: the textbook statistic (`analyse_run` is the gapped,
    bias-corrected form of the same sum).
    """
    x = np.asarray(x, dtype=float).reshape(-1)
    x = x[np.isfinite(x)]
    n = x.size
    h = min(int(lags), n - 1)
    if h - dof < 1:
        raise ValueError(f"ljung_box: {n} finite samples are too few for {lags} lags")
    x = x - x.mean()
    ones = np.ones(n, dtype=bool)
    sums, pairs = lagged_sums(x, ones, x, ones, np.arange(1, h + 1))
    r = sums / pairs / (x @ x / n)
    q = float(portmanteau(r, white_null_variance(pairs, n)))
    return LjungBox(statistic=q, p_value=float(chi2_sf(q, h - dof)), lags=h, n=n)


# ------------------------------------------------------------------------------ one run


@dataclasses.dataclass(frozen=True)
class RunResiduals:
    """Residual correlations of one run (arrays per output j and input l).

    - `lags` (M+1,) frames 0..M; `autocorrelation` (n_y, M+1) with r(0) = 1; `pairs` (n_y,
      M+1) valid pairs per lag; `null_var` (n_y, M+1) variance of r(k) for white residuals.
    - `cross_lags` (2M+1,) -M..M; `cross_correlation` (n_y, n_u, 2M+1) of e(t) with
      u(t - k); `cross_pairs` (n_y, 2M+1).
    - `q` (n_y,) Ljung-Box statistic over lags 1..`test_lag` and `p_value` (n_y,) from the
      shuffled residuals (the chi-square tail beyond their resolution).
    - `n_used` (n_y,) readings used, `n_excluded` (n_y,) gross outliers left out.
    - `grid`: the frame grid (median interval, spread); `permuted_autocorrelation` (n_y,
      B + 1, test_lag): r(1..test_lag) observed (row 0) and for each shuffle, while the runs
      are pooled; None in a finished analysis (the p-values hold what it gave).
    """

    name: str
    lags: np.ndarray
    autocorrelation: np.ndarray
    pairs: np.ndarray
    null_var: np.ndarray
    cross_lags: np.ndarray
    cross_correlation: np.ndarray
    cross_pairs: np.ndarray
    q: np.ndarray
    p_value: np.ndarray
    n_used: np.ndarray
    n_excluded: np.ndarray
    grid: FrameGrid
    test_lag: int
    permuted_autocorrelation: np.ndarray = dataclasses.field(repr=False, default=None)

    @property
    def max_lag(self) -> int:
        return int(self.lags[-1])

    def band(self, confidence: float = CONFIDENCE) -> np.ndarray:
        """(n_y, M+1) half-width of the white-noise band of the autocorrelation."""
        z = NormalDist().inv_cdf(0.5 + confidence / 2)
        return z * np.sqrt(self.null_var)

    def cross_band(self, confidence: float = CONFIDENCE) -> np.ndarray:
        """(n_y, 2M+1) half-width of the band of the cross-correlation (white residuals)."""
        z = NormalDist().inv_cdf(0.5 + confidence / 2)
        with np.errstate(divide="ignore"):
            return z / np.sqrt(self.cross_pairs)


ORDER_CACHE_ELEMENTS = 1 << 22  # a stream's B x n orders above this are drawn block by block
_orders = _Cache(64 << 20)  # shuffle orders kept for reuse (a batch's devices share them)


def _stream(key: tuple, skip: int = 0, n: int = 0) -> np.random.Generator:
    """The random stream of the shuffles of `key` (seed, run, output): `default_rng(list(key))`,
    past its first `skip` shuffles of `n` values (drawn and dropped: a later stage of
    `_shuffle_tests` continues the stream where the first stopped)."""
    rng = np.random.default_rng(list(key))
    if skip:
        rng.random((skip, n))
    return rng


def _drawn_orders(rng: np.random.Generator, rows: int, n: int) -> np.ndarray:
    """The next `rows` shuffles of `rng`'s stream: one `rng.random(n)` row each, ranked. Drawn
    at once or block by block, a stream gives the same shuffles."""
    return rng.random((rows, n)).argsort(axis=1)


def _shuffle_orders(key: tuple, n: int, b: int) -> np.ndarray | None:
    """(b, n) rank orders of the shuffles of stream `key` (`default_rng(list(key))`, one
    `rng.random(n)` row per shuffle, ranked), cached: they depend only on the stream and the
    number of values, so the devices of a batch (and a repeated fit) draw them once. None
    above ORDER_CACHE_ELEMENTS (the caller then draws the same stream block by block)."""
    if b * n > ORDER_CACHE_ELEMENTS:
        return None

    def make():
        order = _drawn_orders(_stream(key), b, n)  # platform ints: a gather with int32
        order.setflags(write=False)  # indices converts them on every use (2x its cost)
        return order

    return _orders.get((key, n, b), make, lambda o: o.nbytes)


@dataclasses.dataclass
class _Shuffled:
    """One run and output to test by shuffles: residuals `g` on the grid (`occ` occupied, zero
    elsewhere), pair counts `npairs` at lags 1..h, readings `n`, variance `c0`, stream `key`,
    its r(1..h) `observed` (double precision); `out` (B + 1, h) receives r(1..h), observed
    (row 0) and shuffled."""

    g: np.ndarray
    occ: np.ndarray
    npairs: np.ndarray
    n: int
    c0: float
    key: tuple
    observed: np.ndarray
    out: np.ndarray

    @functools.cached_property
    def unit(self) -> np.ndarray:
        """`g` / sqrt(c0) in SHUFFLE_DTYPE: what the shuffle pass multiplies (r(k) does not
        depend on the scale, and unit variance keeps any unit's squares far from single
        precision's underflow and overflow)."""
        return (self.g / np.sqrt(self.c0)).astype(SHUFFLE_DTYPE)

    @property
    def output(self) -> int:
        """The output this job tests (its stream key's last element)."""
        return self.key[-1]

    @functools.cached_property
    def order_key(self) -> tuple:
        """(stream `key`, number of occupied slots): what picks the job's rank orders
        (`_shuffle_orders`); the jobs of a batch that share it share one order table."""
        return self.key, int(self.occ.sum())

    @functools.cached_property
    def slot_runs(self) -> tuple[np.ndarray, np.ndarray]:
        """(the occupied slots in order, the index in them where each stretch of consecutive
        occupied slots starts, closed by their count): a shuffled row is written stretch by
        stretch (slice copies) rather than column by column (a scatter, 2-3x slower)."""
        slots = np.flatnonzero(self.occ)
        cut = np.flatnonzero(np.diff(slots) != 1) + 1
        first = np.concatenate([[0], cut, [slots.size]])
        return slots, first


def _pieces(jobs, shuffles: range):
    """(job, first row of `out`, the order rows of shuffles) for the shuffles `shuffles` of
    each job's stream, in blocks of at most LAG_BLOCK / n_slots shuffles, lazily: slices of
    the cached orders or, for long runs, the same stream drawn block by block."""
    for job in jobs:
        if not shuffles:
            continue
        _, slots_n = job.order_key
        rows = max(1, LAG_BLOCK // max(job.g.size, 1))
        cached = _shuffle_orders(job.key, slots_n, job.out.shape[0] - 1)
        rng = None if cached is not None else _stream(job.key, shuffles.start, slots_n)
        for start in range(shuffles.start, shuffles.stop, rows):
            stop = min(start + rows, shuffles.stop)
            if cached is not None:
                yield job, 1 + start, cached[start:stop]
            else:
                yield job, 1 + start, _drawn_orders(rng, stop - start, slots_n)


def _blocks(pieces):
    """Consecutive pieces packed into blocks of at most LAG_BLOCK elements (rows x longest
    grid; a single larger piece is a block of its own)."""
    block, size, width = [], 0, 0
    for piece in pieces:
        rows = piece[2].shape[0]
        w = max(width, piece[0].g.size)
        if block and (size + rows) * w > LAG_BLOCK:
            yield block, size, width
            block, size, w = [], 0, piece[0].g.size
        block.append(piece)
        size, width = size + rows, w
    if block:
        yield block, size, width


def _permuted_autocorrelation(jobs, shuffles: range) -> None:
    """Fill rows of each job's `out` (B + 1, h) with the bias-corrected r(1..h): row 0 its
    observed one, and for each shuffle i of `shuffles` (of the B of its stream) row 1 + i,
    that of the shuffle of the values among the occupied slots (the gaps stay where they
    are; single precision, `SHUFFLE_DTYPE`). The rows of every job (all runs of a
    fit, all devices of a batch) go through one product per lag and block (row-wise dot
    products of each row with its lagged self; a row is zero-padded to its block's longest
    grid, and zeros add nothing); blocks bound memory, and a job's shuffles are one stream
    whatever the blocking and the other jobs. Blocks are independent (each writes its own
    rows of its jobs' `out`) and numpy's copies and products release the interpreter, so on a
    machine with cores to spare (`shuffle_threads`) they run side by side, a bounded window
    of blocks at a time; the numbers do not depend on it. On an accelerator the same pass
    is one compiled kernel (`shuffle_kernel`, `_compiled_shuffles`)."""
    if not jobs:
        return
    if shuffles and _compiled_shuffles(jobs, len(shuffles)):
        from greybox._estimate import shuffle_kernel

        total = jobs[0].out.shape[0] - 1  # a pass's jobs share their B
        shuffle_kernel.fill(jobs, shuffles, _orders_of(shuffles, total))
    elif shuffles:
        _numpy_shuffles(jobs, shuffles)
    rows = slice(1 + shuffles.start, 1 + shuffles.stop)
    for job in jobs:
        if not shuffles.start:
            job.out[0] = job.observed
        job.out[rows, job.npairs == 0] = np.nan


def _numpy_shuffles(jobs, shuffles: range) -> None:
    """`_permuted_autocorrelation`'s rows 1 + `shuffles` by numpy blocks, in threads where
    `shuffle_threads` allows."""
    h = max(job.npairs.size for job in jobs)
    # the jobs of one order table (the same run of many devices) one after another: they
    # gather through it while it is in cache (3,072 runs: 0.87 -> 0.72 s); each job writes
    # only its own rows, so the order of the jobs changes no number
    jobs = sorted(jobs, key=lambda job: job.order_key)
    blocks = _blocks(_pieces(jobs, shuffles))
    workers = shuffle_threads()
    if workers == 1:
        scratch = _Scratch()
        for block in blocks:
            _block_autocorrelation(*block, h, scratch)
        return
    local = threading.local()

    def run(block):
        if not hasattr(local, "scratch"):
            local.scratch = _Scratch()
        _block_autocorrelation(*block, h, local.scratch)

    with ThreadPoolExecutor(workers, thread_name_prefix="greybox-shuffles") as pool:
        while window := list(itertools.islice(blocks, 4 * workers)):  # bounded memory
            list(pool.map(run, window))


class _Scratch:
    """One thread's reusable block buffer (no fresh pages for every block)."""

    def __init__(self):
        self.buffer = np.empty(0)

    def grid(self, size: int, width: int) -> np.ndarray:
        if self.buffer.size < size * width:
            self.buffer = np.empty(size * width, dtype=SHUFFLE_DTYPE)
        grid = self.buffer[: size * width].reshape(size, width)
        grid.fill(0.0)
        return grid


def _compiled_shuffles(jobs, shuffles: int) -> bool:
    """Whether the shuffle pass of `jobs` runs as one compiled kernel (`shuffle_kernel`): on
    an accelerator, for a batch's worth of shuffles (COMPILED_SHUFFLES_MIN elements, counted
    over this pass's `shuffles` a job: one of `_shuffle_tests`' stages), where numpy's pass
    was most of a batch's host work. A single fit's pass (the chevron's six runs:
    ~2.4 million elements, ~10 ms of numpy) stays numpy there: compiling the kernel would
    cost it more than it saves. On a CPU numpy's blocks are faster
    (`benchmarks/shuffle_pass.py`)."""
    from greybox import _platform

    elements = int(shuffles) * sum(job.g.size for job in jobs)
    return elements >= COMPILED_SHUFFLES_MIN and _platform.on_accelerator()


def _orders_of(shuffles: range, total: int):
    """(key, n) -> the rank orders of shuffles `shuffles` of the `total` of stream `key`:
    the cached ones, or for a long run (beyond the cache) the same stream drawn, as
    `_pieces` draws it block by block."""

    def orders(key, n):
        cached = _shuffle_orders(key, n, total)
        if cached is not None:
            return cached[shuffles.start : shuffles.stop]
        return _drawn_orders(_stream(key, shuffles.start, n), len(shuffles), n)

    return orders


def shuffle_threads() -> int:
    """Threads for the shuffle blocks: the cores this process may use beyond one (which the
    caller's own work, e.g. `fit_batch`'s compiled solves, keeps busy), at most
    SHUFFLE_THREADS_MAX; 1 (no threads) on a two-core machine."""
    from greybox import _platform

    cores = _platform.usable_cores()
    return int(max(1, min(SHUFFLE_THREADS_MAX, cores - 1 if cores > 2 else 1)))


def _block_autocorrelation(block, size, width, h, scratch) -> None:
    """One block of `_permuted_autocorrelation`: its rows placed, lag-multiplied, written."""
    grid = scratch.grid(size, width)
    r = 0
    for job, _, order in block:
        slots, first = job.slot_runs
        k = order.shape[0]
        shuffled = job.unit[slots][order]
        if first.size > MAX_SLICES:
            grid[r : r + k, slots] = shuffled
        else:
            for a, b in zip(first[:-1], first[1:]):
                grid[r : r + k, slots[a] : slots[a] + b - a] = shuffled[:, a:b]
        r += k
    sums = np.empty((size, h), dtype=SHUFFLE_DTYPE)
    for k in range(1, h + 1):  # row by row dot products: einsum is 2x a stacked matmul
        if k < width:
            np.einsum("ij,ij->i", grid[:, k:], grid[:, : width - k], out=sums[:, k - 1])
        else:
            sums[:, k - 1] = 0.0
    r = 0
    for job, first, order in block:  # r(k) = sums / pairs + 1 / (n - 1): unit variance, c0 = 1
        k, hj = order.shape[0], job.npairs.size
        out = job.out[first : first + k]
        np.divide(sums[r : r + k, :hj], np.maximum(job.npairs, 1), out=out)
        out += 1.0 / (job.n - 1)
        r += k


def _p_values(perm_r: np.ndarray, null_var: np.ndarray, dof: int) -> np.ndarray:
    """(...) p-values of Q = sum_k r(k)^2 / null_var(k) from `perm_r` (..., B + 1, h), row 0
    observed, and `null_var` (..., h): the share of shuffles with Q at least as large; when
    none is, the observed Q is beyond what B shuffles resolve and its chi-square tail (dof
    degrees) is given. Lags where r(k) is undefined (no pairs) or null_var is not positive
    are left out of Q; NaN where none is left."""
    r, v = np.asarray(perm_r, dtype=float), np.asarray(null_var, dtype=float)[..., None, :]
    use = np.isfinite(r[..., :1, :]) & (v > 0)
    # r^2 / v where usable, 0 elsewhere, in three unmasked passes (a masked divide was 5x
    # slower): a lag left out divides by inf (0), and a NaN r(k) (no pairs) gives NaN, which
    # fmax against 0 turns into 0 (every other term is >= 0, kept as it is)
    terms = np.square(r)
    np.divide(terms, np.where(use, v, np.inf), out=terms)
    np.fmax(terms, 0.0, out=terms)
    q = _sum_last(terms)
    b = q.shape[-1] - 1
    tail = chi2_sf(q[..., 0], dof)
    if b == 0:
        p = tail
    else:
        beyond = np.sum(q[..., 1:] >= q[..., :1], axis=-1)
        p = np.where(beyond > 0, (1 + beyond) / (b + 1), np.minimum(tail, 1 / (b + 1)))
    return np.where(use.any(axis=(-2, -1)), p, np.nan)


def _sum_last(x: np.ndarray) -> np.ndarray:
    """`x.sum(axis=-1)`, the same numbers: numpy sums fewer than 8 values one after another
    (its pairwise sum's base case), and so does this, as whole-array adds (a reduction over
    a short last axis pays a call per row); 8 or more, numpy's sum itself."""
    if not 0 < x.shape[-1] < 8:
        return x.sum(axis=-1)
    total = x[..., 0] + 0.0  # 0 + x0, as numpy starts: a -0.0 becomes 0.0
    for k in range(1, x.shape[-1]):
        total += x[..., k]
    return total


def _rows_in_cache(shape) -> int:
    """How many arrays of `shape` one `_p_values` call takes: about LAG_BLOCK elements, so
    its temporaries stay in cache (one stack of 3,072 runs was 150 MB per temporary)."""
    return max(1, LAG_BLOCK // max(int(np.prod(shape)), 1))


def _p_values_of(items) -> list:
    """`_p_values` of each (perm_r, null_var, dof) of `items`, those of one shape stacked (all
    the runs of a batch of devices) in chunks (`_rows_in_cache`)."""
    out: list = [None] * len(items)
    groups: dict = {}
    for i, (r, v, dof) in enumerate(items):
        groups.setdefault((r.shape, v.shape, dof), []).append(i)
    for (shape, _, dof), idx in groups.items():
        step = _rows_in_cache(shape)
        for c in range(0, len(idx), step):
            part = idx[c : c + step]
            r = np.stack([items[i][0] for i in part])
            p = _p_values(r, np.stack([items[i][1] for i in part]), dof)
            for k, i in enumerate(part):
                out[i] = p[k]
    return out


def analyse_run(
    name,
    t_s,
    residuals,
    valid,
    inputs,
    max_lag: int,
    test_lag: int | None = None,
    *,
    permutations: int = PERMUTATIONS,
    seed=0,
) -> RunResiduals:
    """Correlations and Ljung-Box test of one run (see the module docstring).

    `residuals` (N, n_y) measured - model in any consistent unit, `valid` (N, n_y) readings to
    use, `inputs` (N, n_u) input levels at the frame times (or None), `max_lag` M in frames
    (correlations shown), `test_lag` the lags of the Ljung-Box test (default M),
    `permutations` the most shuffles behind its p-value (the first FIRST_SHUFFLES alone
    where they settle it; 0: chi-square only), `seed` their seed.
    """
    pending, shuffled = _pending_runs(
        [(name, t_s, residuals, valid, inputs, max_lag, test_lag, seed)], permutations
    )
    p_runs, _, _ = _shuffle_tests([pending], shuffled, permutations)
    return _finished([pending[0][0]], p_runs)[0]


def _run_p_values(runs, shuffled, rows: int) -> list:
    """Each run's p-value (n_y,) from the first `rows` rows (observed and shuffled) of its
    shuffled autocorrelations: read from `shuffled`, the array that holds them all
    (`_pending_runs`), where there is one, else stacked from the runs' own."""
    if shuffled is None:
        return _p_values_of(
            [
                (r.permuted_autocorrelation[:, :rows], r.null_var[:, 1 : h + 1], h)
                for r in runs
                for h in [r.test_lag]
            ]
        )
    h = runs[0].test_lag
    v = np.stack([r.null_var[:, 1 : h + 1] for r in runs])
    step = _rows_in_cache((shuffled.shape[1], rows, shuffled.shape[3]))
    return [
        p
        for c in range(0, len(runs), step)
        for p in _p_values(shuffled[c : c + step, :, :rows], v[c : c + step], h)
    ]


def _shuffle_tests(fits, shuffled, permutations: int) -> tuple:
    """The shuffle tests of `fits` (per fit, its runs' (`RunResiduals`, `_Shuffled` jobs)
    from `_pending_runs`, whose array of all shuffled autocorrelations is `shuffled`, or
    None): (per run its p-values (n_y,), per fit its pooled statistics (`_pooled`: its
    autocorrelation and null variances), per fit its pooled p-values (n_y,)). In two stages
    (module docstring): every job's first FIRST_SHUFFLES shuffles, then the rest of its
    `permutations` for each job whose own test or whose fit's pooled test of that output
    they leave undecided. A test's p-value is that of the first stage where it is settled
    there (at least DECIDED_EXCEEDANCES shuffles reach its Q), else of all `permutations`."""
    b = int(permutations)
    first = min(b, FIRST_SHUFFLES)
    runs = [run for parts in fits for run, _ in parts]
    every_job = [j for parts in fits for _, jobs in parts for j in jobs]
    _permuted_autocorrelation(every_job, range(first))
    p_runs = _run_p_values(runs, shuffled, first + 1)  # before the pooling zeroes their NaN
    pooled, p = _pooled_tests(fits, range(len(fits)), shuffled, first + 1)
    if first == b:
        return p_runs, pooled, p
    settled = (1 + DECIDED_EXCEEDANCES - 0.5) / (first + 1)  # p of 10 of `first` reaching Q
    more, fits_more, runs_more, r = [], [], [], 0
    for f, parts in enumerate(fits):
        open_pooled = p[f] < settled  # NaN (nothing tested) is settled
        if open_pooled.any():
            fits_more.append(f)
        for run, jobs in parts:
            open_jobs = [j for j in jobs if open_pooled[j.output] or p_runs[r][j.output] < settled]
            if open_jobs:
                more += open_jobs
                runs_more.append(r)
            r += 1
    if not more:
        return p_runs, pooled, p
    _permuted_autocorrelation(more, range(first, b))
    full = _run_p_values(
        [runs[i] for i in runs_more], None if shuffled is None else shuffled[runs_more], b + 1
    )
    for i, pf in zip(runs_more, full):  # a settled run kept its shuffles for its pooled test
        p_runs[i] = np.where(p_runs[i] < settled, pf, p_runs[i])
    _, p_more = _pooled_tests(fits, fits_more, shuffled, b + 1)
    for f, pf in zip(fits_more, p_more):
        p[f] = np.where(p[f] < settled, pf, p[f])
    return p_runs, pooled, p


def _pooled_tests(fits, which, shuffled, rows: int) -> tuple:
    """(pooled statistics (`_pooled`), pooled p-values (n_y,)) of the fits at `which`, from
    the first `rows` rows (observed and rows - 1 shuffles) of their runs' shuffled
    autocorrelations. In `shuffled` (each fit's runs consecutive: pooled without a copy)
    those rows get their NaN set to 0 in place, what `_pooled` sums: read the runs' own
    p-values first."""
    ends = np.cumsum([len(parts) for parts in fits])
    pooled = []
    for f in which:
        runs = [run for run, _ in fits[f]]
        rk = None
        if shuffled is not None:
            rk = np.nan_to_num(shuffled[ends[f] - len(runs) : ends[f], :, :rows], copy=False)
        pooled.append(_pooled(runs, rk, rows))
    p = _p_values_of([(perm, v[:, 1 : h + 1], h) for perm, _, v, h in pooled])
    return pooled, p


def _finished(runs, p) -> list:
    """`runs` with their p-values `p`, and without their shuffled autocorrelations: pooled
    already (`_pooled`), they are 90 % of a fit's result (6 runs x 1,000 shuffles x 10 lags:
    480 kB a device, gigabytes for a wafer of devices)."""
    return [_replaced(r, p_value=pr, permuted_autocorrelation=None) for r, pr in zip(runs, p)]


def _replaced(obj, **changes):
    """`dataclasses.replace(obj, **changes)` of a frozen dataclass without a `__post_init__`,
    by copying its fields (replace calls `__init__`, which sets each field of a frozen class
    through `object.__setattr__`: 10 us a run, 30 ms a batch of 512 devices)."""
    new = object.__new__(type(obj))
    new.__dict__.update(obj.__dict__, **changes)
    return new


def _sorted_median(x: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Per row, the median of the first `count` entries of the row-sorted `x` (rows padded
    with inf), as np.median gives it: the middle value, or the mean of the two middle ones."""
    rows = np.arange(x.shape[0])
    lo, hi = x[rows, np.maximum(count - 1, 0) // 2], x[rows, count // 2]
    with np.errstate(invalid="ignore", over="ignore"):
        return np.where(count % 2 == 1, lo, (lo + hi) / 2.0)


def _robust_keep_rows(e: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Per row of `e` (S, N): `valid` without readings further than OUTLIER_SCALES robust
    scales (1.4826 MAD) from the row's median; rows with fewer than 3 valid readings, or no
    spread, keep every valid reading."""
    count = valid.sum(axis=1)
    with np.errstate(invalid="ignore", over="ignore"):  # unused readings may be inf or NaN
        med = _sorted_median(np.sort(np.where(valid, e, np.inf), axis=1), count)
        dev = np.abs(e - med[:, None])
        scale = 1.4826 * _sorted_median(np.sort(np.where(valid, dev, np.inf), axis=1), count)
        near = dev <= OUTLIER_SCALES * scale[:, None]
    robust = (count >= 3) & (scale > 0)
    return valid & (near | ~robust[:, None])


def _on_grids(values, ok, slots, width) -> tuple[np.ndarray, np.ndarray]:
    """Rows of values (S, N) with `ok` (S, N) placed on their frame grids: (S, width) values
    (zero where empty) and occupancy; `slots` per row, the slot of each of its frames."""
    s = values.shape[0]
    grid, occ = np.zeros((s, width)), np.zeros((s, width), dtype=bool)
    if not s:
        return grid, occ
    rows = np.concatenate([np.full(sl.size, i) for i, sl in enumerate(slots)])
    cols = np.concatenate(slots)
    frames = np.concatenate([np.arange(sl.size) for sl in slots])
    grid[rows, cols] = np.where(ok[rows, frames], values[rows, frames], 0.0)
    occ[rows, cols] = ok[rows, frames]
    return grid, occ


def padded_stack(arrays, fill, dtype=float) -> np.ndarray:
    """(len(arrays), longest N, ...) stack of arrays (N_i, ...) of one trailing shape, the
    shorter ones padded with `fill` (runs of different lengths as one array; at least one)."""
    n = max(np.shape(a)[0] for a in arrays)
    out = np.full((len(arrays), n, *np.shape(arrays[0])[1:]), fill, dtype=dtype)
    for k, a in enumerate(arrays):
        out[k, : np.shape(a)[0]] = a
    return out


def _pending_runs(specs, permutations) -> tuple[list, np.ndarray | None]:
    """`analyse_run` without its shuffles, for many runs at once: per run (its
    `RunResiduals`, p-values not yet set; the `_Shuffled` jobs that fill its
    `permuted_autocorrelation`), so that many runs, of one fit or of a batch of devices,
    shuffle in one vectorised pass; and, where every run has the same outputs and test lags
    (a fit, a batch of one structure), the one array (runs, n_y, B + 1, h) whose rows are
    their `permuted_autocorrelation`s (else None), so that the p-values and the pooling read
    them without stacking them again. `specs`: (name, t_s, residuals, valid, inputs,
    max_lag, test_lag, seed) per run. Every output of every run is one row of one stacked pass
    (the robust outlier screen, the placing on the frame grid, the lagged sums of every lag),
    runs of similar grid lengths together (`_bucket_rows`)."""
    runs = []
    for name, t_s, residuals, valid, inputs, max_lag, test_lag, seed in specs:
        e = np.asarray(residuals, dtype=float)
        e = e.reshape(e.shape[0], -1)
        ok = np.asarray(valid, dtype=bool).reshape(e.shape) & np.isfinite(e)
        m = int(max_lag)
        h = m if test_lag is None else int(min(test_lag, m))
        u = None if inputs is None else np.asarray(inputs, dtype=float).reshape(e.shape[0], -1)
        runs.append((str(name), FrameGrid.build(t_s), e, ok, u, m, h, seed))
    shapes = {(r[2].shape[1], r[6]) for r in runs}
    shuffled = None
    if len(shapes) == 1:
        ((n_y, h),) = shapes
        shuffled = np.full((len(runs), n_y, int(permutations) + 1, h), np.nan)
    out = [None] * len(runs)
    for members in _bucket_rows([r[1].n_slots for r in runs]):
        rows = None if shuffled is None else [shuffled[i] for i in members]
        group = _pending_group([runs[i] for i in members], permutations, rows)
        for k, done in zip(members, group):
            out[k] = done
    return out, shuffled


def _bucket_rows(widths) -> list:
    """Indices of `widths` grouped by their power-of-two bucket (padding wastes at most half)."""
    groups: dict = {}
    for i, w in enumerate(widths):
        groups.setdefault(max(int(w) - 1, 0).bit_length(), []).append(i)
    return list(groups.values())


def _pending_group(runs, permutations, shuffled_rows=None) -> list:
    """`_pending_runs` of runs of similar grid lengths (one stacked pass); `shuffled_rows`:
    the NaN arrays that become their `permuted_autocorrelation`s (None: made here)."""
    n_rows = [r[2].shape[1] for r in runs]
    first = np.concatenate([[0], np.cumsum(n_rows)])
    width = max(r[1].n_slots for r in runs)
    m_max = max(r[5] for r in runs)
    e = padded_stack([row for r in runs for row in r[2].T], np.nan)  # one row per output
    ok = padded_stack([row for r in runs for row in r[3].T], False, dtype=bool)
    slots = [r[1].slots for r in runs for _ in range(r[2].shape[1])]
    keep = _robust_keep_rows(e, ok)
    n = keep.sum(axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        centred = np.where(keep, e - (np.where(keep, e, 0.0).sum(axis=1) / n)[:, None], 0.0)
    g, occ = _on_grids(centred, keep, slots, width)
    with np.errstate(invalid="ignore", divide="ignore"):
        c0 = np.einsum("st,st->s", g, g) / n
    live = (n >= 3) & (c0 > 0)
    lags = np.arange(m_max + 1)
    sums = lag_products(g, g, lags)
    npairs = lag_products(occ.astype(float), occ.astype(float), lags)
    with np.errstate(invalid="ignore", divide="ignore"):
        auto = np.where(
            live[:, None] & (npairs > 0),
            sums / np.maximum(npairs, 1) / c0[:, None] + 1.0 / (n[:, None] - 1),
            np.nan,
        )
        null_var = np.where(live[:, None], white_null_variance(npairs, n[:, None]), np.nan)
    auto[live, 0] = 1.0
    npairs = np.where(live[:, None], npairs, 0.0)
    cross_rows = _cross_correlations(runs, first, g, occ, c0, live, m_max, width)
    q_all = _row_portmanteau(
        auto, null_var, live, [(a, r[2].shape[1], r[6]) for r, a in zip(runs, first)]
    )
    unset = np.full(first[-1], np.nan)  # every run's p-values until its shuffles set them
    results = []
    for i, ((name, grid, e_r, ok_r, u, m, h, seed), a) in enumerate(zip(runs, first)):
        n_y, rows = e_r.shape[1], slice(a, a + e_r.shape[1])
        n_u = 0 if u is None else u.shape[1]
        q = q_all[rows]
        if shuffled_rows is None:
            perm_r = np.full((n_y, int(permutations) + 1, h), np.nan)
        else:
            perm_r = shuffled_rows[i]
        jobs = [
            _Shuffled(
                g[a + j, : grid.n_slots],
                occ[a + j, : grid.n_slots],
                npairs[a + j, 1 : h + 1],
                int(n[a + j]),
                float(c0[a + j]),
                (*(int(x) for x in np.atleast_1d(seed)), j),
                auto[a + j, 1 : h + 1],
                perm_r[j],
            )
            for j in range(n_y)
            if live[a + j]
        ]
        cross, cross_pairs = cross_rows(a, n_y, n_u, m)
        run = RunResiduals(
            name,
            np.arange(m + 1),
            auto[rows, : m + 1],
            npairs[rows, : m + 1],
            null_var[rows, : m + 1],
            np.arange(-m, m + 1),
            cross,
            cross_pairs,
            q,
            unset[rows],
            n[rows],
            ok_r.sum(axis=0) - n[rows],
            grid,
            h,
            perm_r,
        )
        results.append((run, jobs))
    return results


def _row_portmanteau(auto, null_var, live, spans) -> np.ndarray:
    """Per row of `auto` and `null_var` (rows, M + 1), the portmanteau statistic over its
    run's lags 1..h (NaN where not `live`); `spans`: (first row, rows, h) per run. The rows
    of one h in one call (a run's rows summed exactly as a call of their own would)."""
    h_of = np.zeros(auto.shape[0], dtype=int)
    for a, n_rows, h in spans:
        h_of[a : a + n_rows] = h
    q = np.full(auto.shape[0], np.nan)
    for h in np.unique(h_of):
        rows = np.flatnonzero(live & (h_of == h))
        q[rows] = portmanteau(auto[rows, 1 : h + 1], null_var[rows, 1 : h + 1])
    return q


def _cross_correlations(runs, first, g, occ, c0, live, m_max, width):
    """A function (first row, n_y, n_u, M) -> (cross-correlations (n_y, n_u, 2M + 1),
    their pair counts (n_y, 2M + 1)) of each run's residual rows with its inputs, every
    (output, input) pair of every run in one stacked pass of the lagged sums."""
    u_rows, u_ok, u_slots, owner = [], [], [], []
    for k, (_, grid, e_r, _, u, *_rest) in enumerate(runs):
        if u is None:
            continue
        for col in u.T:
            u_rows.append(col)
            u_ok.append(np.isfinite(col))
            u_slots.append(grid.slots)
            owner.append(k)
    lags = np.arange(-m_max, m_max + 1)
    pairs_g, pairs_u, where = [], [], {}
    if u_rows:
        uv, uo = padded_stack(u_rows, 0.0), padded_stack(u_ok, False, dtype=bool)
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = np.where(uo, uv, 0.0).sum(axis=1) / uo.sum(axis=1)
        ug, uocc = _on_grids(np.where(uo, uv - mean[:, None], 0.0), uo, u_slots, width)
        cu = np.einsum("st,st->s", ug, ug) / np.maximum(uocc.sum(axis=1), 1)
        col_of = {}
        for i, k in enumerate(owner):
            col_of.setdefault(k, []).append(i)
        for k, cols in col_of.items():
            n_y = runs[k][2].shape[1]
            for j in range(n_y):
                if not live[first[k] + j]:
                    continue
                for l, i in enumerate(cols):
                    if cu[i] > 0:
                        where[(first[k] + j, l)] = len(pairs_g)
                        pairs_g.append(first[k] + j)
                        pairs_u.append(i)
    if pairs_g:
        pg, pu = np.asarray(pairs_g), np.asarray(pairs_u)
        s = lag_products(g[pg], ug[pu], lags)
        npair = lag_products(occ[pg].astype(float), uocc[pu].astype(float), lags)
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = (
                np.where(npair > 0, s / np.maximum(npair, 1), np.nan)
                / np.sqrt(c0[pg] * cu[pu])[:, None]
            )

    def rows_of(a, n_y, n_u, m):
        cross = np.full((n_y, n_u, 2 * m + 1), np.nan)
        cross_pairs = np.zeros((n_y, 2 * m + 1))
        band = slice(m_max - m, m_max + m + 1)
        for j in range(n_y):
            for l in range(n_u):
                i = where.get((a + j, l))
                if i is not None:  # the last usable input's pair counts, as one pass each gave
                    cross[j, l] = corr[i, band]
                    cross_pairs[j] = npair[i, band]
        return cross, cross_pairs

    return rows_of


# --------------------------------------------------------------------------- all runs


def _ranges(values) -> str:
    """[1, 2, 3, 7, 9, 10] -> "1-3, 7, 9-10"."""
    out, values = [], sorted(int(v) for v in values)
    i = 0
    while i < len(values):
        j = i
        while j + 1 < len(values) and values[j + 1] == values[j] + 1:
            j += 1
        sep = ".." if values[i] < 0 else "-"
        out.append(f"{values[i]}" if i == j else f"{values[i]}{sep}{values[j]}")
        i = j + 1
    return ", ".join(out)


@dataclasses.dataclass(frozen=True)
class ResidualAnalysis:
    """Residual tests of every run of a fit or a validation, pooled per output.

    - `runs`: one `RunResiduals` per run; `output_names`: labels of the outputs.
    - `autocorrelation` (n_y, M+1), `null_var` (n_y, M+1): pooled over runs.
    - `cross_correlation` (n_y, n_u, 2M+1), `cross_pairs` (n_y, 2M+1): pooled.
    - `q`, `p_value` (n_y,): pooled Ljung-Box statistic over lags 1..`test_lag` and its
      p-value (shuffles pooled the same way; the chi-square tail with `test_lag` dof beyond
      their resolution).
    - `white` (n_y,): p >= ALPHA / n_y; `lags_outside` per output: lags 1..M whose pooled
      r(k) is outside the 99 % band; `cross_outside` per output and input: lags outside.
    - `frame_interval_s`: median frame interval over the runs (converts lags to seconds).
    - `notes`: how irregular frames and outliers were handled in these data.
    """

    runs: tuple
    output_names: tuple
    lags: np.ndarray
    autocorrelation: np.ndarray
    null_var: np.ndarray
    cross_lags: np.ndarray
    cross_correlation: np.ndarray
    cross_pairs: np.ndarray
    q: np.ndarray
    p_value: np.ndarray
    white: np.ndarray
    lags_outside: tuple
    cross_outside: tuple
    frame_interval_s: float
    notes: tuple
    test_lag: int
    confidence: float = CONFIDENCE

    @property
    def max_lag(self) -> int:
        return int(self.lags[-1])

    @property
    def dof(self) -> int:
        return int(self.test_lag)

    @property
    def all_white(self) -> bool:
        return bool(np.all(self.white | ~np.isfinite(self.q)))

    def band(self) -> np.ndarray:
        z = NormalDist().inv_cdf(0.5 + self.confidence / 2)
        return z * np.sqrt(self.null_var)

    def _label(self, j: int) -> str:
        return f" in {self.output_names[j]}" if len(self.output_names) > 1 else ""

    def _lag_text(self, lags) -> str:
        dt = self.frame_interval_s
        span = ""
        if lags and np.isfinite(dt):
            lo, hi = min(lags) * dt, max(lags) * dt
            span = f", {_seconds(lo)}" + (f" to {_seconds(hi)}" if hi > lo else "")
        return f"lags {_ranges(lags)} frames{span}"

    @property
    def verdict(self) -> str:
        """One line: white, or where the structure the model misses sits."""
        how = (
            f"Ljung-Box, {self.test_lag} lags, pooled over {len(self.runs)} run"
            f"{'s' if len(self.runs) != 1 else ''}"
        )
        if not np.any(np.isfinite(self.q)):
            return "residual test not possible (too few valid readings)"
        if self.all_white:
            p = np.nanmin(self.p_value)
            return f"residuals consistent with white noise ({how}: {p_phrase(p)})"
        parts = []
        for j in np.flatnonzero(~self.white & np.isfinite(self.q)):
            lags = list(self.lags_outside[j]) or [
                int(np.nanargmax(np.abs(self.autocorrelation[j, 1:]))) + 1
            ]
            parts.append(
                f"{self._lag_text(lags)}{self._label(j)} (Q = {self.q[j]:.4g} on "
                f"{self.dof} dof, {p_phrase(self.p_value[j])})"
            )
        return (
            "residuals not white: structure the model misses dynamics at "
            + "; ".join(parts)
            + f" ({how})"
        )

    def cross_lines(self) -> list[str]:
        """Inputs whose cross-correlation with the residuals leaves the band, per output."""
        out = []
        for j, per_input in enumerate(self.cross_outside):
            for l, lags in enumerate(per_input):
                if lags:
                    out.append(
                        f"input {l + 1}{self._label(j)}: cross-correlation outside the "
                        f"{self.confidence * 100:g} % band at lags {_ranges(lags)} frames "
                        "(positive: the input leads the residual)"
                    )
        return out


def _seconds(x: float) -> str:
    return f"{x * 1e3:.3g} ms" if abs(x) < 1 else f"{x:.3g} s"


def p_value_text(p) -> str:
    """A p-value for a table cell: "n/a", "< 1e-300" (below double precision's reach) or two
    significant digits."""
    if p is None or not np.isfinite(p):
        return "n/a"
    return "< 1e-300" if p < 1e-300 else f"{p:.2g}"


def p_phrase(p) -> str:
    """A p-value in a sentence: "p = 0.012", "p < 1e-300" or "p = n/a"."""
    text = p_value_text(p)
    return f"p {text}" if text.startswith("<") else f"p = {text}"


def analyse(
    runs,
    *,
    output_names=None,
    max_lag: int | None = None,
    test_lag: int | None = None,
    permutations: int = PERMUTATIONS,
    seed: int = 0,
) -> ResidualAnalysis:
    """Residual analysis of several runs.

    `runs`: sequence of (name, t_s (N,), residuals (N, n_y), valid (N, n_y), inputs (N, n_u)
    or None). `max_lag`: lags shown, in frames (default `MAX_LAG`, at most a quarter of the
    shortest run's valid readings, at least 1). `test_lag`: lags of the Ljung-Box test
    (default `TEST_LAG`, at most a fifth of the shortest run, at least 1; never above
    `max_lag`): with many lags against few frames the chi-square reference is liberal.
    `permutations`, `seed`: the most within-run shuffles behind a p-value (the first
    FIRST_SHUFFLES alone where they settle it: module docstring) and their seed
    (reproducible).
    """
    return analyse_many(
        [runs],
        output_names=output_names,
        max_lag=max_lag,
        test_lag=test_lag,
        permutations=permutations,
        seed=seed,
    )[0]


def analyse_many(
    fits,
    *,
    output_names=None,
    max_lag: int | None = None,
    test_lag: int | None = None,
    permutations: int = PERMUTATIONS,
    seed: int = 0,
) -> list[ResidualAnalysis]:
    """`analyse` of each element of `fits` (each a sequence of runs as `analyse` takes them,
    e.g. one per device of a batch), exactly as one call each would give, with the shuffles
    of every run of every fit in one vectorised pass (`_permuted_autocorrelation`)."""
    pending = []
    for runs in fits:
        runs = list(runs)
        if not runs:
            raise ValueError("runs: nothing to analyse")
        m, h = max_lag, test_lag
        if m is None or h is None:
            shortest = min(int(np.asarray(r[3]).sum(axis=0).min()) for r in runs)
            m = int(max(1, min(MAX_LAG, shortest // 4))) if m is None else m
            h = int(max(1, min(TEST_LAG, shortest // 5))) if h is None else h
        m, h = int(m), int(min(h, m))
        pending.append([(*r, m, h, (seed, i)) for i, r in enumerate(runs)])
    done_runs, shuffled = _pending_runs([spec for specs in pending for spec in specs], permutations)
    done_runs = iter(done_runs)
    pending = [[next(done_runs) for _ in specs] for specs in pending]
    p_runs, pooled, p = _shuffle_tests(pending, shuffled, permutations)
    done = iter(_finished([run for parts in pending for run, _ in parts], p_runs))
    return [
        _analysis(tuple(next(done) for _ in parts), auto, null_var, output_names, pj)
        for parts, (_, auto, null_var, _), pj in zip(pending, pooled, p)
    ]


def _pooled(per_run, shuffled=None, rows=None) -> tuple:
    """(pooled shuffled r(1..h) (n_y, rows, h), pooled autocorrelation (n_y, M + 1), pooled
    null variances (n_y, M + 1), h): each output's runs pooled with their pair counts as
    weights (a run where r(k) is undefined left out), the shuffles the same way as the
    observed autocorrelation (every output of every run in one stacked pass). `shuffled`:
    the runs' shuffled r(1..h) stacked already, NaN set to 0 (None: stacked here from the
    first `rows` rows of each run's, all where None)."""
    h = per_run[0].test_lag
    ra = np.stack([r.autocorrelation for r in per_run])  # (R, n_y, M + 1)
    w = np.where(np.isfinite(ra), np.stack([r.pairs for r in per_run]), 0.0)
    vv = np.nan_to_num(np.stack([r.null_var for r in per_run]), copy=False)
    rk = shuffled
    if rk is None:
        rk = np.stack([r.permuted_autocorrelation[:, :rows] for r in per_run])
        rk = np.nan_to_num(rk, copy=False)
    tot = w.sum(axis=0)  # (n_y, M + 1)
    with np.errstate(invalid="ignore", divide="ignore"):
        auto = np.where(tot > 0, (w * np.nan_to_num(ra)).sum(axis=0) / tot, np.nan)
        null_var = np.where(tot > 0, (w**2 * vv).sum(axis=0) / tot**2, np.nan)
        # the same pair weights for every shuffle
        pooled_perm = np.einsum("rjk,rjbk->jbk", w[:, :, 1 : h + 1], rk) / tot[:, None, 1 : h + 1]
    return pooled_perm, auto, null_var, h


def _analysis(per_run, auto, null_var, output_names, p) -> ResidualAnalysis:
    """The runs' correlations and tests pooled per output (see the module docstring), with
    the pooled autocorrelation `auto` and null variances `null_var` (n_y, M + 1) and
    p-values `p` (n_y,) (`_pooled`)."""
    n_y = per_run[0].autocorrelation.shape[0]
    h = per_run[0].test_lag
    lags, cross_lags = per_run[0].lags, per_run[0].cross_lags
    # every output and input of every run pooled in one stacked pass, runs first
    cw = np.stack([r.cross_pairs for r in per_run])[:, :, None, :]  # (R, n_y, 1, 2M + 1)
    cr = np.stack([r.cross_correlation for r in per_run])  # (R, n_y, n_u, 2M + 1)
    wl = np.where(np.isfinite(cr), cw, 0.0)
    tl = wl.sum(axis=0)
    cross_pairs = cw.sum(axis=0)[:, 0]
    n_u = cr.shape[2]
    with np.errstate(invalid="ignore", divide="ignore"):
        cross = np.where(tl > 0, (wl * np.nan_to_num(cr)).sum(axis=0) / tl, np.nan)
    a_h, v_h = auto[:, 1 : h + 1], null_var[:, 1 : h + 1]
    testable = np.any(np.isfinite(a_h) & (v_h > 0), axis=1)
    q = np.where(testable, portmanteau(a_h, v_h), np.nan)
    white = ~(p < ALPHA / n_y)
    z = NormalDist().inv_cdf(0.5 + CONFIDENCE / 2)
    band = z * np.sqrt(null_var)
    outside = tuple(
        tuple(int(k) for k in lags[1:][np.abs(auto[j, 1:]) > band[j, 1:]]) for j in range(n_y)
    )
    root = np.sqrt(cross_pairs)
    cband = np.divide(z, root, out=np.full_like(root, np.inf), where=root > 0)
    cross_out = tuple(
        tuple(tuple(int(k) for k in cross_lags[np.abs(cross[j, l]) > cband[j]]) for l in range(n_u))
        for j in range(n_y)
    )
    intervals = [r.grid.dt_s for r in per_run if np.isfinite(r.grid.dt_s)]
    dt = float(np.median(intervals)) if intervals else float("nan")
    notes = []
    irregular = [r.name for r in per_run if r.grid.spread > IRREGULAR_SPREAD]
    if irregular:
        notes.append(
            f"frame intervals spread by more than {IRREGULAR_SPREAD:.0%} of the median in "
            f"{', '.join(irregular)}; lags are counted in frames of the median interval, so "
            "some frames may sit one lag off"
        )
    excluded = int(sum(r.n_excluded.sum() for r in per_run))
    if excluded:
        notes.append(
            f"{excluded} reading(s) more than {OUTLIER_SCALES:g} robust scales from the median "
            "residual were left out as gross outliers"
        )
    names = (
        tuple(output_names)
        if output_names is not None
        else tuple(f"output {j + 1}" for j in range(n_y))
    )
    return ResidualAnalysis(
        per_run,
        names,
        lags,
        auto,
        null_var,
        cross_lags,
        cross,
        cross_pairs,
        q,
        p,
        white,
        outside,
        cross_out,
        dt,
        tuple(notes),
        h,
    )


# ------------------------------------------------------------------- known noise


@dataclasses.dataclass(frozen=True)
class GoodnessOfFit:
    """Residuals against a known noise level (readings in units of their known sigma).

    - `chi2`, `dof`, `p_value`: sum of squared scaled residuals over every valid reading,
      n_data - n_params degrees of freedom, upper-tail p-value (small: the residuals are
      larger than the noise allows, i.e. the model misses something or sigma is too small).
    - `ratio` (n_y,): RMS scaled residual per output, sqrt(chi2_j / dof_j): the estimated noise
      over the known noise (1 when the model fits down to the noise).
    - `robust_ratio` (n_y,): the same from 1.4826 MAD (insensitive to a few corrupted frames).
    """

    chi2: float
    dof: int
    p_value: float
    ratio: np.ndarray
    robust_ratio: np.ndarray

    @property
    def line(self) -> str:
        ratios = ", ".join(f"{r:.3g}" for r in self.ratio)
        robust = ", ".join(f"{r:.3g}" for r in self.robust_ratio)
        return (
            f"estimated / known noise = {ratios} (robust: {robust}); chi-square "
            f"{self.chi2:.5g} on {self.dof} dof, {p_phrase(self.p_value)}"
        )


def goodness_of_fit(scaled_residuals, valid, n_params: int) -> GoodnessOfFit:
    """`scaled_residuals`: list of (N, n_y) (y - model) / known sigma per run; `valid` alike."""
    r = np.concatenate(
        [np.asarray(x, dtype=float).reshape(np.shape(x)[0], -1) for x in scaled_residuals]
    )
    ok = np.concatenate([np.asarray(v, dtype=bool).reshape(-1, r.shape[1]) for v in valid])
    ok = ok & np.isfinite(r)
    n = int(ok.sum())
    chi2 = float(np.sum(np.where(ok, r, 0.0) ** 2))
    dof = max(n - int(n_params), 1)
    ratio, robust = [], []
    for j in range(r.shape[1]):
        rj = r[ok[:, j], j]
        dof_j = max(rj.size - n_params * rj.size / max(n, 1), 1.0)
        ratio.append(float(np.sqrt(np.sum(rj**2) / dof_j)) if rj.size else float("nan"))
        robust.append(
            float(1.4826 * np.median(np.abs(rj - np.median(rj)))) if rj.size else float("nan")
        )
    return GoodnessOfFit(
        chi2, dof, float(chi2_sf(chi2, dof)), np.asarray(ratio), np.asarray(robust)
    )
