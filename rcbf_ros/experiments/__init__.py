"""The paper's experiments as commands (no ROS): definitions, runner, evaluation, report.

``rcbf_ros experiment sample_efficiency|transfer|value_maps|all --budget smoke|paper`` trains
every configuration of an experiment over N seeds (sequentially, or as Ray tasks), skips runs
that already finished, evaluates and writes CSV + PNG + a markdown report. See
:mod:`rcbf_ros.experiments.definitions` for what each experiment runs and docs/RESULTS.md for
the numbers.
"""
from __future__ import annotations
