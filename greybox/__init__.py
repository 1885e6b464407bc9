"""greybox: close the loop between a physical state-space model and measured data."""

from .exceptions import (
    CovarianceError,
    DataError,
    DimensionError,
    GreyboxError,
    GreyboxWarning,
    IdentificationError,
    ModelError,
    OutputExistsError,
    RankConditionError,
)

__version__ = "0.1.0"

__all__ = [
    "GreyboxError",
    "DimensionError",
    "DataError",
    "ModelError",
    "RankConditionError",
    "CovarianceError",
    "IdentificationError",
    "OutputExistsError",
    "GreyboxWarning",
]

from .filters import (  # noqa: E402
    FilterResult,
    SteadyStateFilter,
    check_rank_condition,
    kalman_filter,
    steady_state_filter,
    uikf,
)
from .filters.delayed import (  # noqa: E402
    RelativeDegree,
    delayed_uikf,
    detect_relative_degree,
    input_weights,
)
from .filters.feedthrough import feedthrough_uikf, with_sensor_error  # noqa: E402
from .filters.smoother import smooth_uikf  # noqa: E402
from .plants import (  # noqa: E402
    TAPE_DRIVE_DT,
    TAPE_DRIVE_Q,
    TAPE_DRIVE_R,
    TapeDriveParams,
    tape_drive_nominal,
    tape_drive_tension,
    tape_drive_true,
)
from .signals import SimulationResult, lowpass_noise, multisine, random_binary, simulate  # noqa: E402
from .system import (  # noqa: E402
    SplitModel,
    discretize,
    named_ss,
    split_inputs,
    zoh_equivalent_input,
)
from .metrics import (  # noqa: E402
    RelativeError,
    WhitenessTest,
    autocorrelation,
    cross_correlation,
    relative_error,
    whiteness_test,
    innovation_test,
)
from .ident import N4SIDResult, n4sid, pbsid  # noqa: E402
from .ident.oe import OEResult, output_error  # noqa: E402
from .ident.regression import forward_selection, static_least_squares  # noqa: E402
from .update import (  # noqa: E402
    DeltaModel,
    Subsystem,
    UpdatedModel,
    augment_model,
    delta_update,
    identify_subsystem,
)
from .validate import ModelValidation, estimate_initial_state, validate_model  # noqa: E402
from .workflow import (  # noqa: E402
    CandidateScore, Decision, Effect, EffectStep, LoopReport, close_the_loop)

__all__ += [
    "FilterResult",
    "SteadyStateFilter",
    "check_rank_condition",
    "kalman_filter",
    "steady_state_filter",
    "uikf",
    "TAPE_DRIVE_DT",
    "TAPE_DRIVE_Q",
    "TAPE_DRIVE_R",
    "TapeDriveParams",
    "tape_drive_nominal",
    "tape_drive_tension",
    "tape_drive_true",
    "SimulationResult",
    "lowpass_noise",
    "multisine",
    "random_binary",
    "simulate",
    "SplitModel",
    "discretize",
    "zoh_equivalent_input",
    "named_ss",
    "split_inputs",
    "RelativeError",
    "WhitenessTest",
    "autocorrelation",
    "cross_correlation",
    "relative_error",
    "whiteness_test",
    "innovation_test",
    "N4SIDResult",
    "n4sid",
    "pbsid",
    "OEResult",
    "output_error",
    "forward_selection",
    "static_least_squares",
    "DeltaModel",
    "Subsystem",
    "UpdatedModel",
    "augment_model",
    "delta_update",
    "identify_subsystem",
    "ModelValidation",
    "estimate_initial_state",
    "validate_model",
    "CandidateScore",
    "Decision",
    "Effect",
    "LoopReport",
    "EffectStep",
    "close_the_loop",
]

# unknown inputs behind the sensors (issue 11)
__all__ += [
    "RelativeDegree",
    "delayed_uikf",
    "detect_relative_degree",
    "input_weights",
    "feedthrough_uikf",
    "smooth_uikf",
    "with_sensor_error",
]

# nonlinear models and filters (section IV, issue 10)
from .filters import MerweScaledSigmaPoints, ensemble_uikf, ui_ukf, ukf  # noqa: E402
from .filters import delayed_ui_ukf  # noqa: E402
from .nonlinear import (  # noqa: E402
    add_law,
    as_nonlinear,
    discretize_nonlinear,
    kinematic_identities,
    linear_output_map,
    linearize_at,
    rk4_substeps,
    rk4_substeps_for,
    simulate_nonlinear,
    with_unknown_inputs,
)
from .workflow_nonlinear import NonlinearUpdate  # noqa: E402
from .nominal_refit import JointRefit, ParameterChange, refit_jointly  # noqa: E402
from .plants import (  # noqa: E402
    MOTOR_PUMP_DT,
    MOTOR_PUMP_Q,
    MOTOR_PUMP_R,
    MotorPumpParams,
    motor_pump_nominal,
    motor_pump_true,
)

__all__ += [
    "MerweScaledSigmaPoints",
    "ensemble_uikf",
    "ui_ukf",
    "ukf",
    "delayed_ui_ukf",
    "discretize_nonlinear",
    "linear_output_map",
    "rk4_substeps",
    "kinematic_identities",
    "rk4_substeps_for",
    "simulate_nonlinear",
    "add_law",
    "as_nonlinear",
    "linearize_at",
    "with_unknown_inputs",
    "NonlinearUpdate",
    "JointRefit",
    "ParameterChange",
    "refit_jointly",
    "MOTOR_PUMP_DT",
    "MOTOR_PUMP_Q",
    "MOTOR_PUMP_R",
    "MotorPumpParams",
    "motor_pump_nominal",
    "motor_pump_true",
]

# a fleet of units on Dask (issue 29): Dask itself is imported only when fleet() runs
from .fleet import FleetReport, UnitResult, fleet  # noqa: E402

__all__ += ["FleetReport", "UnitResult", "fleet"]
