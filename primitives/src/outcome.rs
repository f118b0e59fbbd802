//! What a step reports back: success with what it achieved, or a typed failure with the
//! measurements the engine's recovery conditions need.

use serde::{Deserialize, Serialize};

/// Measurements a step took, for recovery conditions and for the throw's record. `None` when
/// the step does not measure it.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Measurements {
    /// How far the grasped needle endpoint moved during an extraction, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub endpoint_travel_m: Option<f64>,
    /// Angle between the needle normal before and after a handover grasp, rad.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub normal_change_rad: Option<f64>,
    /// Lateral offset of the tip from the entry hole when it crossed the hole plane, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub entry_error_m: Option<f64>,
    /// Lateral offset of the tip from the exit hole when it crossed the hole plane, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub exit_error_m: Option<f64>,
    /// Thread consumed or pulled by this step, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thread_used_m: Option<f64>,
    /// Thread left on the needle's side after this step, where something can tell, m.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thread_left_m: Option<f64>,
    /// A handover's look at the thread before it grasped (its `thread_margin`): how near the
    /// traced thread came to the closing blades, less twice its uncertainty, m; below the
    /// margin it pushed the thread away first.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thread_clearance_m: Option<f64>,
    /// Why the needle estimator gave no estimate, each cycle of this step it gave none (a
    /// typed perception failure): a step that waited on the needle says what it saw instead;
    /// a thread that could not be traced, where a step looked at it, is said here too.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub perception_failures: Vec<String>,
}

/// Why a step failed. The engine decides retry, intervention or failure from this and the
/// measurements; the paper's error class comes from the phase, except for thread failures.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
#[non_exhaustive]
pub enum FailureKind {
    /// The motion ran but did not move the needle as it should (an extraction whose endpoint
    /// barely moved; a handover grasp that left the normal unchanged). The recovery
    /// conditions of "Motion Failure Recovery" apply.
    NoProgress,
    /// The needle or thread could not be seen (no estimate, or too uncertain to act on).
    PerceptionDropout,
    /// The step's physical goal was missed (the tip missed the entry or exit, the needle
    /// stayed in the tissue, the grasp closed on nothing).
    Missed,
    /// The needle fell from the jaws.
    NeedleDropped,
    /// The closing jaw caught the thread, alone or with the needle.
    ThreadCaught,
    /// The thread is tangled around a jaw.
    ThreadTangled,
    /// Not enough thread left to cinch this suture.
    ThreadShort,
    /// The robot reported a fault (the message is the robot's).
    ArmFault {
        /// What the robot said.
        message: String,
    },
}

impl FailureKind {
    /// Whether this failure is about the thread (the paper's class T whatever the phase).
    pub fn is_thread(&self) -> bool {
        matches!(
            self,
            FailureKind::ThreadCaught | FailureKind::ThreadTangled | FailureKind::ThreadShort
        )
    }

    /// A short name for timelines and journals.
    pub fn label(&self) -> &'static str {
        match self {
            FailureKind::NoProgress => "no progress",
            FailureKind::PerceptionDropout => "perception dropout",
            FailureKind::Missed => "missed",
            FailureKind::NeedleDropped => "needle dropped",
            FailureKind::ThreadCaught => "thread caught",
            FailureKind::ThreadTangled => "thread tangled",
            FailureKind::ThreadShort => "thread short",
            FailureKind::ArmFault { .. } => "arm fault",
        }
    }
}

/// A failed step: why, and what was measured.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Failure {
    /// Why it failed.
    #[serde(flatten)]
    pub kind: FailureKind,
    /// What the step measured before failing.
    pub measured: Measurements,
}

/// The result of one attempt at one step.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "result", rename_all = "snake_case")]
pub enum StepOutcome {
    /// The step reached its goal.
    Succeeded {
        /// What it measured and achieved.
        measured: Measurements,
    },
    /// The step did not reach its goal.
    Failed(Failure),
    /// The supervisor ended the attempt mid-step (take-over, abort, e-stop): the arms held and
    /// it commanded nothing more. Neither a success nor a failure: no retry and no
    /// intervention follows from it.
    Interrupted {
        /// Whether the step had passed its commit point (what it does to the needle, tissue
        /// or thread was under way).
        committed: bool,
        /// What it measured before it was stopped.
        measured: Measurements,
    },
}

impl StepOutcome {
    /// Success with nothing measured.
    pub fn ok() -> Self {
        StepOutcome::Succeeded {
            measured: Measurements::default(),
        }
    }

    /// Failure of `kind` with nothing measured.
    pub fn failed(kind: FailureKind) -> Self {
        StepOutcome::Failed(Failure {
            kind,
            measured: Measurements::default(),
        })
    }

    /// The measurements, whichever the result.
    pub fn measured(&self) -> &Measurements {
        match self {
            StepOutcome::Succeeded { measured } => measured,
            StepOutcome::Failed(f) => &f.measured,
            StepOutcome::Interrupted { measured, .. } => measured,
        }
    }
}
