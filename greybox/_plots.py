"""PNG figures for fits and simulations (matplotlib, imported lazily inside each function).

Figures are built with `matplotlib.figure.Figure` directly (no pyplot, no global backend or
rcParams changes), so importing greybox never imports matplotlib and plotting never touches
the caller's matplotlib state. Every axis is labelled with its unit.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from greybox._fit import OUTLIER_SIGMAS
from greybox._report import display_unit

DPI = 110


def _figure(width: float, height: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width, height), layout="constrained")


def _steps(wave, t0: float, t1: float):
    """(t, levels (n, channels)) that draw a piecewise-constant waveform over [t0, t1]."""
    times = np.asarray(wave.times_s, dtype=float)
    levels = np.asarray(wave.values, dtype=float).reshape(times.size, -1)
    t = np.concatenate([[min(t0, times[0])], times, [max(t1, wave.end_s)]])
    v = np.concatenate([np.zeros((1, levels.shape[1])), levels, levels[-1:]])
    return t, v


def _rest_reference(model_y: np.ndarray) -> float:
    finite = model_y[np.isfinite(model_y)]
    return float(finite[0]) if finite.size else 0.0


def _columns(a, n: int) -> np.ndarray:
    return np.asarray(a, dtype=float).reshape(n, -1)


def run_figure(
    path,
    *,
    name: str,
    role: str,
    t_s,
    y,
    y_model,
    inputs,
    sigma,
    fit_percent,
    outputs: tuple = (("shuttle displacement", "m"),),
    input_labels: tuple = (("laser power", "W"),),
) -> None:
    """Measured vs model for one run, one panel per output, the input waveform(s) beneath.

    `y`, `y_model`: readings (N,) or (N, n_y) in SI; `sigma`: noise per output (SI);
    `fit_percent`: simulation fit % per output (a scalar for one output), shown on each panel;
    `outputs`, `input_labels`: (label, SI unit) per output / input channel. Outputs are shown
    relative to the model's reading at the first frame (the rest position, which absorbs the
    camera offset); frames further than the outlier threshold from the model are marked.
    """
    t = np.asarray(t_s, dtype=float)
    y, y_model = _columns(y, t.size), _columns(y_model, t.size)
    n_y = y.shape[1]
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n_y,))
    pct = np.broadcast_to(np.asarray(fit_percent, dtype=float).reshape(-1), (n_y,))
    fig = _figure(9.0, 2.2 + 3.0 * n_y)
    axes = fig.subplots(n_y + 1, 1, sharex=True, height_ratios=[3] * n_y + [1])
    for j, top in enumerate(axes[:-1]):
        label, unit = outputs[j]
        fy, uy = display_unit(unit)
        ref = _rest_reference(y_model[:, j])
        meas = (y[:, j] - ref) * fy
        model = (y_model[:, j] - ref) * fy
        outlier = np.abs(y[:, j] - y_model[:, j]) > OUTLIER_SIGMAS * sig[j]
        top.plot(t, meas, ".", ms=3.5, color="0.35", label="measured")
        top.plot(
            t,
            model,
            "-",
            lw=1.3,
            color="C0",
            label="model (free-run simulation, at the frame times)",
        )
        if outlier.any():
            top.plot(
                t[outlier],
                meas[outlier],
                "x",
                ms=6,
                color="C3",
                label=f"outliers (> {OUTLIER_SIGMAS:g} sigma)",
            )
        top.set_ylabel(f"{label} [{uy}]\n(relative to rest)")
        top.legend(loc="upper right", fontsize=8)
        top.grid(alpha=0.3)
        fit_text = f"simulation fit {pct[j]:.1f} %"
        top.set_title(
            f"{name} ({role}): {fit_text}" if j == 0 else f"{label}: {fit_text}", fontsize=10
        )
    bottom = axes[-1]
    tt, vv = _steps(inputs, float(t.min()), float(t.max()))
    for k in range(vv.shape[1]):
        label, unit = input_labels[min(k, len(input_labels) - 1)]
        fu, uu = display_unit(unit)
        bottom.step(
            tt, vv[:, k] * fu, where="post", color=f"C{k + 1}", lw=1.0, label=f"{label} [{uu}]"
        )
    bottom.set_ylabel("input" if vv.shape[1] > 1 else f"{input_labels[0][0]}\n[{uu}]")
    if vv.shape[1] > 1:
        bottom.legend(loc="upper right", fontsize=7)
    bottom.set_xlabel("time [s]")
    bottom.grid(alpha=0.3)
    bottom.set_xlim(float(t.min()), float(t.max()))
    fig.savefig(Path(path), dpi=DPI)


def residuals_figure(
    path, runs, *, sigma: float, output: tuple = ("shuttle displacement", "m")
) -> None:
    """Residuals (measured - model) of one output per run, with +-sigma and the outlier threshold.

    `runs`: sequence of (name, role, t_s, y, y_model) in SI (one output column each).
    """
    fy, uy = display_unit(output[1])
    n = len(runs)
    cols = 3 if n > 4 else max(n, 1)
    rows = int(np.ceil(n / cols))
    fig = _figure(4.0 * cols, 2.3 * rows + 0.6)
    axes = np.atleast_1d(fig.subplots(rows, cols, sharey=True, squeeze=False)).reshape(-1)
    s = sigma * fy
    for ax, (name, role, t, y, y_model) in zip(axes, runs):
        r = (np.asarray(y) - np.asarray(y_model)) * fy
        out = np.abs(r) > OUTLIER_SIGMAS * s
        ax.plot(np.asarray(t)[~out], r[~out], ".", ms=2.5, color="0.3")
        ax.plot(np.asarray(t)[out], np.clip(r[out], -8 * s, 8 * s), "x", ms=5, color="C3")
        for k, style in ((1, ":"), (OUTLIER_SIGMAS, "--")):
            ax.axhline(k * s, color="C0", ls=style, lw=0.8)
            ax.axhline(-k * s, color="C0", ls=style, lw=0.8)
        ax.set_title(f"{name} ({role})", fontsize=9)
        ax.set_ylim(-8 * s, 8 * s)
        ax.grid(alpha=0.3)
    for ax in axes[n:]:
        ax.set_visible(False)
    for ax in axes[:n]:
        ax.set_xlabel("time [s]", fontsize=8)
    for ax in axes[::cols]:
        ax.set_ylabel(f"residual [{uy}]", fontsize=8)
    fig.suptitle(
        f"{output[0]}: residuals, measured - model (dotted: +-sigma = {s:.3g} {uy}; dashed: "
        f"outlier threshold {OUTLIER_SIGMAS:g} sigma; clipped at 8 sigma)",
        fontsize=9,
    )
    fig.savefig(Path(path), dpi=DPI)


def correlation_figure(path, labels, correlation) -> None:
    """Heatmap of the parameter correlation matrix (raw coordinates), values annotated."""
    corr = np.asarray(correlation, dtype=float)
    k = corr.shape[0]
    size = min(max(3.5, 0.55 * k + 2.0), 12.0)
    fig = _figure(size + 1.2, size)
    ax = fig.subplots()
    im = ax.imshow(np.nan_to_num(corr), vmin=-1, vmax=1, cmap="RdBu_r")
    ax.set_xticks(range(k), labels, rotation=60, ha="right", fontsize=7)
    ax.set_yticks(range(k), labels, fontsize=7)
    if k <= 16:
        for i in range(k):
            for j in range(k):
                v = corr[i, j]
                ax.text(
                    j,
                    i,
                    "n/a" if not np.isfinite(v) else f"{v:.2f}",
                    ha="center",
                    va="center",
                    fontsize=6,
                    color="white" if abs(v) > 0.6 else "black",
                )
    fig.colorbar(im, ax=ax, label="correlation (dimensionless, -1 to 1)")
    ax.set_title("Parameter correlation (posterior, transformed coordinates)", fontsize=9)
    fig.savefig(Path(path), dpi=DPI)


def band_figure(
    path,
    band,
    inputs,
    *,
    title: str = "",
    output_labels: tuple = (("shuttle displacement", "m"),),
    input_labels: tuple = (("laser power", "W"),),
):
    """Simulated response with its band, one panel per output channel (`output_labels`:
    (description, SI unit) per output), and one panel per input channel beneath
    (`input_labels`). Returns the matplotlib `Figure` (already saved to `path`)."""
    t = np.asarray(band.t_s)
    y = _columns(band.y, t.size)
    lower, upper = _columns(band.lower, t.size), _columns(band.upper, t.size)
    n_y = y.shape[1]
    tt, vv = _steps(inputs, float(t.min()), float(t.max()))
    n_u = vv.shape[1]
    output_labels = tuple(output_labels) + tuple(
        (f"output {j + 1}", "") for j in range(len(output_labels), n_y)
    )
    input_labels = tuple(input_labels) + tuple(
        (f"input {k + 1}", "") for k in range(len(input_labels), n_u)
    )
    fig = _figure(9.0, 1.0 + 2.2 * n_y + 1.1 * n_u)
    axes = fig.subplots(n_y + n_u, 1, sharex=True, height_ratios=[3] * n_y + [1] * n_u)
    axes = np.atleast_1d(axes)
    kind = "prediction interval" if band.includes_noise else "confidence band"
    for j in range(n_y):
        ax = axes[j]
        fy, uy = display_unit(output_labels[j][1])
        lo, hi = lower[:, j] * fy, upper[:, j] * fy
        finite = np.isfinite(lo) & np.isfinite(hi)
        ax.fill_between(
            t,
            np.where(finite, lo, np.nan),
            np.where(finite, hi, np.nan),
            color=f"C{j}",
            alpha=0.25,
            lw=0,
            label=f"{band.level * 100:g} % {kind}",
        )
        ax.plot(t, y[:, j] * fy, "-", color=f"C{j}", lw=1.3, label="model (simulation)")
        ax.set_ylabel(f"{output_labels[j][0]}\n[{uy}]", fontsize=8)
        ax.legend(loc="upper right", fontsize=8)
        ax.grid(alpha=0.3)
    axes[0].set_title(title or "Simulated response", fontsize=10)
    for k in range(n_u):
        ax = axes[n_y + k]
        fu, uu = display_unit(input_labels[k][1])
        ax.step(tt, vv[:, k] * fu, where="post", color="0.3", lw=1.0)
        ax.set_ylabel(f"{input_labels[k][0]}\n[{uu}]", fontsize=8)
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    axes[-1].set_xlim(float(t.min()), float(t.max()))
    fig.savefig(Path(path), dpi=DPI)
    return fig


def residual_correlation_figure(path, analysis, *, outputs=None, input_labels=None) -> None:
    """Residual tests of a fit (`FitResult.residuals` or `ValidationResult.residuals`), as
    MATLAB `resid`: per output, the autocorrelation of the residuals over lags 0..M frames
    and their cross-correlation with each input (input leading: positive lags), pooled over
    the runs, with the 99 % band of white noise. The title of each panel carries the
    Ljung-Box p-value."""
    a = analysis
    n_y = a.autocorrelation.shape[0]
    n_u = a.cross_correlation.shape[1]
    names = outputs or a.output_names
    inputs = input_labels or tuple(f"input {k + 1}" for k in range(n_u))
    fig = _figure(4.2 * (1 + n_u), 2.6 * n_y + 0.4)
    axes = np.atleast_2d(fig.subplots(n_y, 1 + n_u, squeeze=False))
    band = a.band()
    with np.errstate(divide="ignore"):
        cband = 2.5758293035489004 / np.sqrt(a.cross_pairs)  # z(0.995)
    for j in range(n_y):
        ax = axes[j, 0]
        ax.bar(a.lags[1:], a.autocorrelation[j, 1:], width=0.6, color="C0")
        ax.fill_between(a.lags[1:], -band[j, 1:], band[j, 1:], color="0.8", zorder=0)
        p = a.p_value[j]
        ax.set_title(f"{names[j]}: autocorrelation (Ljung-Box p = {p:.2g})", fontsize=9)
        ax.set_xlabel("lag [frames]", fontsize=8)
        ax.grid(alpha=0.3)
        for k in range(n_u):
            ax = axes[j, 1 + k]
            ax.bar(a.cross_lags, a.cross_correlation[j, k], width=0.6, color="C1")
            ax.fill_between(a.cross_lags, -cband[j], cband[j], color="0.8", zorder=0)
            ax.set_title(f"{names[j]}: cross-correlation with {inputs[k]}", fontsize=9)
            ax.set_xlabel("lag [frames] (positive: the input leads)", fontsize=8)
            ax.grid(alpha=0.3)
    fig.suptitle(
        f"Residuals (measured - model): {a.verdict}; grey: 99 % band of white noise "
        f"(frames of {a.frame_interval_s * 1e3:.3g} ms)",
        fontsize=8,
    )
    fig.savefig(Path(path), dpi=DPI)
