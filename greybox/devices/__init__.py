"""Finding and adapting devices: the installed devices by name, each device's
module, its default simulation method, a device with its camera replaced, and common channels.

A public re-export of names that live in private modules; each is imported on first use.
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

# public name -> (module, attribute)
_NAMES = {
    "available_devices": ("greybox._registry", "available"),
    "get_device": ("greybox._registry", "get_device"),
    "device_module": ("greybox._registry", "device_module"),
    "default_method": ("greybox._model.device", "default_method"),
    "with_camera": ("greybox._model.device", "with_camera"),
    "DISPLACEMENT": ("greybox._model.channels", "DISPLACEMENT"),
    "LASER_POWER": ("greybox._model.channels", "LASER_POWER"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy_names(__name__, _NAMES)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._model.channels import DISPLACEMENT as DISPLACEMENT
    from greybox._model.channels import LASER_POWER as LASER_POWER
    from greybox._model.device import default_method as default_method
    from greybox._model.device import with_camera as with_camera
    from greybox._registry import available as available_devices  # noqa: F401 (re-exported)
    from greybox._registry import device_module as device_module
    from greybox._registry import get_device as get_device
