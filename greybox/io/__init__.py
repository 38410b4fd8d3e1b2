"""File formats at the library's edge: experiment folders, params.json, result folders, video.

`load_experiment_set` reads an experiment folder (``experiment.toml`` + run CSVs, format in
``experiments/README.md``); `params_document`/`write_params`/`load_params` write and read
``params.json``; `experiment_writer` helpers write the inverse of the loader. Video I/O
(`probe`, `iter_frames`, `write_video`) needs the ``video`` extra.
"""

from greybox.io._atomic import atomic_output_dir as atomic_output_dir
from greybox.io._atomic import atomic_output_file as atomic_output_file
from greybox.io._csv import CsvTable as CsvTable
from greybox.io._csv import read_csv as read_csv
from greybox.io._dataframe import experiment_from_dataframe as experiment_from_dataframe
from greybox.io._dataframe import experiment_to_dataframe as experiment_to_dataframe
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
from greybox.io._params_file import FittedModel as FittedModel
from greybox.io._params_file import load_params as load_params
from greybox.io._params_file import params_document as params_document
from greybox.io._params_file import write_params as write_params
from greybox.io._waveform_spec import parse_waveform_spec as parse_waveform_spec
from greybox.io._waveform_spec import waveform_from_csv as waveform_from_csv
from greybox.io._waveform_spec import waveform_from_description as waveform_from_description
