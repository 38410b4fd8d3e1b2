"""Property-based: every input to the loaders either loads or raises the located `InputError`.

Covers the experiment folder loader (TOML description + run CSV), the CSV reader alone, the
``--waveform`` parser and `load_params`. A bounded number of examples keeps the suite in the
default run (a few seconds); no example may take long, raise anything else, or echo more
than a short excerpt of what it read.
"""

import json
import os
import string

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from greybox._model.errors import InputError
from greybox._registry import resolve
from greybox.io._csv import read_csv
from greybox.io._experiment_set import candidate_names, load_experiment_set
from greybox.io._params_file import SCHEMA, load_params
from greybox.io._waveform_spec import parse_waveform_spec

# GREYBOX_FUZZ_EXAMPLES=2000 runs a longer, randomised search (the default run is fixed)
_N = int(os.environ.get("GREYBOX_FUZZ_EXAMPLES", "0"))
FUZZ = settings(
    max_examples=_N or 60,
    deadline=2000,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
    derandomize=not _N,
    database=None,
)
CHANNEL = resolve("chevron_laser").spec.inputs[0]
MARK = "ZZSECRETZZ" * 30  # if this long run of file content reached a message, it leaked


def _check(err: InputError) -> None:
    text = str(err)
    assert err.file is not None or err.field is not None, text
    assert len(text) < 1500, text[:300]
    assert MARK not in text


# ---- TOML: structured documents with hostile values -----------------------------------

scalars = st.one_of(
    st.integers(min_value=-(2**70), max_value=2**70),
    st.floats(allow_nan=True, allow_infinity=True),
    st.booleans(),
    st.text(max_size=20),
    st.just(MARK),
)
keys = st.sampled_from(
    [
        "type", "power_mW", "power_W", "period_ms", "duty", "n_pulses", "n", "delay_ms",
        "tail_ms", "times_s", "end_s", "absorptance", "thermal.tau_s", "camera.n_quadrature",
        "zz",
    ]
)  # fmt: skip
values = st.recursive(
    scalars,
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(keys, inner, max_size=3),
    max_leaves=8,
)


def _toml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if v != v else ("inf" if v == np.inf else "-inf" if v == -np.inf else repr(v))
    if isinstance(v, str):
        return json.dumps(v)
    if isinstance(v, list):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    return "{ " + ", ".join(f'"{k}" = {_toml_value(x)}' for k, x in v.items()) + " }"


@st.composite
def experiment_folders(draw):
    wave = draw(
        st.dictionaries(keys, values, max_size=6)
        | st.just({"type": "pulse_train", "power_mW": 20, "period_ms": 400, "n_pulses": 3})
    )
    settings_table = draw(st.dictionaries(keys, values, max_size=2))
    fit = draw(
        st.dictionaries(st.sampled_from(["n_starts", "max_steps", "loss"]), scalars, max_size=2)
    )
    run_extra = draw(
        st.dictionaries(st.sampled_from(["t_start_s", "y_column", "file"]), scalars, max_size=2)
    )
    lines = ["[experiment]", 'device = "chevron_laser"']
    if settings_table:
        lines.append(f"settings = {_toml_value(settings_table)}")
    lines += ["[camera]", f"fps = {_toml_value(draw(scalars | st.just(30)))}"]
    if fit:
        lines += ["[fit]"] + [f"{k} = {_toml_value(v)}" for k, v in fit.items()]
    run = {"name": "est", "file": "est.csv", "role": "estimation", **run_extra}
    lines += ["[[runs]]"] + [f"{k} = {_toml_value(v)}" for k, v in run.items()]
    lines.append(f"waveform = {_toml_value(wave)}")
    return "\n".join(lines) + "\n"


cells = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers().map(str),
    st.text(alphabet=string.printable, max_size=12),
    st.just(MARK),
    st.just(""),
)


