"""The Python API from the inputs users have: numpy arrays in SI, a pandas DataFrame as a
logger writes it (time index, unit-suffixed columns), and pint quantities in um and ms.

The demo's estimation runs (experiments/chevron_laser, loaded as `greybox fit` loads them,
start-value hook included) are fitted three times with `greybox.fit`; the estimates must
agree to 1e-8 (relative) with the fit from the SI arrays, which is the command line's own
call (`fit(fs.model, fs.estimation, fs.free, **fs.fit_options)`)."""

from pathlib import Path

import numpy as np
import pytest

import greybox
from greybox import Experiment
from greybox.io import experiment_from_dataframe, experiment_to_dataframe, load_experiment_set

ROOT = Path(__file__).resolve().parents[1]
pd = pytest.importorskip("pandas")
pint = pytest.importorskip("pint")
UREG = pint.UnitRegistry()


@pytest.fixture(scope="module")
def demo():
    import jax

    jax.config.update("jax_enable_x64", True)
    fs = load_experiment_set(ROOT / "experiments" / "chevron_laser")
    runs = fs.estimation[:2]
    options = {**fs.fit_options, "n_starts": 1}
    reference = greybox.fit(fs.model, runs, fs.free, **options)
    return fs, runs, options, reference


def _values(result):
    return np.array([p.value for p in result.parameters])


def _same(result, reference):
    np.testing.assert_allclose(_values(result), _values(reference), rtol=1e-8, atol=0)


def test_dataframe_runs_give_the_same_fit(demo):
    fs, runs, options, reference = demo
    frames = [
        pd.DataFrame({"y_um": e.y[:, 0] * 1e6}, index=pd.Index(e.t_s, name="t_s")) for e in runs
    ]
    exps = [
        experiment_from_dataframe(df, fs.spec, inputs=e.inputs, name=e.name)
        for df, e in zip(frames, runs)
    ]
    np.testing.assert_allclose(exps[0].y, runs[0].y, rtol=1e-14)
    _same(greybox.fit(fs.model, exps, fs.free, **options), reference)


def test_pint_quantities_in_um_and_ms_give_the_same_fit(demo):
    fs, runs, options, reference = demo
    exps = [
        Experiment(
            e.name,
            UREG.Quantity(e.t_s * 1e3, "ms"),
            UREG.Quantity(e.y * 1e6, "um"),
            e.inputs,
        )
        for e in runs
    ]
    assert exps[0].y[5, 0] == pytest.approx(runs[0].y[5, 0], rel=1e-14)  # um -> m, not 1e6x
    _same(greybox.fit(fs.model, exps, fs.free, **options), reference)


def test_dataframe_round_trip_and_refusals(demo):
    fs, runs, _, _ = demo
    e = runs[0]
    df = experiment_to_dataframe(e, fs.spec)
    assert df.index.name == "t_s" and list(df.columns) == ["y_um", "laser_mW"]
    np.testing.assert_allclose(df["y_um"].to_numpy(), e.y[:, 0] * 1e6)
    back = experiment_from_dataframe(df, fs.spec, name=e.name)
    np.testing.assert_allclose(back.y, e.y, rtol=1e-14)
    np.testing.assert_allclose(back.inputs(e.t_s), e.inputs(e.t_s), rtol=1e-14)
    # a whole DataFrame with a Timedelta index works too
    td = df.copy()
    td.index = pd.to_timedelta(e.t_s, unit="s")
    np.testing.assert_allclose(experiment_from_dataframe(td, fs.spec).t_s, e.t_s)  # elapsed
    with pytest.raises(ValueError, match="not a time"):
        Experiment(e.name, UREG.Quantity(e.t_s, "um"), e.y, e.inputs)
    with pytest.raises(ValueError, match="dimensionless"):
        Experiment(e.name, e.t_s, UREG.Quantity(e.y[:, 0], "percent"), e.inputs)
