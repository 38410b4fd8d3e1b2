"""Public plotting functions: each draws onto the matplotlib axes you pass (or new ones) and
returns the `Figure`, so figures go into notebooks and papers as they are.

Labels and units come from the device's channels (`spec.outputs`, `spec.inputs`) and, when
given, the unit of the fit's files (``file_units``: a user's ``x_mm`` output is drawn in mm);
nothing here assumes a particular device. matplotlib is imported only when a function runs,
and pyplot never: greybox never changes the caller's matplotlib state.

    fig = greybox.plots.plot_fit(result, 0, outputs=spec.outputs, inputs=spec.inputs)
    fig.savefig("run0.pdf")
"""

from __future__ import annotations

import textwrap
from collections.abc import Sequence

import numpy as np

__all__ = [
    "plot_compare",
    "plot_fit",
    "plot_population",
    "plot_residual_tests",
    "plot_simulation",
]


def _new_axes(n: int, height_ratios=None, width: float = 8.0, height: float | None = None):
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height or 1.2 + 2.2 * n), layout="constrained")
    axes = fig.subplots(n, 1, sharex=True, squeeze=False, height_ratios=height_ratios)
    return fig, list(axes[:, 0])


def _axes(axes, n: int, height_ratios=None):
    """(figure, list of n axes): the caller's (one `Axes` or a sequence) or new ones."""
    if axes is None:
        return _new_axes(n, height_ratios)
    flat = list(np.atleast_1d(np.asarray(axes, dtype=object)).reshape(-1))
    if len(flat) < n:
        raise ValueError(f"needs {n} axes (one per output, then one per input), got {len(flat)}")
    return flat[0].get_figure(), flat[:n]


def _label(item, j: int, file_units=None, kind: str = "output"):
    """(label, SI -> shown values, unit) of a `Channel` or a (label, SI unit) pair."""
    from greybox.report._markdown import display_unit
    from greybox.report._plots import axis_unit

    if item is None:
        return f"{kind} {j + 1}", (lambda v: np.asarray(v)), "SI"
    if hasattr(item, "si_unit"):
        to_unit, unit = axis_unit(item, file_units)
        return item.description or item.name, to_unit, unit
    label, si = item
    factor, unit = display_unit(si)
    return label, (lambda v: np.asarray(v) * factor), unit


def _at(seq, j):
    seq = tuple(seq or ())
    return seq[j] if j < len(seq) else None


def _ylabel(ax, label: str, unit: str) -> None:
    # a long label wraps instead of running into the neighbouring panel's label
    import textwrap

    ax.set_ylabel("\n".join(textwrap.wrap(f"{label} [{unit}]", 28)), fontsize=8)


def _draw_inputs(axes, inputs, t0: float, t1: float, channels) -> None:
    from greybox.report._plots import _steps

    tt, vv = _steps(inputs, t0, t1)
    for k, ax in enumerate(axes):
        channel = _at(channels, k)
        label, to_unit, unit = _label(channel, k, kind="input")
        ax.step(tt, to_unit(vv[:, k]), where="post", color="0.3", lw=1.0, label=label)
        # a short panel: the channel's name on the axis, what it is in the legend
        short = getattr(channel, "name", None) or (label if len(label) <= 12 else f"input {k + 1}")
        ax.set_ylabel(f"{short} [{unit}]", fontsize=8)
        ax.legend(loc="best", fontsize=7, frameon=True, framealpha=0.8)
        ax.grid(alpha=0.3)


def _n_inputs(inputs) -> int:
    return np.asarray(inputs.values).reshape(np.size(inputs.times_s), -1).shape[1]


def _draw_band(ax, t, lo, hi, color, label, unit: str = "") -> None:
    """A band that stays visible when it is narrower than the line: filled, edged with
    dashed lines, and its widest width in the legend."""
    finite = np.isfinite(lo) & np.isfinite(hi)
    lo, hi = np.where(finite, lo, np.nan), np.where(finite, hi, np.nan)
    width = float(np.nanmax(hi - lo)) if finite.any() else float("nan")
    label = f"{label} (widest {width:.3g} {unit})".replace(" )", ")")
    ax.fill_between(t, lo, hi, color=color, alpha=0.35, lw=0, label=label)
    ax.plot(t, lo, "--", color=color, lw=0.7)
    ax.plot(t, hi, "--", color=color, lw=0.7)