@st.composite
def csv_texts(draw):
    header = draw(
        st.lists(
            st.sampled_from(["t_s", "y_um", "y_px", "laser_mW", "t_ms", "y", "q", '"']),
            min_size=0,
            max_size=4,
        )
        | st.just(["t_s", "y_um"])
    )
    n = draw(st.integers(0, 30))
    rows = [
        ",".join(draw(st.lists(cells, min_size=len(header), max_size=len(header) + 1)))
        for _ in range(n)
    ]
    if draw(st.booleans()):  # mostly-valid numbers: reach the deeper checks
        t = np.cumsum(draw(st.lists(st.floats(-0.01, 0.1), min_size=3, max_size=40)))
        y = draw(st.lists(st.floats(-1e3, 1e3), min_size=t.size, max_size=t.size))
        header, rows = ["t_s", "y_um"], [f"{a!r},{b!r}" for a, b in zip(t, y)]
    return ",".join(header) + "\n" + "\n".join(rows) + ("\n" if draw(st.booleans()) else "")


@FUZZ
@given(toml=experiment_folders() | st.text(max_size=200), csv_text=csv_texts())
def test_experiment_folder_loads_or_raises_input_error(tmp_path_factory, toml, csv_text):
    folder = tmp_path_factory.mktemp("exp")
    (folder / "experiment.toml").write_text(toml, encoding="utf-8", errors="surrogatepass")
    (folder / "est.csv").write_text(csv_text, encoding="utf-8", errors="surrogatepass")
    try:
        load_experiment_set(folder)
    except InputError as err:
        _check(err)


@FUZZ
@given(data=st.binary(max_size=400) | csv_texts().map(str.encode))
def test_csv_reader_loads_or_raises_input_error(tmp_path_factory, data):
    p = tmp_path_factory.mktemp("csv") / "r.csv"
    p.write_bytes(data)
    try:
        read_csv(p)
    except InputError as err:
        _check(err)


spec_values = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True).map(repr),
    st.integers(min_value=-(2**80), max_value=2**80).map(str),
    st.text(alphabet=string.printable, max_size=8),
)


@FUZZ
@given(
    items=st.lists(
        st.tuples(
            st.sampled_from(
                [
                    "power_mW",
                    "power_W",
                    "period_ms",
                    "period_s",
                    "duty",
                    "n",
                    "n_pulses",
                    "delay_ms",
                    "tail_s",
                    "zz",
                    "",
                ]
            ),
            spec_values,
        ),
        max_size=7,
    ),
    prefix=st.sampled_from(["pulse:", "pulse", "square:", ""]),
)
def test_waveform_option_parses_or_raises_input_error(items, prefix):
    spec = prefix + ",".join(f"{k}={v}" for k, v in items)
    try:
        wave, text = parse_waveform_spec(spec, CHANNEL)
    except InputError as err:
        assert err.field == "--waveform"
        _check(err)
    else:
        assert np.isfinite(wave.end_s) and np.all(np.isfinite(np.asarray(wave.values)))


json_values = st.recursive(
    st.none() | st.booleans() | st.floats() | st.integers() | st.text(max_size=10),
    lambda inner: (
        st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=8), inner, max_size=3)
    ),
    max_leaves=10,
)
GOOD = {
    "schema": SCHEMA,
    "device": {"name": "chevron_laser", "ref": "chevron_laser", "source": "builtin",
               "location": "chevron_laser", "options": {}},
    "model": {"camera": {"m_per_px": 6.45e-7, "exposure_s": 0.01}, "fixed": {},
              "fitted": {"absorptance": 0.55}, "method": "zoh",
              "solver": {"rtol": 1e-8, "atol": 1e-10, "max_steps": 16384}},
    "free": [{"path": "absorptance", "unit": "1", "lower": 0.4, "upper": 0.7}],
    "raw": [0.0],  # logit((0.55 - 0.4) / 0.3): the fitted value, raw
    "covariance_raw": [[0.01]],
    "sigma": {"value": [1e-7]},
    "noise_model": {"kind": "output error"},
}  # fmt: skip
# the same fit as a process-noise file (greybox.params/3): the noise section rebuilds it
GOOD_PROCESS = {
    **{k: v for k, v in GOOD.items() if k != "sigma"},
    "noise_model": {
        "kind": "process noise",
        "structure": {"process_groups": {"states": [0]}, "disturbances": [],
                      "walk_initial_sd": 0.0, "filter": "auto", "substeps": None},
        "values": {"process.states": 1e-12, "measurement.y": 1e-7},
    },
}  # fmt: skip


