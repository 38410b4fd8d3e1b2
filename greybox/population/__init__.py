"""Many devices at once: batches of independent fits (one per device), fits
spread over a Dask cluster, and population (hierarchical) models of the parameters across devices.

A public re-export of names that live in private modules; each is imported on first use.
"""

from typing import TYPE_CHECKING as _TYPE_CHECKING

from greybox._lazy import lazy_names as _lazy_names

# public name -> (module, attribute)
_NAMES = {
    "fit_batch": ("greybox._estimate.batch", "fit_batch"),
    "BatchResult": ("greybox._estimate.batch", "BatchResult"),
    "batch_table": ("greybox._estimate.batch", "batch_table"),
    "Device": ("greybox._estimate.batch", "Device"),
    "device_from_spec": ("greybox._estimate.batch", "device_from_spec"),
    "fit_distributed": ("greybox._estimate.distributed", "fit_distributed"),
    "population_fit": ("greybox._estimate.population", "population_fit"),
    "population_from_batch": ("greybox._estimate.population", "population_from_batch"),
    "PopulationFit": ("greybox._estimate.population", "PopulationFit"),
    "PopulationParameter": ("greybox._estimate.population", "PopulationParameter"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = _lazy_names(__name__, _NAMES)

if _TYPE_CHECKING:  # static analysers and IDEs see the eager imports
    from greybox._estimate.batch import BatchResult as BatchResult
    from greybox._estimate.batch import Device as Device
    from greybox._estimate.batch import batch_table as batch_table
    from greybox._estimate.batch import device_from_spec as device_from_spec
    from greybox._estimate.batch import fit_batch as fit_batch
    from greybox._estimate.distributed import fit_distributed as fit_distributed
    from greybox._estimate.population import PopulationFit as PopulationFit
    from greybox._estimate.population import PopulationParameter as PopulationParameter
    from greybox._estimate.population import population_fit as population_fit
    from greybox._estimate.population import population_from_batch as population_from_batch
