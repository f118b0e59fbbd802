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

use serde::{Deserialize, Serialize};
use std::time::Duration;
use stitch_robot::{Point, Vector, WoundPoint};

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

/// Where the plan has the needle when a condition asks about it (which jaw to look near).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeedleAt {
    /// Held by the right (inserting) jaw, near the swage.
    RightJaw,
    /// In the tissue through the throw's holes, held by neither jaw.
    Tissue,
    /// Held by the left (extracting) jaw.
    LeftJaw,
}

/// What the engine asks for when a plan's condition is decided.
#[derive(Clone, Copy, Debug)]
pub struct ObserveRequest<'a> {
    /// Throw index, 0-based.
    pub throw: usize,
    /// The throw's wound point.
    pub point: &'a WoundPoint,
    /// Whether to run a needle query (one estimator cycle) now.
    pub needle: bool,
    /// Whether to trace the thread now (from the last stitch's exit to the swage of the
    /// needle query's estimate; a condition on the thread asks for both).
    pub thread: bool,
    /// Where the plan has the needle.
    pub needle_at: NeedleAt,
}

/// A needle estimate as a condition reads it, robot frame, m.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct NeedleSeen {
    /// The arc's centre.
    pub center: Point,
    /// The unit normal of the needle's plane.
    pub normal: Vector,
    /// The tip.
    pub tip: Point,
    /// The swage.
    pub swage: Point,
    /// How sure the estimator was, 0 to 1.
    pub confidence: f64,
    /// When its images were taken, on the run's clock, s.
    pub stamp_s: f64,
}

/// A thread trace as a condition reads it (and the journal keeps it), robot frame.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadSeen {
    /// Points along the thread from where it leaves the tissue (or its tail) to the swage,
    /// about every 5 mm, m.
    pub points: Vec<Point>,
    /// Each point's uncertainty (its expected distance from the truth), m.
    pub sigma_m: Vec<f64>,
    /// The traced length, m.
    pub length_m: f64,
    /// The share of it the camera saw (the rest bridged behind a jaw or the needle).
    pub seen_share: f64,
}

impl ThreadSeen {
    /// A trace kept at points at least `step_m` apart (the first and last always).
    pub fn from_trace(
        points: &[Point],
        sigma_m: &[f64],
        length_m: f64,
        seen_share: f64,
        step_m: f64,
    ) -> Self {
        let mut out = ThreadSeen {
            points: Vec::new(),
            sigma_m: Vec::new(),
            length_m,
            seen_share,
        };
        let mut since = f64::INFINITY;
        for (i, (p, s)) in points.iter().zip(sigma_m).enumerate() {
            if i > 0 {
                since += (p - points[i - 1]).norm();
            }
            if since >= step_m || i + 1 == points.len() {
                out.points.push(*p);
                out.sigma_m.push(*s);
                since = 0.0;
            }
        }
        out
    }
}

/// What the robot could tell when a condition was decided. Only what its sensors give: a
/// needle estimate and the arms' measured poses.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Observation {
    /// The latest needle estimate: this query's if it saw the needle, else an earlier one
    /// (its stamp says how old), else none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub needle: Option<NeedleSeen>,
    /// Whether this query saw the needle.
    #[serde(default)]
    pub needle_now: bool,
    /// Why this query saw no needle (a typed perception failure), if it ran and saw none.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub needle_failure: Option<String>,
    /// The thread as traced now, if asked and traced.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub thread: Option<ThreadSeen>,
    /// Why the thread was not traced (a typed perception failure), if asked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub thread_failure: Option<String>,
    /// The right jaw's tip, as PSM1 measures it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub right_jaw: Option<Point>,
    /// The left jaw's tip, as PSM2 measures it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left_jaw: Option<Point>,
    /// What went wrong while observing (an arm that did not report its pose): the
    /// observation lacks that part, and says why.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub faults: Vec<String>,
    /// A value a schedule dictates instead of an observation (scripted primitives and
    /// replays of model-checker paths only; a robot never sets it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scripted: Option<bool>,
}

/// The engine's only way to move the robot. Implementations: the real primitives over the
/// `robot/` traits (mock or real dVRK), and [`ScriptedPrimitives`] for tests.
pub trait Primitives {
    /// Run one attempt of one step and report its outcome. Robot errors during the step are
    /// reported as a [`FailureKind::ArmFault`] failure, after the arms were made to hold.
    /// While it runs it asks `control` whether to go on, between motions and during each
    /// one (every [`StepControl::slice`]): the supervisor may pause it (the arms hold, then
    /// it goes on where it stopped), or end it ([`StepOutcome::Interrupted`]: the arms hold
    /// and it commands nothing more).
    fn run(&mut self, req: &StepRequest<'_>, control: &mut dyn StepControl) -> StepOutcome;

    /// Observe for a plan's condition: a needle query if asked (one estimator cycle, no
    /// motion) and the arms' measured poses. Never fails: what could not be seen is absent.
    fn observe(&mut self, req: &ObserveRequest<'_>) -> Observation;

    /// Stop every motion and hold both arms where they are. Called on pause, take-over,
    /// abort, e-stop and at the end of a failed run.
    fn hold_all(&mut self) -> Result<(), PrimitiveError>;
}

/// What a primitive asks of whoever runs it, while it runs: the supervising surgeon may speak
/// in the middle of a motion, not only between steps.
pub trait StepControl {
    /// How long the primitive may wait on a motion (or sleep) before it asks
    /// [`StepControl::check`] again, on the run's clock; `None`: as long as the motion takes.
    fn slice(&mut self) -> Option<Duration>;

    /// Whether to go on. When a command stops the motion, the control calls `hold` (stop
    /// every motion, hold both arms) before anything else, then decides: go on
    /// ([`Control::Resumed`] after a pause: the stopped motion must be commanded again), or
    /// [`Control::Stop`].
    fn check(&mut self, hold: &mut dyn FnMut() -> Result<(), PrimitiveError>) -> Control;

    /// The step passed its commit point: what it does to the needle, tissue or thread is
    /// under way and cannot be undone by running it again (the needle let go in the tissue,
    /// a pull on the thread begun, the needle let go by the other jaw). A take-over from here
    /// hands back to the step after it.
    fn commit(&mut self);
}

/// What a [`StepControl`] tells a primitive.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Control {
    /// Go on.
    Go,
    /// The run was paused and is resumed: command the stopped motion again, and go on.
    Resumed,
    /// End the attempt at once and command nothing more: the arms hold.
    Stop,
}

/// A control that never interrupts (tests, tools that run a primitive alone).
#[derive(Clone, Copy, Debug, Default)]
pub struct Uninterrupted;

impl StepControl for Uninterrupted {
    fn slice(&mut self) -> Option<Duration> {
        None
    }
    fn check(&mut self, _hold: &mut dyn FnMut() -> Result<(), PrimitiveError>) -> Control {
        Control::Go
    }
    fn commit(&mut self) {}
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