@FUZZ
@given(
    path=st.sampled_from(
        [("schema",), ("device", "name"), ("device", "options"), ("model", "camera"),
         ("model", "fitted"), ("model", "fixed"), ("model", "method"), ("model", "solver"),
         ("model", "solver", "max_steps"), ("model", "solver", "rtol"), ("free",), ("raw",),
         ("covariance_raw",), ("sigma", "value"), ("sigma",), ("null_directions_raw",),
         ("free", 0, "path"), ("free", 0, "lower"), ("covariance_raw", 0, 0), ("raw", 0),
         ("device", "ref"), ("device", "source"), ("device", "location"),
         ("model", "camera", "exposure_s"), ("model", "camera", "fps"),
         ("model", "fitted", "absorptance"), ("free", 0, "per_experiment"),
         ("noise_model",), ("noise_model", "kind"), ("noise_model", "structure"),
         ("noise_model", "values"), ("noise_model", "structure", "process_groups"),
         ("noise_model", "values", "measurement.y")]
    ),
    value=json_values,
    whole=st.booleans(),
    process=st.booleans(),
)  # fmt: skip
def test_params_json_loads_or_raises_input_error(tmp_path_factory, path, value, whole, process):
    """Any corruption of a least-squares or a process-noise params.json loads or raises a
    located InputError, never another exception."""
    good = GOOD_PROCESS if process else GOOD
    if path[0] == "sigma" and process or path[0] == "noise_model" and not process and len(path) > 2:
        path = ("raw", 0)  # not in this kind of file
    doc = json.loads(json.dumps(good))
    if whole:
        doc = value
    else:
        obj = doc
        for k in path[:-1]:
            obj = obj[k]
        obj[path[-1]] = value
    p = tmp_path_factory.mktemp("params") / "params.json"
    p.write_text(json.dumps(doc, allow_nan=True))
    try:
        fitted = load_params(p)
    except InputError as err:
        _check(err)
    else:
        assert np.all(np.isfinite(fitted.raw)) and np.all(np.isfinite(fitted.covariance_raw))
        assert np.linalg.eigvalsh(fitted.covariance_raw).min() >= -1e-8 * max(
            1.0, np.abs(fitted.covariance_raw).max()
        )


@pytest.mark.parametrize("good", [GOOD, GOOD_PROCESS], ids=["output error", "process noise"])
def test_the_uncorrupted_params_files_load(tmp_path, good):
    p = tmp_path / "params.json"
    p.write_text(json.dumps(good))
    fitted = load_params(p)
    assert fitted.noise_model == good["noise_model"]["kind"]


# ---- issue 27: [[candidates]], [columns], [noise], design constraints -------------------

FEW = settings(FUZZ, max_examples=_N or 25)
BASE = (
    '[experiment]\ndevice = "chevron_laser"\n[camera]\nfps = 30\nexposure_ms = 10\n'
    '[[runs]]\nname = "est"\nfile = "est.csv"\nrole = "estimation"\n'
    'waveform = { type = "pulse_train", power_mW = 20, period_ms = 400, n_pulses = 3, '
    "delay_ms = 200 }\n"
)
GOOD_CSV = "t_s,y_um\n" + "".join(
    f"{(k + 0.5) / 30:.6f},{200 + 1.5 * (np.sin(2 * np.pi * (k + 0.5) / 12) > 0):.4f}\n"
    for k in range(42)
)
option_values = st.one_of(
    scalars, st.sampled_from(["exact", "linear", 1, 2, 0, True, 3500.0, float("nan")])
)
option_names = st.sampled_from(
    ["kinematics", "thermal_nodes", "elongation_lag", "beam_length_um", "angle_deg", "zz"]
)


def _folder(tmp_path_factory, toml: str, csv_text: str = GOOD_CSV):
    folder = tmp_path_factory.mktemp("exp")
    (folder / "experiment.toml").write_text(toml, encoding="utf-8", errors="surrogatepass")
    (folder / "est.csv").write_text(csv_text)
    return folder


