"""The public surface: a short top level, the rest in subpackages by job, and every name that
left the top level still resolving (with a DeprecationWarning naming its new home)."""

import importlib
import warnings

import pytest

import greybox

MOVED = sorted(greybox._MOVED.items())


def test_top_level_is_the_core_and_hides_its_helpers():
    assert len(greybox.__all__) <= 50
    shown = set(dir(greybox))
    assert not shown & {"importlib", "TYPE_CHECKING", "lazy_names", "warnings"}
    assert set(greybox.__all__) <= shown
    assert not shown & set(greybox._MOVED)
    assert not set(greybox.__all__) & set(greybox._MOVED)
    for name in greybox.__all__:  # every core name resolves without a warning
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            getattr(greybox, name)


@pytest.mark.parametrize("name,home", MOVED, ids=[n for n, _ in MOVED])
def test_moved_name_warns_and_is_its_new_home(name, home):
    new = getattr(importlib.import_module(f"greybox.{home}"), name)
    message = rf"greybox\.{name} moved to greybox\.{home}\.{name}"
    with pytest.warns(DeprecationWarning, match=message):
        old = getattr(greybox, name)
    assert old is new and name in importlib.import_module(f"greybox.{home}").__all__
    with pytest.warns(DeprecationWarning):  # every use warns, not only the first
        getattr(greybox, name)


# where the objects are defined (the private modules the old top level re-exported)
DEFINED = {
    "rmse": "greybox._estimate.metrics",
    "ljung_box": "greybox._estimate.stochastic_fit",
    "set_values": "greybox._model.parameters",
    "as_arrays": "greybox._simulate.simulate",
    "record": "greybox._simulate.synthetic",
    "steady_state": "greybox._simulate.periodic",
    "prediction_band": "greybox._estimate.prediction",
    "population_fit": "greybox._estimate.population",
    "with_camera": "greybox._model.device",
}


@pytest.mark.parametrize("name", sorted(DEFINED))
def test_old_and_new_names_are_the_defined_object(name):
    defined = getattr(importlib.import_module(DEFINED[name]), name)
    with pytest.warns(DeprecationWarning):
        assert getattr(greybox, name) is defined
    assert getattr(importlib.import_module(f"greybox.{greybox._MOVED[name]}"), name) is defined


SUBPACKAGES = ["metrics", "waveforms", "parameters", "uncertainty", "population", "devices"]


@pytest.mark.parametrize("sub", SUBPACKAGES)
def test_subpackages_resolve_every_name_and_say_what_they_are_for(sub):
    module = importlib.import_module(f"greybox.{sub}")
    assert module.__doc__ and len(module.__doc__.split()) > 10
    dunders = {n for n in vars(module) if n.startswith("__")}
    assert sorted(dir(module)) == sorted(set(module.__all__) | dunders)
    for name in module.__all__:
        assert getattr(module, name) is not None


def test_unknown_names_still_raise():
    with pytest.raises(AttributeError, match="no attribute 'nonexistent'"):
        greybox.nonexistent  # noqa: B018
