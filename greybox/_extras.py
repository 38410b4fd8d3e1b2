"""Optional extras (``pip install "greybox[video]"``, ``"greybox[distributed]"``): a command
that needs one that is missing says which, as bad input (exit 2), not as a traceback."""

from __future__ import annotations

import importlib

from greybox._model.errors import InputError

EXTRAS = {
    "video": ("imageio", "imageio_ffmpeg", "skimage"),
    "distributed": ("dask", "distributed"),
    "dataframe": ("pandas",),
}


def _missing(err: ModuleNotFoundError, module: str) -> bool:
    """True when `module` itself is absent (not a module it imports that is broken)."""
    return err.name is not None and err.name.split(".")[0] == module.split(".")[0]


def _message(extra: str, module: str, what: str) -> str:
    return (
        f"{what} needs the optional extra {extra!r} ({module} is not installed); "
        f'install it with: pip install "greybox[{extra}]"'
    )


def import_extra(module: str, extra: str, what: str):
    """`module`, imported; a `ModuleNotFoundError` naming the extra when it is missing (for
    the Python API, where an ImportError is what a user expects)."""
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if not _missing(err, module):
            raise
        raise ModuleNotFoundError(_message(extra, module, what), name=module) from None


def require_extra(extra: str, field: str | None = None, what: str = "this command") -> None:
    """Import every module of `extra`; if one is missing raise an `InputError` naming the
    extra to install (a module that is present but broken is a real error and propagates)."""
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as err:
            if not _missing(err, module):
                raise
            raise InputError(_message(extra, module, what), field=field) from None