@FEW
@given(
    candidates=st.lists(
        st.fixed_dictionaries(
            {},
            optional={
                "name": st.text(max_size=12) | scalars,
                "model": st.dictionaries(option_names, option_values, max_size=3) | scalars,
                "free": st.lists(st.sampled_from(["absorptance", "thermal.tau_s", "zz", ""]),
                                 max_size=3) | scalars,
                "zz": scalars,
            },
        ),
        min_size=1,
        max_size=3,
    )
)  # fmt: skip
def test_candidates_load_or_raise_input_error(tmp_path_factory, candidates):
    toml = BASE + "".join(
        "[[candidates]]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in c.items())
        for c in candidates
    )
    folder = _folder(tmp_path_factory, toml)
    try:
        names = candidate_names(folder)
        for i in range(len(names)):
            fs = load_experiment_set(folder, candidate=i)
            assert all(v == v for v in fs.options.values())  # a NaN option never loads
    except InputError as err:
        _check(err)


units = st.sampled_from(["um", "px", "m", "mW", "W", "degC", "delta_degC", "year", "min", "s",
                         "ms", "zz", "", MARK])  # fmt: skip


@FEW
@given(
    columns=st.dictionaries(
        st.sampled_from(["time", "y", "laser", "zz"]),
        st.sampled_from(["t_s", "y_um", "laser_mW", "T", ""])
        | st.fixed_dictionaries({"column": st.sampled_from(["t_s", "y_um", "zz"])},
                                optional={"unit": units})
        | scalars,
        max_size=3,
    ),
    data=st.dictionaries(
        st.sampled_from(["input_delay_s", "header", "time_origin", "zz"]), scalars, max_size=2
    ),
)  # fmt: skip
def test_columns_and_data_rules_load_or_raise_input_error(tmp_path_factory, columns, data):
    head = "[data]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in data.items())
    head += "[columns]\n" + "".join(f"{k} = {_toml_value(v)}\n" for k, v in columns.items())
    folder = _folder(tmp_path_factory, head + BASE)
    try:
        fs = load_experiment_set(folder)
    except InputError as err:
        _check(err)
    else:
        assert all(np.isfinite(e.t_s).all() for e in fs.estimation)


@FEW
@given(
    noise=st.dictionaries(
        st.sampled_from(["process", "disturbances", "walk_initial_sd", "filter", "k_step",
                         "priors", "zz"]),
        values | st.sampled_from(["all", "ekf", "ukf", 10, 1e10]),
        max_size=3,
    )
)  # fmt: skip
def test_noise_tables_parse_or_raise_input_error(tmp_path_factory, noise):
    from greybox.io._noise_table import parse_noise
    from greybox.io._toml import TomlDocument

    toml = '[fit]\nnoise_model = "process"\n[noise]\n' + "".join(
        f"{k} = {_toml_value(v)}\n" for k, v in noise.items()
    )
    path = tmp_path_factory.mktemp("noise") / "experiment.toml"
    path.write_text(toml)
    spec = resolve("chevron_laser").spec
    try:
        doc = TomlDocument(path)
        parse_noise(doc, doc.data.get("noise"), spec.model(), spec)
    except InputError as err:
        _check(err)


@FEW
@given(
    c=st.fixed_dictionaries(
        {"power_max_W": st.floats() | st.just(0.03), "run_duration_s": st.floats() | st.just(5.0),
         "n_runs": st.integers(-3, 10**6), "fps": st.floats() | st.just(30.0),
         "min_pulse_s": st.floats() | st.just(0.02), "exposure_s": st.floats() | st.just(0.01),
         "lead_s": st.floats() | st.just(0.3), "power_min_W": st.floats() | st.just(0.0)}
    )
)  # fmt: skip
def test_design_constraints_check_or_raise_a_named_value_error(c):
    from greybox.design._design import MAX_DESIGN_FRAMES, LabConstraints

    try:
        LabConstraints(**c).check()
    except ValueError as err:
        assert str(err).split(":")[0] in c or str(err).startswith("average_power"), str(err)
    else:  # accepted constraints are finite and bounded work
        assert all(np.isfinite(v) for k, v in c.items() if k != "n_runs")
        assert c["n_runs"] * c["run_duration_s"] * c["fps"] <= MAX_DESIGN_FRAMES
