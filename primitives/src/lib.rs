#![doc = include_str!("../README.md")]

#[cfg(feature = "mock")]
mod mock;
mod outcome;
mod params;
mod robot;
mod scripted;

#[cfg(feature = "mock")]
pub use mock::{
    MockObserver, MockPerception, ModelEstimator, PIPELINE_FRAME_TIME_S, mock_layout,
    mock_primitives, mock_primitives_observed, mock_primitives_with,
};
pub use outcome::{Failure, FailureKind, Measurements, StepOutcome};
pub use params::*;
pub use robot::{
    CINCH_MAX_PULL_M, ESTIMATE_TRIES, Layout, MOTION_TIMEOUT, Observer, PassObservation, RETREAT_M,
    ROTATION_STEP_RAD, Rig, RobotPrimitives, insertion_start, insertion_waypoints, mean_pose,
    regrasp_waypoints, rotated_about,
};
pub use scripted::{Call, OutcomeModel, SCRIPTED_TOKENS, Scripted, ScriptedPrimitives};

use stitch_robot::WoundPoint;

/// What the engine asks a primitive to do: one attempt at one step of one throw.
#[derive(Clone, Copy, Debug)]
pub struct StepRequest<'a> {
    /// Throw index, 0-based (suture number i = throw + 1).
    pub throw: usize,
    /// Step index within the throw, 0-based.
    pub step: usize,
    /// The wound point this throw sutures.
    pub point: &'a WoundPoint,
    /// The step and its parameters.
    pub kind: &'a StepKind,
    /// Attempt number for this step, 0 for the first.
    pub attempt: u32,
}

/// The engine's only way to move the robot. Implementations: the real primitives over the
/// `robot/` traits (mock or real dVRK), and [`ScriptedPrimitives`] for tests.
pub trait Primitives {
    /// Run one attempt of one step and report its outcome. Robot errors during the step are
    /// reported as a [`FailureKind::ArmFault`] failure, after the arms were made to hold.
    fn run(&mut self, req: &StepRequest<'_>) -> StepOutcome;

    /// Stop every motion and hold both arms where they are. Called on pause, take-over,
    /// abort, e-stop and at the end of a failed run.
    fn hold_all(&mut self) -> Result<(), PrimitiveError>;
}

/// Errors of this crate.
#[derive(Clone, Debug, PartialEq, thiserror::Error, serde::Serialize)]
#[non_exhaustive]
pub enum PrimitiveError {
    /// The robot refused or failed a command.
    #[error("robot error: {message}")]
    Robot {
        /// The robot's message.
        message: String,
    },
}
