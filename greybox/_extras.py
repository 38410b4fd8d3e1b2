"""Optional extras (``pip install "greybox[video]"``, ``"greybox[distributed]"``): a command
that needs one that is missing says which, as bad input (exit 2), not as a traceback."""

from __future__ import annotations

import importlib

from greybox._model.errors import InputError

EXTRAS = {
    "video": ("imageio", "imageio_ffmpeg", "skimage"),
    "distributed": ("dask", "distributed"),
}


def require_extra(extra: str, field: str | None = None, what: str = "this command") -> None:
    """Import every module of `extra`; if one is missing raise an `InputError` naming the
    extra to install (a module that is present but broken is a real error and propagates)."""
    for module in EXTRAS[extra]:
        try:
            importlib.import_module(module)
        except ModuleNotFoundError as err:
            if err.name is None or err.name.split(".")[0] != module.split(".")[0]:
                raise
            raise InputError(
                f"{what} needs the optional extra {extra!r} ({module} is not installed); "
                f'install it with: pip install "greybox[{extra}]"',
                field=field,
            ) from None