def plot_simulation(
    band,
    inputs,
    *,
    axes=None,
    outputs: Sequence = (),
    input_channels: Sequence = (),
    file_units: dict | None = None,
    title: str = "",
):
    """A simulated response with its band (`greybox.Band`, from `Posterior.band`): one axis
    per output, then one per input channel of the waveform `inputs`. `outputs`,
    `input_channels`: the device's channels (or (label, SI unit) pairs)."""
    t = np.asarray(band.t_s, dtype=float)
    y = np.asarray(band.y, dtype=float).reshape(t.size, -1)
    lower = np.asarray(band.lower, dtype=float).reshape(t.size, -1)
    upper = np.asarray(band.upper, dtype=float).reshape(t.size, -1)
    n_y, n_u = y.shape[1], _n_inputs(inputs)
    fig, ax = _axes(axes, n_y + n_u, [3] * n_y + [1] * n_u)
    kind = "prediction interval" if band.includes_noise else "confidence band"
    for j in range(n_y):
        label, to_unit, unit = _label(_at(outputs, j), j, file_units)
        _draw_band(
            ax[j],
            t,
            to_unit(lower[:, j]),
            to_unit(upper[:, j]),
            f"C{j}",
            f"{band.level * 100:g} % {kind}",
            unit,
        )
        ax[j].plot(t, to_unit(y[:, j]), "-", color=f"C{j}", lw=1.3, label="model (simulation)")
        _ylabel(ax[j], label, unit)
        ax[j].legend(loc="best", fontsize=7)
        ax[j].grid(alpha=0.3)
    ax[0].set_title(title or "Simulated response", fontsize=9, wrap=True)
    _draw_inputs(ax[n_y:], inputs, float(t.min()), float(t.max()), input_channels)
    ax[-1].set_xlabel("time [s]")
    ax[-1].set_xlim(float(t.min()), float(t.max()))
    return fig


def plot_fit(
    result,
    run: int = 0,
    *,
    axes=None,
    outputs: Sequence = (),
    inputs: Sequence = (),
    file_units: dict | None = None,
    band: bool = True,
):
    """Measured readings of estimation run `run` of a `FitResult` against the fitted model's
    free-run simulation, with the 95 % confidence band of the shared parameters (`band`),
    one axis per output, then one per input. Values are absolute, in the channels' units."""
    e = result.experiments[run]
    t = np.asarray(e.t_s, dtype=float)
    y = np.asarray(e.y, dtype=float).reshape(t.size, -1)
    model = np.asarray(result.predict(run), dtype=float).reshape(t.size, -1)
    n_y, n_u = y.shape[1], _n_inputs(e.inputs)
    fig, ax = _axes(axes, n_y + n_u, [3] * n_y + [1] * n_u)
    lohi = None
    if band:
        b = result.posterior.band(e.inputs, t, t_start_s=getattr(e, "t_start_s", 0.0))
        lohi = (
            np.asarray(b.lower, dtype=float).reshape(t.size, -1),
            np.asarray(b.upper, dtype=float).reshape(t.size, -1),
        )
        # the band is of the shared parameters; centre it on this run's own prediction
        centre = np.asarray(b.y, dtype=float).reshape(t.size, -1)
        lohi = (lohi[0] - centre + model, lohi[1] - centre + model)
    pct = np.asarray(result.fit_percent.get(e.name, np.full(n_y, np.nan))).reshape(-1)
    for j in range(n_y):
        label, to_unit, unit = _label(_at(outputs, j), j, file_units)
        ax[j].plot(t, to_unit(y[:, j]), ".", ms=3, color="0.35", label="measured")
        if lohi is not None:
            _draw_band(
                ax[j], t, to_unit(lohi[0][:, j]), to_unit(lohi[1][:, j]), "C0",
                "95 % confidence band", unit,
            )
        ax[j].plot(t, to_unit(model[:, j]), "-", lw=1.3, color="C0", label="model (simulation)")
        _ylabel(ax[j], label, unit)
        ax[j].set_title(
            f"{e.name}: {label}, simulation fit {pct[min(j, pct.size - 1)]:.1f} %", fontsize=9
        )
        ax[j].legend(loc="best", fontsize=7)
        ax[j].grid(alpha=0.3)
    _draw_inputs(ax[n_y:], e.inputs, float(t.min()), float(t.max()), inputs)
    ax[-1].set_xlabel("time [s]")
    ax[-1].set_xlim(float(t.min()), float(t.max()))
    return fig


