"""Names of a package imported on first use (PEP 562), so that importing greybox, or asking
its command line for --help, does not pay for JAX and matplotlib."""

import importlib


def lazy_names(package: str, names: dict, subpackages=()):
    """(`__getattr__`, `__dir__`) for `package`: `names` maps a public name to (module,
    attribute); `subpackages` are imported as `package.<name>` on first use."""
    namespace = importlib.import_module(package).__dict__

    def __getattr__(name: str):
        if name in names:
            module, attribute = names[name]
            value = getattr(importlib.import_module(module), attribute)
        elif name in subpackages:
            value = importlib.import_module(f"{package}.{name}")
        else:
            raise AttributeError(f"module {package!r} has no attribute {name!r}")
        namespace[name] = value  # looked up once
        return value

    def __dir__():
        return sorted(set(namespace) | set(names) | set(subpackages))

    return __getattr__, __dir__
