"""One extended model per cause, fitted on the estimation data and simulated free-run on the
validation data (``Split.validation_output``); one module per cause, what they share in
``common``.

Every extension starts from a paper's estimate or from the baseline and is refined on the
simulation error (``simulation_error.refine``), like the baseline, so that the gains compare
structures, not estimators.
"""

from __future__ import annotations

from collections.abc import Callable

from ..causes import EXTENSION
from .backlash import extend_backlash
from .common import NUMERICAL_FAILURES, Context, ExtendedModel, MapPlot, NotFitted, failure_reason, map_plot
from .input_dynamics import extend_input_dynamics
from .output_feedback import FeedbackLayout, extend_output_feedback, map_on
from .output_nonlinearity import extend_output_nonlinearity
from .parallel_path import extend_parallel_path, linear_fit
from .periodic_disturbance import extend_periodic_disturbance
from .time_varying import extend_time_varying
from .unmodeled_dynamics import extend_unmodeled_dynamics

EXTENSIONS: dict[str, Callable[[Context], ExtendedModel]] = {
    "output_feedback": extend_output_feedback,
    "parallel_path": extend_parallel_path,
    "output_nonlinearity": extend_output_nonlinearity,
    "backlash": extend_backlash,
    "time_varying": extend_time_varying,
    "unmodeled_dynamics": extend_unmodeled_dynamics,
    "periodic_disturbance": extend_periodic_disturbance,
    "input_dynamics": extend_input_dynamics,
}

assert set(EXTENSIONS) == set(EXTENSION)

__all__ = [
    "EXTENSIONS",
    "NUMERICAL_FAILURES",
    "Context",
    "ExtendedModel",
    "FeedbackLayout",
    "MapPlot",
    "NotFitted",
    "extend_backlash",
    "extend_input_dynamics",
    "extend_output_feedback",
    "extend_output_nonlinearity",
    "extend_parallel_path",
    "extend_periodic_disturbance",
    "extend_time_varying",
    "extend_unmodeled_dynamics",
    "failure_reason",
    "linear_fit",
    "map_on",
    "map_plot",
]
