"""Figures for fits and simulations (matplotlib, imported lazily inside each function).

Figures are built with `matplotlib.figure.Figure` directly (no pyplot, no global backend or
rcParams changes), so importing greybox never imports matplotlib and plotting never touches
the caller's matplotlib state. Every axis is labelled with its unit.
"""

from __future__ import annotations

import contextlib
import contextvars
from pathlib import Path

import numpy as np

from greybox._estimate.metrics import OUTLIER_SIGMAS
from greybox.plots import _label

DPI = 200  # raster figures (png); svg and pdf are vector
# zlib level of the PNGs (the same pixels): level 1 instead of Pillow's 6 writes the six
# figures of the TCLab two-heater result ~0.1 s faster (of 1.8 s), in files 18 % larger
PNG_COMPRESS_LEVEL = 1


# (pool, futures) of `png_writes_in_background`, where one is open
_PNG_WRITES = contextvars.ContextVar("greybox_png_writes", default=None)


def save_figure(fig, path, fmt: str | None = None):
    """Save `fig` to `path` in `fmt` (png, svg, pdf; None: the path's suffix) and return the
    path written (its suffix replaced by the format). A PNG is drawn here and, inside
    `png_writes_in_background`, compressed and written by a thread while the next figure
    is drawn."""
    path = Path(path)
    if fmt is not None:
        path = path.with_suffix("." + fmt)
    kind = path.suffix.lstrip(".") or "png"
    if kind != "png":
        fig.savefig(path, dpi=DPI, format=kind)
        return path
    rgba = _render(fig)
    writes = _PNG_WRITES.get()
    if writes is None:
        _write_png(path, rgba)
    else:
        pool, futures = writes
        futures.append(pool.submit(_write_png, path, rgba))
    return path


def _render(fig) -> np.ndarray:
    """The figure's pixels at `DPI` (RGBA), as `fig.savefig` draws them (the caller's figure
    keeps its own resolution and canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas, dpi = fig.canvas, fig.dpi
    try:
        fig.set_dpi(DPI)
        agg = FigureCanvasAgg(fig)
        agg.draw()
        return np.array(agg.buffer_rgba())  # a copy: the figure can be drawn again
    finally:
        fig.set_canvas(canvas)
        fig.set_dpi(dpi)


def warm_up() -> None:
    """Draw a small figure and discard it: what the first figure of a process costs beyond
    the others (Agg, the fonts and their glyphs), paid in advance."""
    fig = _figure(2.0, 1.5)
    ax = fig.subplots()
    ax.plot([0.0, 1.0], [0.0, 1.0], ".-", label="measured")
    ax.legend(loc="best", fontsize=7)
    ax.set_xlabel("time [s]")
    ax.set_title("warm-up", fontsize=10)
    _render(fig)


def _write_png(path: Path, rgba: np.ndarray) -> None:
    from matplotlib.image import imsave

    # the arguments of matplotlib's own PNG writer (`print_png`): the same file as savefig's
    imsave(
        path,
        rgba,
        format="png",
        origin="upper",
        dpi=DPI,
        pil_kwargs={"compress_level": PNG_COMPRESS_LEVEL},
    )


@contextlib.contextmanager
def png_writes_in_background():
    """Within this block PNGs are compressed and written by one thread while the figures
    after them are drawn (zlib lets go of the interpreter). Every file is written, and the
    first error writing one raised, when the block ends."""
    from concurrent.futures import ThreadPoolExecutor

    with ThreadPoolExecutor(max_workers=1, thread_name_prefix="greybox-png") as pool:
        futures = []
        token = _PNG_WRITES.set((pool, futures))
        try:
            yield
        finally:
            _PNG_WRITES.reset(token)
        for future in futures:
            future.result()


def axis_unit(channel, file_units=None) -> tuple:
    """(to_unit: SI -> shown values, unit) for a channel's axis: the unit of the fit's files
    (params.json "file_units") when known, else the channel's readable or own unit
    (`greybox.report._markdown.channel_unit`): a user's x_mm output is drawn in mm, never um."""
    from greybox.report._markdown import channel_unit

    unit = (file_units or {}).get(channel.name)
    if isinstance(unit, str):
        from greybox.io._units import channel_conversion

        try:
            conv = channel_conversion(channel, unit)
        except ValueError:
            conv = None
        if conv is not None:
            scale, offset = conv
            return (lambda v: (np.asarray(v) - offset) / scale), unit
    factor, unit = channel_unit(channel)
    return (lambda v: np.asarray(v) * factor), unit


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
    relative_to_rest: bool | None = None,
    file_units: dict | None = None,
    fmt: str | None = None,
) -> None:
    """Measured vs model for one run, one panel per output, the input waveform(s) beneath.

    `y`, `y_model`: readings (N,) or (N, n_y) in SI; `sigma`: noise per output (SI);
    `fit_percent`: simulation fit % per output (a scalar for one output), shown on each panel;
    `outputs`, `input_labels`: the device's `Channel`s (units from them and `file_units`:
    an x_mm output is drawn in mm) or (label, SI unit) pairs. Outputs are shown
    relative to the model's reading at the first frame (the rest position, which absorbs the
    camera offset) when `relative_to_rest` (None: for position outputs, in m, whose camera
    offset is arbitrary; other outputs are absolute); frames further than the outlier
    threshold from the model are marked.
    """
    import textwrap

    t = np.asarray(t_s, dtype=float)
    y, y_model = _columns(y, t.size), _columns(y_model, t.size)
    n_y = y.shape[1]
    sig = np.broadcast_to(np.asarray(sigma, dtype=float), (n_y,))
    pct = np.broadcast_to(np.asarray(fit_percent, dtype=float).reshape(-1), (n_y,))
    fig = _figure(9.0, 2.2 + 3.0 * n_y)
    axes = fig.subplots(n_y + 1, 1, sharex=True, height_ratios=[3] * n_y + [1])
    for j, top in enumerate(axes[:-1]):
        label, to_unit, uy = _label(outputs[j], j, file_units)
        unit = getattr(outputs[j], "si_unit", None) or outputs[j][1]
        relative = unit == "m" if relative_to_rest is None else relative_to_rest
        ref = to_unit(_rest_reference(y_model[:, j])) if relative else 0.0
        meas = to_unit(y[:, j]) - ref
        model = to_unit(y_model[:, j]) - ref
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
        text = f"{label} [{uy}]" + (" relative to rest" if relative else "")
        top.set_ylabel("\n".join(textwrap.wrap(text, 28)), fontsize=8)
        top.legend(loc="best", fontsize=7)
        top.grid(alpha=0.3)
        fit_text = f"simulation fit {pct[j]:.1f} %"
        top.set_title(
            f"{name} ({role}): {fit_text}" if j == 0 else f"{label}: {fit_text}", fontsize=10
        )
    bottom = axes[-1]
    tt, vv = _steps(inputs, float(t.min()), float(t.max()))
    for k in range(vv.shape[1]):
        label, to_unit, uu = _label(input_labels[min(k, len(input_labels) - 1)], k)
        bottom.step(
            tt, to_unit(vv[:, k]), where="post", color=f"C{k + 1}", lw=1.0, label=f"{label} [{uu}]"
        )
    bottom.set_ylabel(
        "input"
        if vv.shape[1] > 1
        else "\n".join(textwrap.wrap(f"{label} [{uu}]", 28)),
        fontsize=8,
    )
    if vv.shape[1] > 1:
        bottom.legend(loc="best", fontsize=7)
    bottom.set_xlabel("time [s]")
    bottom.grid(alpha=0.3)
    bottom.set_xlim(float(t.min()), float(t.max()))
    save_figure(fig, path, fmt)


