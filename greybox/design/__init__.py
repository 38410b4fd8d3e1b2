"""Experiment and waveform design: Fisher information of candidate runs, designs that
shrink chosen standard errors under lab constraints, and waveforms that track a target."""

from greybox.design._design import Design as Design
from greybox.design._design import DesignedRun as DesignedRun
from greybox.design._design import DesignProblem as DesignProblem
from greybox.design._design import LabConstraints as LabConstraints
from greybox.design._design import TrackingDesign as TrackingDesign
from greybox.design._design import comparison_table as comparison_table
from greybox.design._design import design_experiment as design_experiment
from greybox.design._design import design_problem as design_problem
from greybox.design._design import design_standard_errors as design_standard_errors
from greybox.design._design import det_gain as det_gain
from greybox.design._design import evaluate_design as evaluate_design
from greybox.design._design import format_design_table as format_design_table
from greybox.design._design import habitual_baseline as habitual_baseline
from greybox.design._design import run_information as run_information
from greybox.design._design import track_target as track_target
