"""File formats at the library's edge: experiment folders, params.json, result folders, video.

`load_experiment_set` reads an experiment folder (``experiment.toml`` + run CSVs, format in
``experiments/README.md``); `params_document`/`write_params`/`load_params` write and read
``params.json``; `experiment_writer` helpers write the inverse of the loader;
`configure_jax` sets JAX up as the `greybox` commands do (float64, compiled programs kept on
disk). Video I/O
(`probe`, `iter_frames`, `write_video`) needs the ``video`` extra.

Names are imported on first use.
"""

from typing import TYPE_CHECKING

from greybox._lazy import lazy_names

_NAMES = {
    "atomic_output_dir": ("greybox.io._atomic", "atomic_output_dir"),
    "atomic_output_file": ("greybox.io._atomic", "atomic_output_file"),
    "CsvTable": ("greybox.io._csv", "CsvTable"),
    "read_csv": ("greybox.io._csv", "read_csv"),
    "experiment_from_dataframe": ("greybox.io._dataframe", "experiment_from_dataframe"),
    "experiment_to_dataframe": ("greybox.io._dataframe", "experiment_to_dataframe"),
    "predictions_to_dataframe": ("greybox.io._dataframe", "predictions_to_dataframe"),
    "experiment_toml": ("greybox.io._design_file", "experiment_toml"),
    "ExperimentSet": ("greybox.io._experiment_set", "ExperimentSet"),
    "InputErrors": ("greybox.io._experiment_set", "InputErrors"),
    "RunInfo": ("greybox.io._experiment_set", "RunInfo"),
    "candidate_names": ("greybox.io._experiment_set", "candidate_names"),
    "configure_model": ("greybox.io._experiment_set", "configure_model"),
    "fit_memory_estimate": ("greybox.io._experiment_set", "fit_memory_estimate"),
    "configure_jax": ("greybox.io._jax_setup", "configure"),
    "load_experiment_set": ("greybox.io._experiment_set", "load_experiment_set"),
    "format_number": ("greybox.io._experiment_writer", "format_number"),
    "inline_table": ("greybox.io._experiment_writer", "inline_table"),
    "pulse_train_description": ("greybox.io._experiment_writer", "pulse_train_description"),
    "run_csv": ("greybox.io._experiment_writer", "run_csv"),
    "run_table": ("greybox.io._experiment_writer", "run_table"),
    "StateSpaceExport": ("greybox.io._export", "StateSpaceExport"),
    "to_state_space": ("greybox.io._export", "to_state_space"),
    "FittedModel": ("greybox.io._params_file", "FittedModel"),
    "load_params": ("greybox.io._params_file", "load_params"),
    "params_document": ("greybox.io._params_file", "params_document"),
    "write_params": ("greybox.io._params_file", "write_params"),
    "parse_waveform_spec": ("greybox.io._waveform_spec", "parse_waveform_spec"),
    "waveform_from_csv": ("greybox.io._waveform_spec", "waveform_from_csv"),
    "waveform_from_description": ("greybox.io._waveform_spec", "waveform_from_description"),
}
__all__ = sorted(_NAMES)
__getattr__, __dir__ = lazy_names(__name__, _NAMES)

if TYPE_CHECKING:
    from greybox.io._atomic import atomic_output_dir as atomic_output_dir
    from greybox.io._atomic import atomic_output_file as atomic_output_file
    from greybox.io._csv import CsvTable as CsvTable
    from greybox.io._csv import read_csv as read_csv
    from greybox.io._dataframe import experiment_from_dataframe as experiment_from_dataframe
    from greybox.io._dataframe import experiment_to_dataframe as experiment_to_dataframe
    from greybox.io._dataframe import predictions_to_dataframe as predictions_to_dataframe
    from greybox.io._design_file import experiment_toml as experiment_toml
    from greybox.io._experiment_set import ExperimentSet as ExperimentSet
    from greybox.io._experiment_set import InputErrors as InputErrors
    from greybox.io._experiment_set import RunInfo as RunInfo
    from greybox.io._experiment_set import candidate_names as candidate_names
    from greybox.io._experiment_set import configure_model as configure_model
    from greybox.io._experiment_set import fit_memory_estimate as fit_memory_estimate
    from greybox.io._experiment_set import load_experiment_set as load_experiment_set
    from greybox.io._experiment_writer import format_number as format_number
    from greybox.io._experiment_writer import inline_table as inline_table
    from greybox.io._experiment_writer import pulse_train_description as pulse_train_description
    from greybox.io._experiment_writer import run_csv as run_csv
    from greybox.io._experiment_writer import run_table as run_table
    from greybox.io._export import StateSpaceExport as StateSpaceExport
    from greybox.io._export import to_state_space as to_state_space
    from greybox.io._jax_setup import configure as configure_jax  # noqa: F401 (re-export)
    from greybox.io._params_file import FittedModel as FittedModel
    from greybox.io._params_file import load_params as load_params
    from greybox.io._params_file import params_document as params_document
    from greybox.io._params_file import write_params as write_params
    from greybox.io._waveform_spec import parse_waveform_spec as parse_waveform_spec
    from greybox.io._waveform_spec import waveform_from_csv as waveform_from_csv
    from greybox.io._waveform_spec import waveform_from_description as waveform_from_description
