#![doc = include_str!("../README.md")]

mod band;
pub mod disparity;
pub mod fit;
#[cfg(feature = "onnx")]
pub mod onnx;
pub mod pipeline;
pub mod refine;
pub mod segment;
pub mod thread;

pub use disparity::{
    DisparityMap, LeftRight, MaskRowMatcher, SemiGlobalMatcher, SgmPaths, StereoMatcher,
};
pub use pipeline::{
    JawHint, NeedleEnd, NeedleHint, NeedlePipeline, PipelineEstimator, PipelineOutput,
    PipelineParams, PoseError, TissueHint,
};
pub use segment::{ColorSegmenter, Masks, Rect, Segmenter, SharedSegmenter};
pub use thread::{ThreadHint, ThreadParams, ThreadTrace};

use serde::{Deserialize, Serialize};
use std::time::Duration;
use stitch_robot::{Needle, Point, Pose, Vector};

/// A needle pose estimate in the robot frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NeedleEstimate {
    /// The needle frame (centre at the origin, normal +z, tip at +x·r, swage at −x·r), robot
    /// frame, m.
    pub pose: Pose,
    /// How sure the estimator is, 0 to 1.
    pub confidence: f64,
    /// When the images it came from were taken, on the run's clock.
    pub stamp: Duration,
}

impl NeedleEstimate {
    /// Centre, normal, tip and swage in the robot frame for a needle of this model.
    pub fn features(&self, needle: &Needle) -> (Point, Vector, Point, Point) {
        let g = needle.in_world(&self.pose);
        (g.center, g.normal, g.tip, g.swage)
    }
}

/// Why there is no estimate: never a made-up pose.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, thiserror::Error)]
#[serde(tag = "kind", rename_all = "snake_case")]
#[non_exhaustive]
pub enum PerceptionError {
    /// The needle was not found in the images.
    #[error("no needle in view")]
    NotFound,
    /// The needle is hidden (by the thread, a jaw, tissue).
    #[error("needle occluded{}", if *by_thread { " by the thread" } else { "" })]
    Occluded {
        /// Whether the thread hides it.
        by_thread: bool,
    },
    /// The fit was too poor to act on.
    #[error("estimate too uncertain (confidence {confidence:.2})")]
    Uncertain {
        /// The fit's confidence, 0 to 1.
        confidence: f64,
    },
    /// No needle pixels in a view.
    #[error("no needle pixels in the {view} image")]
    NoMask {
        /// Which view.
        view: String,
    },
    /// Too few 3D points on the needle.
    #[error("only {found} needle points with a disparity ({needed} needed)")]
    TooFewPoints {
        /// Points found.
        found: usize,
        /// Points needed.
        needed: usize,
    },
    /// The points do not fit the needle's shape.
    #[error("bad fit: {why}")]
    BadFit {
        /// What went wrong.
        why: String,
    },
    /// Tip and swage cannot be told apart.
    #[error("cannot tell the tip from the swage: {why}")]
    AmbiguousEndpoints {
        /// The evidence.
        why: String,
    },
    /// The pipeline's configuration or input cannot be used.
    #[error("perception configuration: {message}")]
    Config {
        /// What is wrong.
        message: String,
    },
    /// The camera failed.
    #[error("camera: {message}")]
    Camera {
        /// What it said.
        message: String,
    },
    /// No thread in a view near where it should be (the needle's swage, the last exit).
    #[error("no thread in the {view} image near the swage and the suture line")]
    NoThread {
        /// Which view.
        view: String,
    },
    /// Too much of the thread is hidden (behind a jaw, the needle, out of the image) to
    /// trace it.
    #[error("thread hidden: only {:.0} % of it seen", seen_share * 100.0)]
    ThreadHidden {
        /// The share of the traced path the left view showed as thread.
        seen_share: f64,
    },
    /// The thread was seen but could not be traced in 3D.
    #[error("thread not traced: {why}")]
    ThreadUntraced {
        /// Why.
        why: String,
    },
    /// A learned model (the segmenter's) failed to run: a fault of the perception system,
    /// like a camera's, not a needle out of sight.
    #[error("model: {message}")]
    Model {
        /// What failed.
        message: String,
    },
}

/// Estimates the needle's pose. Implementations: the mock dVRK's noise model, and the stereo
/// pipeline. Each call may take time on the run's clock.
pub trait NeedleEstimator: Send {
    /// One estimate from the current view.
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError>;

    /// One estimate, knowing where the needle should be: which jaw holds it, or which holes
    /// it is lodged in (estimators that can use it search there and orient by it; the
    /// default ignores it).
    fn estimate_needle_with(
        &mut self,
        hint: Option<&NeedleHint>,
    ) -> Result<NeedleEstimate, PerceptionError> {
        let _ = hint;
        self.estimate_needle()
    }

    /// Trace the free thread from where it leaves the suture line to the swage
    /// ([`thread`]), knowing its ends. Estimators without a thread tracer say so, typed.
    fn trace_thread(&mut self, hint: &ThreadHint) -> Result<ThreadTrace, PerceptionError> {
        let _ = hint;
        Err(PerceptionError::Config {
            message: "this perception has no thread tracer".into(),
        })
    }
}
