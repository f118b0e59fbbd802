#![doc = include_str!("../README.md")]

mod faults;
mod phantom;
mod render;
mod sensing;
mod streams;
mod thread;
mod world;

pub use faults::{FaultConfig, FaultKind, Faults, MAX_JOINT_OFFSET, ScheduledFault};
pub use phantom::{
    Breach, HOLE_TOLERANCE_M, Hole, MIN_PROTRUSION_M, PassScore, Phantom, PhantomGeometry,
};
pub use render::{
    CameraConfig, FrameTruth, Label, MockCamera, PhantomView, RenderedPair, SWAGE_LENGTH_M,
    SceneView, StereoRenderer, TIP_TAPER_M, ToolView,
};
pub use sensing::{NoiseSpec, SensingConfig, SensingFailure};
pub use streams::{Streams, Subsystem};
pub use thread::{Capsule, Ground, Thread, ThreadConfig, tool_capsules};
pub use world::{
    GRASP_MIN_CROSSING_RAD, JAW_LENGTH_M, MockArm, MockDvrk, MockJaw, NeedlePlace, NeedleTruth,
    PsmConfig, SceneConfig, Side, grasp_in_needle_frame, ground_of, jaw_reaches_needle,
    nearest_on_needle,
};

/// Errors of the mock dVRK.
#[derive(Clone, Debug, PartialEq, thiserror::Error, serde::Serialize)]
#[non_exhaustive]
pub enum SimError {
    /// A configuration value the mock cannot use.
    #[error("invalid mock configuration {what}: {why}")]
    Config {
        /// Which value.
        what: String,
        /// Why.
        why: String,
    },
}
