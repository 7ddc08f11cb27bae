"""Data-driven control substrate: structured LTI operators, plants, VRFT and De Persis-Tesi learners, analysis."""

from bilevel.ddc.analysis import (
    ClosedLoopResponse,
    StateFeedbackAnalysis,
    analyze_state_feedback,
    closed_loop,
    closed_loop_bode,
    closed_loop_poles,
    closed_loop_response,
    closed_loop_step,
)
from bilevel.ddc.bases import controller_tf, flexible_transmission_basis, pi_basis, pid_basis
from bilevel.ddc.data import (
    batch_reactor_data,
    paper_input,
    simulate,
    state_trajectory,
    step_pulse,
    white_noise,
    white_noise_trajectory,
)
from bilevel.ddc.depersis_tesi import (
    DPTController,
    StateData,
    check_persistency,
    lqr_controller,
    stabilizing_controller,
    state_data,
)
from bilevel.ddc.operators import LTIOperator, reference_inverse, virtual_error_operator
from bilevel.ddc.plants import (
    batch_reactor,
    flexible_transmission,
    flexible_transmission_prefilter,
    flexible_transmission_reference,
)
from bilevel.ddc.systems import as_tf, num_den, series
from bilevel.ddc.vrft import (
    VRFTFit,
    VRFTRegressor,
    fit_vrft,
    instrumental_variables,
    least_squares,
    normal_equations,
    vrft_loss,
    vrft_regressor,
)

__all__ = [
    "ClosedLoopResponse", "DPTController", "LTIOperator", "StateData", "StateFeedbackAnalysis",
    "VRFTFit", "VRFTRegressor", "analyze_state_feedback", "as_tf", "batch_reactor",
    "batch_reactor_data", "check_persistency", "closed_loop", "closed_loop_bode",
    "closed_loop_poles", "closed_loop_response", "closed_loop_step", "controller_tf",
    "fit_vrft", "flexible_transmission", "flexible_transmission_basis",
    "flexible_transmission_prefilter", "flexible_transmission_reference",
    "instrumental_variables", "least_squares", "lqr_controller", "normal_equations",
    "num_den", "paper_input", "pi_basis", "pid_basis", "reference_inverse",
    "series", "simulate", "stabilizing_controller", "state_data", "state_trajectory",
    "step_pulse", "virtual_error_operator", "vrft_loss", "vrft_regressor", "white_noise",
    "white_noise_trajectory",
]
