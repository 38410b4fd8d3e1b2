"""pandas DataFrames in and out of `Experiment`, with the rules of a run CSV.

A DataFrame is read exactly as a run file is (greybox/io/_csv.py): time from a ``t_<unit>``
column, a mapped column or the index (a named numeric index such as ``t_s``, a
`TimedeltaIndex`, or a `DatetimeIndex` counted from its first row); each output from a
``<name>_<unit>`` column (or a mapping, as experiment.toml's [columns]) converted to SI with
pint; the inputs from ``<input>_<unit>`` columns (each level held until the next row) unless a
waveform is given. Errors name the DataFrame row and column. pandas is never imported here:
any object with ``columns``, ``index`` and ``to_numpy`` works.
"""

from __future__ import annotations

import numpy as np

from greybox._model.errors import InputError

WHERE = "<DataFrame>"


def _spec(device):
    if hasattr(device, "outputs") and hasattr(device, "inputs"):
        return device
    from greybox._registry import get_device

    return get_device(str(device))


def _time_index(df):
    """(DataFrame with the index as a column when it is the time, its column name or None)."""
    index = df.index
    kind = type(index).__name__
    if kind in ("DatetimeIndex", "TimedeltaIndex"):
        origin = index - index[0] if kind == "DatetimeIndex" else index
        seconds = np.asarray(origin.total_seconds(), dtype=float)
        name = "t_s" if index.name is None else f"{index.name} [s]"
        out = df.reset_index(drop=True)
        out.insert(0, name, seconds)
        return out, name
    if kind == "RangeIndex" and index.name is None:
        return df, None  # the default index: the time must be a column
    if index.name is None:
        raise InputError(
            "the index is not named, so its unit is unknown; name it after the time and its "
            "unit (df.index.name = 't_s'), or give time = ... in `columns`",
            file=WHERE,
            field="index",
        )
    return df.reset_index(), str(index.name)


def _table(df):
    from greybox.io._csv import CsvTable

    header = tuple(str(c) for c in df.columns)
    n = len(df)
    values = np.full((n, len(header)), np.nan)
    text = {}
    for j, col in enumerate(df.columns):
        column = df[col].to_numpy()
        try:
            values[:, j] = np.asarray(column, dtype=float)
        except (TypeError, ValueError):
            text[header[j]] = tuple("" if v is None else str(v) for v in column)
    # a DataFrame's "line" is its row position (0-based, as df.iloc counts)
    return CsvTable(WHERE, header, values, np.arange(n), header_line=0, text_columns=text)


def _mapping(columns) -> dict:
    out = {}
    for key, value in (columns or {}).items():
        col, unit = (value, None) if isinstance(value, str) else tuple(value)
        out[key] = (str(col), unit, "the columns argument")
    return out


def experiment_from_dataframe(
    df,
    device,
    *,
    inputs=None,
    name: str = "run",
    columns: dict | None = None,
    role: str = "estimation",
    t_start_s: float = 0.0,
    settings: dict | None = None,
):
    """An `Experiment` from a DataFrame (see the module docstring); `device`: a `DeviceSpec`
    or a device name; `columns`: {signal or "time": column or (column, unit)}; `inputs`: a
    waveform in SI instead of input columns.

    (A function of `greybox.io`, not a method of `Experiment`: the core never reads files
    or tables; this is the same reader as a run CSV's.)"""
    from greybox._model.data import Experiment
    from greybox._model.waveforms import from_samples, stack_channels
    from greybox.io._csv import channel_numbers, check_increasing, find_column, time_column

    spec = _spec(device)
    mapping = _mapping(columns)
    frame, index_time = _time_index(df)
    table = _table(frame)
    if "time" not in mapping and index_time is not None:
        named = any(
            c in ("t", "time") or c.startswith(("t_", "time_")) for c in table.header[1:]
        )
        if not named:
            mapping["time"] = (index_time, None, "the DataFrame index")
    t, tref = time_column(table, mapping.get("time"))
    check_increasing(table, t, tref.column)
    ys = []
    for ch in spec.outputs:
        ref = find_column(table, ch, required=len(spec.outputs) == 1, mapped=mapping.get(ch.name))
        if ref is None:
            ys.append(np.full(t.size, np.nan))
            continue
        ys.append(
            channel_numbers(table, ch, ref, what=f"{ch.name} reading", allow_missing=True)
        )
    if inputs is None:
        end = t[-1] + (float(np.median(np.diff(t))) if t.size > 1 else 0.0)
        waves = []
        for ch in spec.inputs:
            ref = find_column(table, ch, required=True, mapped=mapping.get(ch.name))
            v = channel_numbers(table, ch, ref, what=f"{ch.name} level")
            waves.append(from_samples(t, v, end_s=end, name=ref.column))
        inputs = waves[0] if len(waves) == 1 else stack_channels(waves)
    y = np.column_stack(ys)
    return Experiment(
        name,
        t,
        y if y.shape[1] > 1 else y[:, 0],
        inputs,
        t_start_s=t_start_s,
        role=role,
        settings=dict(settings or {}),
    )