def residuals_figure(
    path,
    runs,
    *,
    sigma: float,
    output: tuple = ("shuttle displacement", "m"),
    file_units: dict | None = None,
    fmt: str | None = None,
) -> None:
    """Residuals (measured - model) of one output per run, with +-sigma and the outlier threshold.

    `runs`: sequence of (name, role, t_s, y, y_model) in SI (one output column each);
    `output`: the output's `Channel` or (label, SI unit).
    """
    label, to_unit, uy = _label(output, 0, file_units)
    fy = float(to_unit(1.0) - to_unit(0.0))  # residuals are differences: the scale only
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
        f"{label}: residuals, measured - model\n(dotted: +-sigma = {s:.3g} {uy}; dashed: "
        f"outlier threshold {OUTLIER_SIGMAS:g} sigma; clipped at 8 sigma)",
        fontsize=9,
    )
    save_figure(fig, path, fmt)


def correlation_figure(path, labels, correlation, fmt: str | None = None) -> None:
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
    save_figure(fig, path, fmt)


def band_figure(
    path,
    band,
    inputs,
    *,
    title: str = "",
    output_labels: tuple = (("shuttle displacement", "m"),),
    input_labels: tuple = (("laser power", "W"),),
    output_channels: tuple = (),
    input_channels: tuple = (),
    file_units: dict | None = None,
    fmt: str | None = None,
):
    """Simulated response with its band, one panel per output channel (`output_labels`:
    (description, SI unit) per output), and one panel per input channel beneath
    (`input_labels`). With `output_channels` / `input_channels` (the device's `Channel`s)
    labels and units come from them (and `file_units`). Returns the matplotlib `Figure`
    (already saved to `path`, in `fmt`)."""
    from greybox.plots import plot_simulation

    n_y = _columns(band.y, np.size(band.t_s)).shape[1]
    n_u = np.asarray(inputs.values).reshape(np.size(inputs.times_s), -1).shape[1]
    fig = _figure(9.0, 1.0 + 2.2 * n_y + 1.1 * n_u)
    axes = fig.subplots(n_y + n_u, 1, sharex=True, height_ratios=[3] * n_y + [1] * n_u)
    plot_simulation(
        band,
        inputs,
        axes=np.atleast_1d(axes),
        outputs=output_channels or output_labels,
        input_channels=input_channels or input_labels,
        file_units=file_units,
        title=title,
    )
    save_figure(fig, path, fmt)
    return fig


def residual_correlation_figure(
    path, analysis, *, outputs=None, input_labels=None, fmt: str | None = None
):
    """Residual tests of a fit (`FitResult.residuals` or `ValidationResult.residuals`), as
    MATLAB `resid`: per output, the autocorrelation of the residuals over lags 0..M frames
    and their cross-correlation with each input (input leading: positive lags), pooled over
    the runs, with the 99 % band of white noise (`greybox.plots.plot_residual_tests`)."""
    from greybox.plots import plot_residual_tests

    fig = plot_residual_tests(analysis, outputs=outputs or (), inputs=input_labels or ())
    save_figure(fig, path, fmt)
    return fig
