"""Evaluation of results folders and trajectory files against ground truth: the public names.

The work is split by job: :mod:`~loopmodel.eval.inputs` (results folders, trajectory files,
ground truth), :mod:`~loopmodel.eval.evaluation` (the numbers), :mod:`~loopmodel.eval.render`
(plots, Markdown, HTML, ``metrics.json``) and :mod:`~loopmodel.eval.compare` (many runs).
"""

from __future__ import annotations

from loopmodel.eval.compare import COMPARISON_COLUMNS as COMPARISON_COLUMNS
from loopmodel.eval.compare import comparison_rows as comparison_rows
from loopmodel.eval.compare import comparison_rows_from_metrics as comparison_rows_from_metrics
from loopmodel.eval.compare import csv_text as csv_text
from loopmodel.eval.compare import markdown_table as markdown_table
from loopmodel.eval.compare import write_comparison as write_comparison
from loopmodel.eval.evaluation import RunEvaluation as RunEvaluation
from loopmodel.eval.evaluation import evaluate_run as evaluate_run
from loopmodel.eval.inputs import FINAL_FILE as FINAL_FILE
from loopmodel.eval.inputs import KEYFRAMES_FILE as KEYFRAMES_FILE
from loopmodel.eval.inputs import ONLINE_FILE as ONLINE_FILE
from loopmodel.eval.inputs import RUN_METRICS_FILE as RUN_METRICS_FILE
from loopmodel.eval.inputs import LoopClosureEvent as LoopClosureEvent
from loopmodel.eval.inputs import RunData as RunData
from loopmodel.eval.inputs import TimedTrajectory as TimedTrajectory
from loopmodel.eval.inputs import check_comparable as check_comparable
from loopmodel.eval.inputs import ground_truth_hint as ground_truth_hint
from loopmodel.eval.inputs import load_ground_truth as load_ground_truth
from loopmodel.eval.inputs import load_run as load_run
from loopmodel.eval.inputs import load_trajectory_file as load_trajectory_file
from loopmodel.eval.inputs import parse_loop_closures as parse_loop_closures
from loopmodel.eval.inputs import plain_run as plain_run
from loopmodel.eval.render import PLOT_ERROR_COLORED as PLOT_ERROR_COLORED
from loopmodel.eval.render import PLOT_ERROR_TIME as PLOT_ERROR_TIME
from loopmodel.eval.render import PLOT_RPE_TIME as PLOT_RPE_TIME
from loopmodel.eval.render import PLOT_TOP as PLOT_TOP
from loopmodel.eval.render import PLOT_XYZ_RPY as PLOT_XYZ_RPY
from loopmodel.eval.render import TRACK_LABELS as TRACK_LABELS
from loopmodel.eval.render import make_plots as make_plots
from loopmodel.eval.render import render_html as render_html
from loopmodel.eval.render import render_markdown as render_markdown
from loopmodel.eval.render import write_outputs as write_outputs