def _columns(arr, channels, stem) -> dict:
    """{``<name>_<unit>``: values in that unit} per column of `arr` (SI): the channel's
    readable unit where `channels` names it, else ``<stem><j>_SI``."""
    from greybox.report._markdown import channel_unit

    out = {}
    for j in range(arr.shape[1]):
        if j < len(channels):
            factor, unit = channel_unit(channels[j])
            col = f"{channels[j].name}_{'pct' if unit == '%' else unit}"
        else:
            factor, col = 1.0, f"{stem}{j + 1}_SI"
        out[col] = arr[:, j] * factor
    return out


def _pandas(what: str):
    from greybox._extras import import_extra

    return import_extra("pandas", "dataframe", what)


def experiment_to_dataframe(experiment, device=None):
    """A DataFrame of `experiment`: the index ``t_s``, one column per output and per input
    named ``<name>_<unit>`` in the channel's readable unit (``y_um``, ``T1_K``, ``laser_mW``)
    with `device`, else in SI (``y1_SI``, ``u1_SI``); the inputs as held at each frame."""
    pd = _pandas("experiment_to_dataframe")
    e = experiment
    t = np.asarray(e.t_s, dtype=float)
    levels = np.asarray(e.inputs(t), dtype=float).reshape(t.size, -1)
    spec = _spec(device) if device is not None else None
    data = _columns(np.asarray(e.y), spec.outputs if spec else (), "y")
    data.update(_columns(levels, spec.inputs if spec else (), "u"))
    return pd.DataFrame(data, index=pd.Index(t, name="t_s"))


def predictions_to_dataframe(result, run: str, device=None):
    """A DataFrame of a fit's run `run`: the index ``t_s``, the measured outputs as in
    `experiment_to_dataframe` (``y_um``), then per prediction horizon of the fit
    (``FitResult.predictions``: "simulation", with process noise also "one-step" and
    "k-step") a column ``<output> <horizon>`` and, where the fit has it, ``<output> <horizon>
    sd``, all in the output's unit."""
    pd = _pandas("predictions_to_dataframe")
    names = [e.name for e in result.experiments]
    if run not in names or run not in result.predictions:
        raise KeyError(f"{run}: not a run of this fit; have {names}")
    e = result.experiments[names.index(run)]
    outputs = _spec(device).outputs if device is not None else ()
    data = _columns(np.asarray(e.y), outputs, "y")
    measured = list(data)
    sds = result.prediction_sd.get(run, {})
    for horizon, z in result.predictions[run].items():
        for kind, arr in ((horizon, z), (f"{horizon} sd", sds.get(horizon))):
            if arr is None:
                continue
            arr = np.asarray(arr, dtype=float).reshape(e.n_frames, -1)
            for col, v in zip(measured, _columns(arr, outputs, "y").values()):
                data[f"{col} {kind}"] = v
    return pd.DataFrame(data, index=pd.Index(np.asarray(e.t_s, dtype=float), name="t_s"))
