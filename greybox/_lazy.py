"""Names of a package imported on first use (PEP 562), so that importing greybox, or asking
its command line for --help, does not pay for JAX and matplotlib."""

import importlib
import warnings


def lazy_names(package: str, names: dict, subpackages=(), moved=None):
    """(`__getattr__`, `__dir__`) for `package`: `names` maps a public name to (module,
    attribute); `subpackages` are imported as `package.<name>` on first use; `moved` maps a
    name that left `package` to the subpackage it now lives in: it still resolves, with a
    DeprecationWarning, and is left out of `dir()`."""
    namespace = importlib.import_module(package).__dict__
    moved = moved or {}

    def __getattr__(name: str):
        if name in names:
            module, attribute = names[name]
            value = getattr(importlib.import_module(module), attribute)
        elif name in subpackages:
            value = importlib.import_module(f"{package}.{name}")
        elif name in moved:
            home = f"{package}.{moved[name]}"
            warnings.warn(
                f"{package}.{name} moved to {home}.{name}", DeprecationWarning, stacklevel=2
            )
            return getattr(importlib.import_module(home), name)  # not cached: warns each time
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        namespace[name] = value  # looked up once
        return value

    def __dir__():
        # the public names and the module's dunders; not its helpers or imported submodules
        dunders = {n for n in namespace if n.startswith("__")}
        return sorted(dunders | set(names) | set(subpackages))

    return __getattr__, __dir__