def plot_residual_tests(analysis, *, axes=None, outputs: Sequence = (), inputs: Sequence = ()):
    """The residual tests of a fit (`FitResult.residuals`): per output, the residuals'
    autocorrelation and their cross-correlation with each input, each with the 99 % band of
    white noise. `axes`: a (n_outputs, 1 + n_inputs) grid, or None."""
    from greybox._estimate.residuals import _seconds  # as the verdict's lags are shown

    a = analysis
    n_y, n_u = a.autocorrelation.shape[0], a.cross_correlation.shape[1]
    if axes is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(4.2 * (1 + n_u), 2.8 * n_y + 0.6), layout="constrained")
        grid = np.atleast_2d(fig.subplots(n_y, 1 + n_u, squeeze=False))
    else:
        grid = np.asarray(axes, dtype=object).reshape(n_y, 1 + n_u)
        fig = grid[0, 0].get_figure()
    out_names = [
        (o.name if hasattr(o, "name") else str(o)) for o in (outputs or a.output_names)
    ]
    in_names = [
        (c.name if hasattr(c, "name") else str(c)) for c in inputs
    ] or [f"input {k + 1}" for k in range(n_u)]
    band = a.band()
    with np.errstate(divide="ignore"):
        cband = 2.5758293035489004 / np.sqrt(a.cross_pairs)  # z(0.995)
    # a correlation per lag as one line collection (vlines), not a patch per lag (bar): the
    # figure draws the same, in half the time (TCLab two heaters: 0.8 -> 0.43 s)
    for j in range(n_y):
        ax = grid[j, 0]
        ax.vlines(a.lags[1:], 0.0, a.autocorrelation[j, 1:], lw=3, color="C0")
        ax.fill_between(a.lags[1:], -band[j, 1:], band[j, 1:], color="0.8", zorder=0)
        ax.set_title(
            f"{out_names[j]}: autocorrelation\n(Ljung-Box p = {a.p_value[j]:.2g})", fontsize=8
        )
        ax.set_xlabel("lag [frames]", fontsize=8)
        ax.set_ylabel("correlation (dimensionless)", fontsize=8)
        ax.grid(alpha=0.3)
        for k in range(n_u):
            ax = grid[j, 1 + k]
            ax.vlines(a.cross_lags, 0.0, a.cross_correlation[j, k], lw=3, color="C1")
            ax.fill_between(a.cross_lags, -cband[j], cband[j], color="0.8", zorder=0)
            ax.set_title(f"{out_names[j]}: cross-correlation\nwith {in_names[k]}", fontsize=8)
            ax.set_xlabel("lag [frames] (positive: the input leads)", fontsize=8)
            ax.grid(alpha=0.3)
    # the verdict can name many lags and outputs: wrapped to the figure's width (about 16
    # characters of 8-point text per inch), not cut off at its edges
    chars = max(40, int(16 * fig.get_figwidth()))
    fig.suptitle(
        textwrap.fill(f"Residuals: {a.verdict}", chars)
        + f"\n(grey: 99 % band of white noise; frames of {_seconds(a.frame_interval_s)})",
        fontsize=8,
    )
    return fig


def plot_compare(scores: Sequence, *, ax=None, criterion: str = "aic"):
    """Candidate structures (`greybox.compare` scores) by an information criterion, relative
    to the best (0 = preferred; > 10 is strong evidence against a candidate)."""
    if ax is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(6.0, 1.2 + 0.45 * len(scores)), layout="constrained")
        ax = fig.subplots()
    fig = ax.get_figure()
    values = np.array([float(getattr(s, criterion)) for s in scores])
    delta = values - np.nanmin(values)
    names = [s.name for s in scores]
    ax.barh(range(len(names)), delta, color=["C2" if d == 0 else "C0" for d in delta])
    ax.set_yticks(range(len(names)), names, fontsize=8)
    ax.invert_yaxis()
    ax.axvline(10.0, color="0.5", ls="--", lw=0.8)
    ax.set_xlabel(f"{criterion.upper()} - best {criterion.upper()} (dimensionless)")
    ax.set_title("Candidate structures (0: preferred; dashed: 10)", fontsize=9)
    ax.grid(alpha=0.3, axis="x")
    return fig


def plot_population(results, parameter: str, *, ax=None):
    """The estimates of one shared parameter across devices ({device: FitResult}) with their
    95 % intervals, in the parameter's unit."""
    from greybox.report._markdown import display_unit

    if ax is None:
        from matplotlib.figure import Figure

        fig = Figure(figsize=(6.0, 1.2 + 0.3 * len(results)), layout="constrained")
        ax = fig.subplots()
    fig = ax.get_figure()
    names = list(results)
    est = [results[n].estimate(parameter) for n in names]
    factor, unit = display_unit(est[0].unit, float(np.median([e.value for e in est])))
    v = np.array([e.value for e in est]) * factor
    se = np.array([e.se for e in est]) * factor
    ax.errorbar(v, range(len(names)), xerr=1.96 * se, fmt="o", ms=3, color="C0", capsize=2)
    ax.set_yticks(range(len(names)), names, fontsize=7)
    ax.invert_yaxis()
    ax.set_xlabel(f"{parameter} [{unit}] (95 % interval)")
    ax.set_title(f"{parameter} across {len(names)} devices", fontsize=9)
    ax.grid(alpha=0.3, axis="x")
    return fig
