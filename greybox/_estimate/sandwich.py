"""The meat of the sandwich covariance: model-error residuals and the HAC long-run covariance
of the score contributions (pure numpy).

What the sandwich is asked to estimate, and why it is built this way. The spread of the
estimate over repeated experiments comes from the noise: Var(sum_t g_t) with g_t = J_t^T e_t
the score contributions. The residuals are r_t = m_t + e_t, m_t the model's deterministic
misfit when the structure is wrong, and a Newey-West meat built from r_t counts the misfit's
slow products m_t m_s as if they were noise: on a fixed design the sandwich is conservative
under misspecification (Freedman 2006; Buja et al. 2019, "Models as approximations I"). On
the one-node chevron fitted to two-node data (`benchmarks/whiteness.py`), plain Newey-West
errors came out 1.5-2.3x the estimates' spread. Three steps, each from the literature:

1. Model-error model (Ljung & Guo 1997, "The role of model validation for assessing the
   size of the unmodeled dynamics"; Ljung 2000): the part of the residuals that the
   inputs explain is misfit, not noise. Per run and output the residuals are regressed on
   a constant and each input at frame lags 0..K-1 (an FIR model error model, K the lags
   the residual analysis shows) and the HAC sees only what is left. On the benchmark this
   brings the HAC errors to 1.05-1.2x the spread.
2. Andrews & Monahan (1992) VAR(1) prewhitening with recolouring: the Bartlett kernel's
   bias on strongly autocorrelated scores (AR(1) noise at rho = 0.8 per frame) is what
   left right-structure coverage at 0.91; prewhitened, the kernel sees nearly white
   scores and the VAR recolours them exactly.
3. Degrees of freedom (MacKinnon & White 1985, HC1): the meat is scaled by n / (n - k), k
   the fitted parameters plus the model-error coefficients.

Runs are independent: the meat is a sum over runs, with a VAR fitted to all of them.

Both steps take many fits at once (`model_error_residuals_many`, `hac_meats`: every
regression of every run, every meat of every device of a batch in stacked passes, as the
residual tests do); one fit is a stack of one, so a fit alone and in a batch compute alike.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from greybox._estimate.residuals import FrameGrid, _bucket_rows

AM_CAP = 0.97  # Andrews-Monahan: singular values of the VAR(1) matrix capped here
REGRESSION_BLOCK = 1 << 20  # design elements (8 MB) of one stacked pass of regressions: a
# wave of 64 chevrons is ~0.25 M; a 100,000-frame run alone is more, and then goes alone


def _input_lags(t_s, grid: FrameGrid, inputs, n_frames: int, lags: int) -> np.ndarray:
    """(N, n_u * lags) each input at frame lags 0..lags-1: u(t_i - k dt) when `inputs` is a
    function of time (exact at any frame time, gaps and jitter included); from an (N, n_u)
    array of levels at the frames, the level `k` slots back on the frame grid (an empty
    slot holds the level of the frame before; before the first frame, the first level)."""
    if lags <= 0:
        return np.zeros((n_frames, 0))
    if callable(inputs):
        t = np.asarray(t_s, dtype=float).reshape(-1)
        dt = grid.dt_s if np.isfinite(grid.dt_s) else 0.0
        cols = [
            np.asarray(inputs(t - k * dt), dtype=float).reshape(n_frames, -1) for k in range(lags)
        ]
        return np.concatenate(cols, axis=1)
    u = np.asarray(inputs, dtype=float).reshape(n_frames, -1)
    return _lagged_levels([grid], [u], n_frames, lags)[0]


def _lagged_levels(grids, levels, n_f: int, lags: int) -> np.ndarray:
    """(Q, n_f, lags * n_u) the `_input_lags` of Q runs given their input levels (N_q, n_u),
    one n_u for all, placed on their frame `grids` in one stacked pass (zero-padded rows)."""
    n_u = levels[0].shape[1]
    w = max(g.n_slots for g in grids)
    slots = np.zeros((len(grids), n_f), dtype=int)
    slot_u = np.full((len(grids), w, n_u), np.nan)
    for q, (g, u) in enumerate(zip(grids, levels)):
        slots[q, : g.slots.size] = g.slots
        slot_u[q, g.slots] = u
    # missing timestamps: hold the last known level (forward fill: each slot reads the latest
    # slot at or before it that holds a finite level, per input; one gather)
    known = np.isfinite(slot_u)
    last = np.maximum.accumulate(np.where(known, np.arange(w)[None, :, None], -1), axis=1)
    rows = np.arange(len(grids))[:, None, None]
    filled = np.where(last >= 0, slot_u[rows, np.maximum(last, 0), np.arange(n_u)], 0.0)
    back = np.maximum(slots[:, :, None] - np.arange(lags), 0)  # (Q, n_f, lags) slots
    return filled[rows, back].reshape(len(grids), n_f, lags * n_u)  # (Q, n_f, lags, n_u)


def _n_inputs(t_s, inputs, n_frames: int) -> int:
    if inputs is None:
        return 0
    if callable(inputs):
        return int(np.asarray(inputs(np.asarray(t_s, dtype=float)[:1])).size)
    return int(np.asarray(inputs).reshape(n_frames, -1).shape[1])


def model_error_residuals(t_s, residuals, valid, inputs, lags: int) -> tuple[np.ndarray, int]:
    """Residuals less their FIR model-error model (step 1 above), and the coefficients fitted.

    `residuals` (N, n_y), `valid` (N, n_y) the readings used, `inputs`: the input as a
    function of time (t (M,) -> (M, n_u)), or its levels at the frames (N, n_u), or None (a
    constant only); `lags` K. Per output, least squares over its valid readings of the
    residual on a constant and each input at lags 0..K-1 frames (see `_input_lags`: on the
    frame grid of `analyse_run` for levels, at t - k dt for a function), with K cut to keep
    at least two readings per coefficient. `fit` passes the levels at the frames.
    **Returns:** ((N, n_y) what the model error model leaves, zero at unused readings; the
    number of coefficients fitted, the rank of each regression, summed over outputs).
    """
    return model_error_residuals_many([(t_s, residuals, valid, inputs, lags)])[0]


def model_error_residuals_many(runs) -> list[tuple[np.ndarray, int]]:
    """`model_error_residuals` of each (t_s, residuals, valid, inputs, lags) of `runs`: every
    output of every run one regression, in stacked passes over runs of similar length (a
    power-of-two bucket each, so padding at most doubles the memory one run alone takes),
    at most REGRESSION_BLOCK design elements a pass (a long record: one run at a time)."""
    sizes = [np.shape(run[1])[0] for run in runs]
    n_u = np.array([_n_inputs(run[0], run[3], n) for run, n in zip(runs, sizes)], dtype=int)
    out: list = [None] * len(runs)
    for members in _bucket_rows(sizes):
        width = max(1 + n_u[i] * int(runs[i][4]) for i in members)
        step = max(1, REGRESSION_BLOCK // max(max(sizes[i] for i in members) * width, 1))
        for c in range(0, len(members), step):
            part = members[c : c + step]
            for i, done in zip(part, _regressions([runs[i] for i in part], n_u[part])):
                out[i] = done
    return out


def _regressions(runs, n_u) -> list[tuple[np.ndarray, int]]:
    """`model_error_residuals_many` of runs (`n_u` inputs each) padded to the longest (zero
    rows stand for unused readings); the regressions with the same number of coefficients
    solved as one stack: the minimum-norm least-squares solution of each from its SVD,
    singular values at or below eps max(rows, columns) of the largest left out, as
    `np.linalg.lstsq` does; the rank is the number kept."""
    res = [np.asarray(run[1], dtype=float) for run in runs]
    res = [x.reshape(x.shape[0], -1) for x in res]
    sizes = [x.shape[0] for x in res]
    n_f = max(sizes)
    r = np.zeros((len(runs), n_f, max(x.shape[1] for x in res)))
    ok = np.zeros(r.shape, dtype=bool)
    for i, (x, run) in enumerate(zip(res, runs)):
        n, n_y = x.shape
        valid = np.asarray(run[2], dtype=bool).reshape(x.shape) & np.isfinite(x)
        r[i, :n, :n_y], ok[i, :n, :n_y] = np.where(valid, x, 0.0), valid
    counts = ok.sum(axis=1)  # (S, n_y)
    lags = np.array([int(run[4]) for run in runs])[:, None]
    k = np.where(
        n_u[:, None] > 0, np.clip((counts // 2 - 1) // np.maximum(n_u, 1)[:, None], 0, None), 0
    )
    k = np.minimum(k, np.maximum(lags, 0))
    cols = 1 + n_u[:, None] * k  # (S, n_y) coefficients of each regression
    design = _designs(runs, sizes, n_f, n_u, int(k.max(initial=0)))  # (S, N, C)
    left = np.zeros_like(r)
    rank = np.zeros(counts.shape, dtype=int)
    todo = counts > 0
    for c in np.unique(cols[todo]):
        si, yj = np.nonzero(todo & (cols == c))
        m = ok[si, :, yj]  # (Q, N)
        x = design[si, :, :c]  # a copy (fancy index), zeroed at unused rows and scaled in place
        np.copyto(x, 0.0, where=~m[..., None])
        y = np.where(m, r[si, :, yj], 0.0)
        scale = np.max(np.abs(x), axis=1, keepdims=True)
        x /= np.where(scale > 0, scale, 1.0)
        u, sv, vt = np.linalg.svd(x, full_matrices=False)
        cutoff = np.finfo(float).eps * np.maximum(counts[si, yj], c)[:, None] * sv[:, :1]
        keep = sv > cutoff
        inv = np.where(keep, 1.0 / np.where(keep, sv, 1.0), 0.0)
        beta = np.einsum("qkc,qk->qc", vt, inv * np.einsum("qnk,qn->qk", u, y))
        left[si, :, yj] = np.where(m, y - np.einsum("qnc,qc->qn", x, beta), 0.0)
        rank[si, yj] = keep.sum(axis=1)
    return [
        (left[i, :n, :n_y], int(rank[i].sum())) for i, (n, n_y) in enumerate(x.shape for x in res)
    ]


def _designs(runs, sizes, n_f: int, n_u, lags: int) -> np.ndarray:
    """(S, n_f, 1 + max n_u * lags): per run a constant and its inputs at frame lags
    0..lags-1 (`_input_lags`), zero-padded; runs given their input levels at the frames all
    placed on their frame grids in one stacked pass."""
    width = 1 + int(n_u.max(initial=0)) * lags
    out = np.zeros((len(runs), n_f, width))
    out[:, :, 0] = 1.0
    levels = [i for i, run in enumerate(runs) if run[3] is not None and not callable(run[3])]
    for i, run in enumerate(runs):
        if run[3] is not None and callable(run[3]) and lags:
            lagged = _input_lags(run[0], FrameGrid.build(run[0]), run[3], sizes[i], lags)
            out[i, : sizes[i], 1 : 1 + lagged.shape[1]] = lagged
    if not levels or not lags:
        return out
    for nu in np.unique(n_u[levels]):
        if nu == 0:  # no input: a constant only
            continue
        idx = [i for i in levels if n_u[i] == nu]
        grids = [FrameGrid.build(runs[i][0]) for i in idx]
        u = [np.asarray(runs[i][3], dtype=float).reshape(sizes[i], -1) for i in idx]
        out[idx, :, 1 : 1 + lags * int(nu)] = _lagged_levels(grids, u, n_f, lags)
    return out


@dataclasses.dataclass(frozen=True)
class HACMeat:
    """Long-run covariance of the score contributions, summed over runs (the sandwich's meat).

    `meat` (P, P) = (I - A)^-1 Omega_v (I - A)^-T x n / (n - k): A the VAR(1) of the scores
    (Andrews & Monahan 1992, singular values capped at `AM_CAP`; A = 0 without
    prewhitening), Omega_v = sum over runs of Gamma_0 + sum_{l=1..L} (1 - l/(L+1)) (Gamma_l
    + Gamma_l^T) of the VAR residuals v_t = g_t - A g_(t-1), Gamma_l = sum_t v_t v_(t-l)^T over
    the frame grid (Newey-West, Bartlett kernel); `bandwidth` L in frames from Andrews'
    (1991) AR(1) plug-in rule for the Bartlett kernel on v, L = floor(1.1447 (a T)^(1/3))
    with T the mean run length in frames, capped at T / 2 (`rho` the pooled lag-1
    autocorrelations of the components of v behind `a`); `var1` A, fitted to the score
    components scaled to unit RMS (so the meat does not depend on parameter scales) and
    given in those units; n / (n - k) the degrees-of-freedom factor (`dof_factor`).
    """

    meat: np.ndarray
    bandwidth: int
    rho: np.ndarray
    var1: np.ndarray
    dof_factor: float = 1.0


def _andrews_bandwidth(v, lengths, n_runs, active) -> tuple[np.ndarray, np.ndarray]:
    """Andrews' (1991) AR(1) plug-in bandwidth for the Bartlett kernel, pooled over each fit's
    runs: `v` (D, R, W, P) the runs' components on their grids, zero beyond each run's
    `lengths` (D, R; zero for a fit's missing runs). Returns (bandwidths (D,), rho (D, P))."""
    num = np.einsum("drtp,drtp->dp", v[:, :, 1:], v[:, :, :-1])
    before_last = np.arange(v.shape[2] - 1) < (lengths - 1)[..., None]
    den = np.einsum("drtp,drt->dp", v[:, :, :-1] ** 2, before_last.astype(float))
    rho = np.clip(np.where(den > 0, num / np.where(den > 0, den, 1.0), 0.0), -0.97, 0.97)
    t_mean = lengths.sum(axis=1) / n_runs
    r = np.where(active, rho, 0.0)
    s4 = (1.0 - r**2) ** 2  # innovation variance^2 of a unit-variance AR(1)
    a_num = np.sum(np.where(active, 4 * r**2 * s4 / ((1 - r) ** 6 * (1 + r) ** 2), 0.0), axis=1)
    a_den = np.sum(np.where(active, s4 / (1 - r) ** 4, 0.0), axis=1)
    alpha = np.where(a_den > 0, a_num / np.where(a_den > 0, a_den, 1.0), 0.0)
    return np.floor(1.1447 * (alpha * t_mean) ** (1.0 / 3.0)).astype(int), rho


def _cross_sum(x, y) -> np.ndarray:
    """(D, P, Q): per fit, the sum over its runs r and slots t of x[r, t]^T y[r, t], as one
    matrix product per fit (BLAS: ~14x numpy's einsum, which loops over r and t itself)."""
    d, n = x.shape[0], x.shape[1] * x.shape[2]
    return np.matmul(x.reshape(d, n, x.shape[-1]).transpose(0, 2, 1), y.reshape(d, n, y.shape[-1]))


def _lagged_cross_sums(g, max_lag: int) -> list:
    """[Gamma_l (D, P, P) for l = 1..`max_lag`]: per fit, the sum over its runs r and slots t
    of g[r, t + l]^T g[r, t], `g` (D, R, W, P) zero beyond each run's own slots. Each run is
    padded with `max_lag` more zero slots and the runs laid end to end, so a lag is a shift
    of one array (a view, no copy): a pair that reaches into the next run has its first
    member in the padding, and adds nothing."""
    d, r, w, p = g.shape
    flat = np.zeros((d, r, w + max_lag, p))
    flat[:, :, :w] = g
    flat = flat.reshape(d, r * (w + max_lag), p)
    n = flat.shape[1]
    lags = range(1, max_lag + 1)
    return [_cross_sum(flat[:, None, lag:], flat[:, None, : n - lag]) for lag in lags]


def hac_meat(
    runs,
    *,
    bandwidth: int | None = None,
    prewhiten: bool = True,
    n_readings: int | None = None,
    n_fitted: int = 0,
) -> HACMeat:
    """`runs`: sequence of (t_s (N,), scores (N, P)) with zero rows at unused frames.

    `bandwidth`: Bartlett bandwidth in frames (default: Andrews' plug-in); `prewhiten`:
    Andrews-Monahan VAR(1) prewhitening and recolouring; `n_readings`, `n_fitted`: the
    degrees-of-freedom factor n / (n - k) (none when `n_readings` is None). The runs are
    stacked on their frame grids, zero-padded to the longest (every sum over runs and slots
    is one product; the padding adds nothing).
    """
    return hac_meats(
        [runs],
        bandwidth=bandwidth,
        prewhiten=prewhiten,
        n_readings=[n_readings],
        n_fitted=[n_fitted],
    )[0]


def hac_meats(
    fits, *, bandwidth: int | None = None, prewhiten: bool = True, n_readings=None, n_fitted=None
) -> list[HACMeat]:
    """`hac_meat` of each element of `fits` (its runs, as `hac_meat` takes them), with
    `n_readings` and `n_fitted` one per fit (None: no factor). The fits with the same number
    of score components are one stacked pass (zero-padded runs and slots add nothing)."""
    fits = [list(f) for f in fits]
    n_readings = [None] * len(fits) if n_readings is None else list(n_readings)
    n_fitted = [0] * len(fits) if n_fitted is None else list(n_fitted)
    placed = []
    for runs in fits:
        grids = [FrameGrid.build(t_s) for t_s, _ in runs]
        scores = [np.asarray(g, dtype=float).reshape(np.size(t_s), -1) for t_s, g in runs]
        placed.append((grids, scores))
    by_p: dict = {}
    for d, (_, scores) in enumerate(placed):
        by_p.setdefault(scores[0].shape[1], []).append(d)
    out: list = [None] * len(fits)
    for p, members in by_p.items():
        meats = _hac_stack([placed[d] for d in members], p, bandwidth, prewhiten)
        for d, (meat, bw, rho, a) in zip(members, meats):
            factor = 1.0
            if n_readings[d] is not None and int(n_readings[d]) > int(n_fitted[d]):
                factor = float(n_readings[d]) / (int(n_readings[d]) - int(n_fitted[d]))
            out[d] = HACMeat(meat * factor, bw, rho, a, factor)
    return out


def _hac_stack(placed, p: int, bandwidth, prewhiten: bool) -> list:
    """(meat, bandwidth, rho, A) of fits with P score components each: their runs stacked
    (D fits, R runs, W slots, P) on their frame grids."""
    n_fits, n_runs = len(placed), np.array([len(grids) for grids, _ in placed])
    lengths = np.zeros((n_fits, int(n_runs.max())), dtype=int)
    for d, (grids, _) in enumerate(placed):
        lengths[d, : len(grids)] = [fg.n_slots for fg in grids]
    g = np.zeros((n_fits, lengths.shape[1], int(lengths.max()), p))
    for d, (grids, scores) in enumerate(placed):
        for k, (fg, s) in enumerate(zip(grids, scores)):
            g[d, k, fg.slots] = np.where(np.isfinite(s), s, 0.0)
    inside = (np.arange(g.shape[2]) < lengths[..., None])[..., None]
    active = np.any(g != 0, axis=(1, 2))  # (D, P)
    # each component to unit RMS, so that the VAR, its cap and the pseudo-inverse do not
    # depend on the parameters' units or scales (the meat is scaled back at the end)
    rms = np.sqrt(np.sum(g**2, axis=(1, 2)) / lengths.sum(axis=1)[:, None])
    unit = np.where(rms > 0, rms, 1.0)
    g = g / unit[:, None, None, :]
    a = np.zeros((n_fits, p, p))
    if prewhiten and active.any():
        # a component that is zero throughout has zero rows and columns in both sums, so
        # the VAR of the others is what it would be without it
        lagged = g[:, :, :-1] * inside[:, :, 1:]  # g_(t-1), for t inside each run
        sxx = _cross_sum(lagged, lagged)
        syx = _cross_sum(g[:, :, 1:], lagged)
        u, sv, vt = np.linalg.svd(syx @ np.linalg.pinv(sxx))
        a = (u * np.minimum(sv, AM_CAP)[:, None, :]) @ vt
        a = np.where(active[:, :, None] & active[:, None, :], a, 0.0)
        whitened = g.copy()
        whitened[:, :, 1:] -= g[:, :, :-1] @ a.transpose(0, 2, 1)[:, None]
        g = whitened * inside  # nothing beyond a run's end
    plug_in, rho = _andrews_bandwidth(g, lengths, n_runs, active)
    t_mean = lengths.sum(axis=1) / n_runs
    bw = plug_in if bandwidth is None else np.full(n_fits, int(bandwidth))
    bw = np.maximum(0, np.minimum(bw, (t_mean // 2).astype(int)))
    omega = _cross_sum(g, g)
    max_lag = int(min(bw.max(), g.shape[2] - 1))
    for lag, gam in enumerate(_lagged_cross_sums(g, max_lag), start=1):
        w = np.where(lag <= bw, 1.0 - lag / (bw + 1.0), 0.0)  # Bartlett, zero beyond each L
        omega += w[:, None, None] * (gam + gam.transpose(0, 2, 1))
    recolour = np.linalg.inv(np.eye(p) - a)
    meat = unit[:, :, None] * (recolour @ omega @ recolour.transpose(0, 2, 1)) * unit[:, None, :]
    return [(meat[d], int(bw[d]), rho[d], a[d]) for d in range(n_fits)]
