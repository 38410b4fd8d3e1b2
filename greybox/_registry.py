"""Where device specs come from: built-in devices, installed packages, a user's own file.

This module sits at the library's edge (it imports code from files); the core never uses it.
A device reference is one of

- a name: a built-in device (a module of the project's ``models/`` folder defining ``SPEC``)
  or one published by an installed package under the entry-point group ``greybox.devices``;
- ``path/to/file.py:SPEC`` (``:SPEC`` may be left out): a Python file, relative to `base_dir`
  (the experiment folder) unless absolute; its folder is imported as a package, so the file
  may import its neighbours with relative imports (``from ._common import ...``);
- ``package.module:SPEC``: an importable module.

Every spec is checked once (`DeviceSpec.check`) when it is first loaded. Importing and
checking a user's code is bounded in time, its failures are reported at the user's own file
and line, and while a params.json is loaded only trusted code is imported (`greybox._usercode`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import importlib
import importlib.metadata
import importlib.util
import sys
import types
from pathlib import Path

from greybox import _usercode
from greybox._model.spec import DeviceSpec, DeviceSpecError

ENTRY_POINT_GROUP = "greybox.devices"
_BUILTIN_PACKAGE = "greybox_builtin_devices"
_USER_PACKAGE = "greybox_user_devices"


@dataclasses.dataclass(frozen=True)
class ResolvedDevice:
    """A loaded spec and where it came from.

    - `ref`: the reference as given; `source`: "builtin", "entry point", "file" or "module";
    - `location`: the absolute file path for a file device, the module name otherwise;
    - `module`: the Python module defining the spec (device-specific helpers live there).
    """

    spec: DeviceSpec
    ref: str
    source: str
    location: str
    module: types.ModuleType | None


class DeviceNotFound(LookupError):
    """No device behind a reference (the message says where greybox looked)."""


def _builtin_dir() -> Path:
    here = Path(__file__).resolve().parent
    packed = here / "_builtin_models"  # where the wheel puts the project's models/ folder
    return packed if packed.is_dir() else here.parent / "models"


def _folder_package(folder: Path, name: str) -> str:
    """Register `folder` as a namespace package called `name` (no __init__ is executed)."""
    if name not in sys.modules:
        pkg = types.ModuleType(name)
        pkg.__path__ = [str(folder)]
        pkg.__package__ = name
        sys.modules[name] = pkg
    return name


def _spec_of(module, attr: str, ref: str) -> DeviceSpec:
    spec = getattr(module, attr, None)
    if spec is None:
        raise DeviceSpecError(
            f"device {ref!r}: {module.__name__} defines no {attr}; define "
            f"{attr} = greybox.DeviceSpec(...) in it (see DEVELOPING.md, Adding a device)"
        )
    if not isinstance(spec, DeviceSpec):
        raise DeviceSpecError(
            f"device {ref!r}: {attr} is a {type(spec).__name__}, not a DeviceSpec"
        )
    return spec


def _register_module(module) -> None:
    """A device module of another package is its author's code (not greybox's)."""
    file = getattr(module, "__file__", None)
    if file and Path(__file__).resolve().parent not in Path(file).resolve().parents:
        _usercode.register_user_code(Path(file).parent)


@contextlib.contextmanager
def _users_code(what: str, path: Path | None):
    """Run a user's import/check bounded in time; their failure becomes a `UserCodeError`
    at their line (a spec mistake stays a `DeviceSpecError`)."""
    try:
        with _usercode.time_limit(what, None if path is None else str(path)):
            yield
    except (KeyboardInterrupt, _usercode.UserCodeError):
        raise
    except DeviceSpecError as err:
        blamed = _usercode.blame_user(err.__cause__, what) if err.__cause__ else None
        if blamed is None:
            raise
        raise blamed from None
    except BaseException as err:
        stop = _usercode.stop_behind(err)  # the CLI's SIGTERM or a Ctrl-C: not the user's
        if stop is err:
            raise
        if stop is not None:  # ... also where it landed while the user's class was created
            raise stop from None
        blamed = _usercode.blame_user(err, what)
        if blamed is None:
            raise
        raise blamed from None


def builtin_names() -> list[str]:
    folder = _builtin_dir()
    return sorted(p.stem for p in folder.glob("*.py") if not p.stem.startswith("_") and p.is_file())


def _entry_points() -> dict:
    return {ep.name: ep for ep in importlib.metadata.entry_points(group=ENTRY_POINT_GROUP)}


def available() -> list[str]:
    """Names of the built-in devices and of those installed packages publish."""
    return sorted(set(builtin_names()) | set(_entry_points()))


_CACHE: dict = {}


def resolve(ref: str, base_dir: str | Path | None = None) -> ResolvedDevice:
    """The device behind `ref` (see the module docstring), loaded and checked once."""
    if not isinstance(ref, str) or not ref.strip():
        raise DeviceNotFound("device: give a device name or a file.py:SPEC reference")
    ref = ref.strip()
    path_part, _, attr = ref.partition(":")
    attr = attr or "SPEC"
    is_file = path_part.endswith(".py") or "/" in path_part or "\\" in path_part
    if is_file:
        path = Path(path_part)
        if not path.is_absolute():
            path = Path(base_dir or ".") / path
        path = path.resolve()
        _usercode.check_device_file(path)
        key = ("file", str(path), attr, path.stat().st_mtime_ns if path.is_file() else None)
    else:
        key = ("name", path_part, attr)
        if path_part not in builtin_names() and path_part not in _entry_points():
            if "." in path_part:
                _usercode.check_device_module(path_part)
    if key not in _CACHE:
        _CACHE[key] = _load(ref, path_part, attr, path if is_file else None)
    return _CACHE[key]


def _load(ref: str, name: str, attr: str, path: Path | None) -> ResolvedDevice:
    if path is not None:
        if not path.is_file():
            raise DeviceNotFound(
                f"device file {path} does not exist; give the path of the .py file that "
                "defines the device spec, relative to the experiment folder"
            )
        digest = hashlib.sha1(str(path.parent).encode()).hexdigest()[:12]
        pkg = _folder_package(path.parent, f"{_USER_PACKAGE}_{digest}")
        modname = f"{pkg}.{path.stem}"
        sys.modules.pop(modname, None)  # a changed file is re-read
        _usercode.register_user_code(path.parent)  # its neighbours are the user's code too
        with _users_code(f"importing device file {path.name}", path):
            module = importlib.import_module(modname)
            spec = _spec_of(module, attr, ref).check()
        return ResolvedDevice(spec, ref, "file", str(path), module)
    if name in builtin_names():
        pkg = _folder_package(_builtin_dir(), _BUILTIN_PACKAGE)
        module = importlib.import_module(f"{pkg}.{name}")
        return ResolvedDevice(_spec_of(module, attr, ref).check(), ref, "builtin", name, module)
    eps = _entry_points()
    if name in eps:
        with _users_code(f"loading device {name!r}", None):
            spec = eps[name].load()
        if not isinstance(spec, DeviceSpec):
            raise DeviceSpecError(f"device {name!r}: entry point gives {type(spec).__name__}")
        module = sys.modules.get(eps[name].module)
        _register_module(module)
        with _users_code(f"checking device {name!r}", None):
            spec = spec.check()
        return ResolvedDevice(spec, ref, "entry point", eps[name].value, module)
    if "." in name:
        try:
            with _users_code(f"importing device module {name!r}", None):
                module = importlib.import_module(name)
        except ModuleNotFoundError as err:
            raise DeviceNotFound(
                f"device module {name!r} cannot be imported ({err}); install it or give a "
                "file path (my_devices/device.py:SPEC)"
            ) from None
        _register_module(module)
        with _users_code(f"checking device module {name!r}", None):
            spec = _spec_of(module, attr, ref).check()
        return ResolvedDevice(spec, ref, "module", name, module)
    raise DeviceNotFound(
        f"unknown device {name!r}; built-in and installed: {', '.join(available())}; or "
        'name your own file as device = "my_device.py:SPEC" (relative to the experiment '
        'folder) or an importable module as "package.module:SPEC"'
    )


def get_device(ref: str, base_dir: str | Path | None = None) -> DeviceSpec:
    """The `DeviceSpec` behind `ref`: a built-in name (``"chevron_laser"``), a file
    (``"my_devices/chevron2.py:SPEC"``, relative to `base_dir`) or a module
    (``"mylab.devices:SPEC"``)."""
    return resolve(ref, base_dir).spec


def device_module(ref: str, base_dir: str | Path | None = None) -> types.ModuleType:
    """The module that defines device `ref` (device-specific analyses live there)."""
    return resolve(ref, base_dir).module
