//! The steps a plan can hold, their typed parameters, and the paper's defaults.
//!
//! Every default is a named constant with the section of the STITCH paper
//! (`../shared/paper/`) it comes from, or says that it is a modelling choice.
//! Plans may override each parameter within [`Range`]s checked by the engine.

use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Degrees to radians, for constants.
const fn deg(d: f64) -> f64 {
    d * PI / 180.0
}

// --- Needle Insertion ("Augmented Dexterity Suturing Motion Controller / Needle Insertion")
/// Rotation about the estimated circle normal that drives the needle through the tissue (45°).
pub const INSERT_ROTATION_RAD: f64 = deg(45.0);
/// Straight push of the tip along entry→exit before the rotation. The paper gives no number.
/// Chosen from the geometry (a modelling choice): with the 12 mm needle, a 10 mm bite and the
/// 45° rotation, the tip ends p + 12·sin 45° − 10 mm beyond the exit, so the SRC's 5 mm
/// protrusion needs p ≥ 6.5 mm; 7 mm crosses the exit plane 0.38 mm from the hole.
pub const INSERT_PUSH_M: f64 = 0.007;
/// Before insertion the tip waits this far back from the entry (and half as far above it), so
/// the approach comes from outside the tissue. The paper gives no number; modelling choice.
pub const INSERT_STANDOFF_M: f64 = 0.01;

// --- Thread Sweeping
/// Travel of the open jaw along +y down the wound centre. The paper gives no number; modelling
/// choice (3 cm, longer than the 6-point wound's span from the current point to the camera side).
pub const SWEEP_DISTANCE_M: f64 = 0.03;
/// "Opening the gripper wide": jaw angle for the sweep (dVRK needle drivers open to about 80°;
/// modelling choice 60°).
pub const SWEEP_JAW_OPEN_RAD: f64 = deg(60.0);

// --- Needle Extraction
/// Horizontal stand-off from the re-grasp point before approaching (1 cm).
pub const EXTRACT_OFFSET_M: f64 = 0.01;
/// Approach towards the re-grasp point before closing the jaws (1.5 cm).
pub const EXTRACT_APPROACH_M: f64 = 0.015;
/// Rotation about the estimated needle axis after grasping (80°).
pub const EXTRACT_ROTATION_RAD: f64 = deg(80.0);
/// Recovery condition ("Motion Failure Recovery"): the endpoint moved less than 2 cm → retry.
pub const EXTRACT_MIN_TRAVEL_M: f64 = 0.02;
/// The linear pull that finishes an extraction ("pulled out linearly"; the paper gives no
/// length; modelling choice 3 cm away from the wound and up).
pub const EXTRACT_PULL_M: f64 = 0.03;
/// Retries after a failed extraction ("Motion Failure Recovery": up to 5).
pub const EXTRACT_RETRIES: u8 = 5;

// --- Suture Cinching: β = l_des − (i − 1)·l_each
/// l_des, the thread pulled for the first suture. The paper gives no number; modelling choice
/// (12 cm) within the 10–40 cm threads of "Experimental Setup".
pub const CINCH_L_DES_M: f64 = 0.12;
/// l_each, the thread one suture uses. The paper gives no number; modelling choice (2 cm).
pub const CINCH_L_EACH_M: f64 = 0.02;

// --- Needle Handover
/// Horizontal stand-off from the re-grasp point (1 cm).
pub const HANDOVER_OFFSET_M: f64 = 0.01;
/// Largest random horizontal offset added on a re-attempt ("a small (< 0.5 cm) random
/// horizontal offset").
pub const HANDOVER_JITTER_M: f64 = 0.005;
/// The small rotation that tests a handover grasp: if the right jaw holds the needle, the
/// needle's normal turns with it. The paper compares normals "before and after moving the
/// right needle driver" without a number; modelling choice 20°, well above the estimator's
/// normal noise.
pub const HANDOVER_TUG_RAD: f64 = deg(20.0);
/// How far in from the needle's end the handover grasps it, along the arc: the blades must
/// close on wire, not on the very end. The paper says "the endpoint"; modelling choice 20°
/// (4 mm of a 12 mm needle).
pub const HANDOVER_INSET_RAD: f64 = deg(20.0);
/// Re-attempts after a failed grasp ("up to 5 additional times").
pub const HANDOVER_RETRIES: u8 = 5;
/// Before each grasp, the closing blades should stay this clear of the traced thread (less
/// twice its uncertainty); a re-attempt's random offset that does not goes to the other side
/// of the grasp point. Not in the paper (its handover looks at no thread); 0 leaves the look
/// out, as STITCH does. A plan turns it on (`scripts/stitch_thread.rhai`: 3 mm,
/// docs/experiments.md).
pub const HANDOVER_THREAD_MARGIN_M: f64 = 0.0;
/// Below this change the needle normal counts as "unchanged" (the grasp did not take). The
/// paper says "unchanged"; a measured normal is never exactly equal, and the difference of
/// two estimates carries both their noise, so modelling choice 8° (against the primitive's
/// 20° test rotation).
pub const HANDOVER_NORMAL_TOLERANCE_RAD: f64 = deg(8.0);

// --- Needle Pose Correction
/// Normal samples averaged at the lower back right corner (10).
pub const CORRECT_SAMPLES: u32 = 10;
/// Final rotation about +y after aligning the normal with +y (90°).
pub const CORRECT_FINAL_ROTATION_RAD: f64 = deg(90.0);

// --- Perception queries (not named in the paper; modelling choices)
/// Needle pose samples averaged by an explicit `estimate_needle` step.
pub const ESTIMATE_SAMPLES: u32 = 1;
/// Retries of a perception query after a dropout.
pub const PERCEPTION_RETRIES: u8 = 2;

/// An inclusive range a parameter must lie in, with its unit for messages.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Range {
    /// Smallest allowed value, in SI units.
    pub min: f64,
    /// Largest allowed value, in SI units.
    pub max: f64,
}

impl Range {
    const fn new(min: f64, max: f64) -> Self {
        Self { min, max }
    }
    /// Whether `v` is finite and within the range.
    pub fn contains(&self, v: f64) -> bool {
        v.is_finite() && v >= self.min && v <= self.max
    }
}

/// The physical kind of a parameter, which decides the unit a script must say.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Quantity {
    /// Metres; scripts say `mm(..)`, `cm(..)` or `m(..)`.
    Length,
    /// Radians; scripts say `deg(..)` or `rad(..)`.
    Angle,
    /// A whole number (retries, samples).
    Count,
}

/// One parameter's value: typed, in SI units.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Value {
    /// Metres.
    Length(f64),
    /// Radians.
    Angle(f64),
    /// A whole number.
    Count(i64),
}

/// Where a parameter lives in its step, for the engine's generic checks and the script API.
#[derive(Clone, Copy, Debug)]
pub struct ParamSpec {
    /// Name in scripts (`#{ retries: 5 }`).
    pub name: &'static str,
    /// What the value measures.
    pub quantity: Quantity,
    /// Allowed values.
    pub range: Range,
    /// What it is, for the scripting reference and error messages.
    pub doc: &'static str,
}

macro_rules! spec {
    ($name:literal, $q:ident, $min:expr, $max:expr, $doc:literal) => {
        ParamSpec {
            name: $name,
            quantity: Quantity::$q,
            range: Range::new($min, $max),
            doc: $doc,
        }
    };
}

/// `insert(#{ .. })`: right PSM drives the needle from the wound point's entry to its exit.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct InsertParams {
    /// Rotation about the estimated needle normal, rad.
    pub rotation_rad: f64,
    /// Straight push along entry→exit before rotating, m.
    pub push_m: f64,
    /// Stand-off of the tip from the entry before it goes in, m.
    pub standoff_m: f64,
    /// Needle pose estimates averaged for the grasp right before the insertion. 0, the
    /// paper's: the last pose correction's measurement if there is one, else one estimate.
    /// N ≥ 1: always N fresh estimates (closing the loop after the correction's open-loop
    /// turn).
    pub samples: u32,
}
impl Default for InsertParams {
    fn default() -> Self {
        Self {
            rotation_rad: INSERT_ROTATION_RAD,
            push_m: INSERT_PUSH_M,
            standoff_m: INSERT_STANDOFF_M,
            samples: 0,
        }
    }
}

/// `sweep(#{ .. })`: right jaw wide open, along +y down the wound towards the camera.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct SweepParams {
    /// Travel along +y, m.
    pub distance_m: f64,
    /// Jaw opening during the sweep, rad.
    pub jaw_open_rad: f64,
}
impl Default for SweepParams {
    fn default() -> Self {
        Self {
            distance_m: SWEEP_DISTANCE_M,
            jaw_open_rad: SWEEP_JAW_OPEN_RAD,
        }
    }
}

/// `extract(#{ .. })`: left PSM grasps the nearer endpoint, rotates and pulls the needle out.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct ExtractParams {
    /// Retries while the recovery condition holds; the engine caps this at 5.
    pub retries: u8,
    /// Horizontal stand-off before the approach, m.
    pub offset_m: f64,
    /// Approach towards the re-grasp point, m.
    pub approach_m: f64,
    /// Rotation about the needle axis once grasped, rad.
    pub rotation_rad: f64,
    /// Recovery condition: an endpoint travel below this is retried, m.
    pub min_travel_m: f64,
    /// The final linear pull, m.
    pub pull_m: f64,
}
impl Default for ExtractParams {
    fn default() -> Self {
        Self {
            retries: EXTRACT_RETRIES,
            offset_m: EXTRACT_OFFSET_M,
            approach_m: EXTRACT_APPROACH_M,
            rotation_rad: EXTRACT_ROTATION_RAD,
            min_travel_m: EXTRACT_MIN_TRAVEL_M,
            pull_m: EXTRACT_PULL_M,
        }
    }
}

/// `cinch(#{ .. })`: the left PSM pulls β = l_des − (i − 1)·l_each of thread for suture i.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CinchParams {
    /// l_des, m.
    pub l_des_m: f64,
    /// l_each, m.
    pub l_each_m: f64,
    /// The clearing push after the pull, the thread hung vertical from the swage over the last
    /// stitch: how far past that vertical the right jaw pushes it, m (0: none, the paper's
    /// cinch).
    #[serde(default)]
    pub clear_m: f64,
}
impl Default for CinchParams {
    fn default() -> Self {
        Self {
            l_des_m: CINCH_L_DES_M,
            l_each_m: CINCH_L_EACH_M,
            clear_m: 0.0,
        }
    }
}
impl CinchParams {
    /// β for suture `i` (1-based), m.
    pub fn beta_m(&self, suture: usize) -> f64 {
        self.l_des_m - (suture.saturating_sub(1) as f64) * self.l_each_m
    }
}

/// `handover(#{ .. })`: right PSM grasps the farther endpoint, the left releases.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct HandoverParams {
    /// Re-attempts while the needle normal does not change; the engine caps this at 5.
    pub retries: u8,
    /// Horizontal stand-off before the approach, m.
    pub offset_m: f64,
    /// Largest random horizontal offset on a re-attempt, m.
    pub jitter_m: f64,
    /// A normal change below this counts as "unchanged", rad.
    pub normal_tolerance_rad: f64,
    /// The test rotation after closing, rad.
    pub tug_rad: f64,
    /// How far in from the end the grasp is, along the arc, rad.
    pub inset_rad: f64,
    /// Before each grasp, the thread is traced and a re-attempt's random offset goes to the
    /// side of the grasp point where the closing blades stay clear of it by this much if the
    /// drawn side does not, m (0: no look, the paper's handover).
    #[serde(default)]
    pub thread_margin_m: f64,
}
impl Default for HandoverParams {
    fn default() -> Self {
        Self {
            retries: HANDOVER_RETRIES,
            offset_m: HANDOVER_OFFSET_M,
            jitter_m: HANDOVER_JITTER_M,
            normal_tolerance_rad: HANDOVER_NORMAL_TOLERANCE_RAD,
            tug_rad: HANDOVER_TUG_RAD,
            inset_rad: HANDOVER_INSET_RAD,
            thread_margin_m: HANDOVER_THREAD_MARGIN_M,
        }
    }
}

/// `correct(#{ .. })`: the right PSM takes the needle to the lower back right corner, aligns
/// the averaged normal with +y and rotates 90° about y.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CorrectParams {
    /// Normal samples averaged.
    pub samples: u32,
    /// Final rotation about +y, rad.
    pub final_rotation_rad: f64,
}
impl Default for CorrectParams {
    fn default() -> Self {
        Self {
            samples: CORRECT_SAMPLES,
            final_rotation_rad: CORRECT_FINAL_ROTATION_RAD,
        }
    }
}

/// `estimate_needle(#{ .. })`: a perception query that must see the needle before going on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct EstimateParams {
    /// Pose samples averaged.
    pub samples: u32,
    /// Retries after a perception dropout; the engine caps this at 5.
    pub retries: u8,
}
impl Default for EstimateParams {
    fn default() -> Self {
        Self {
            samples: ESTIMATE_SAMPLES,
            retries: PERCEPTION_RETRIES,
        }
    }
}

/// `track_thread(#{ .. })`: a perception query that must trace the thread before going on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrackThreadParams {
    /// Retries after a perception dropout; the engine caps this at 5.
    pub retries: u8,
}
impl Default for TrackThreadParams {
    fn default() -> Self {
        Self {
            retries: PERCEPTION_RETRIES,
        }
    }
}

/// One step of a throw: a primitive or a perception query, with its parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "primitive", rename_all = "snake_case")]
pub enum StepKind {
    /// Needle insertion.
    Insert(InsertParams),
    /// Thread sweeping.
    Sweep(SweepParams),
    /// Needle extraction.
    Extract(ExtractParams),
    /// Suture cinching.
    Cinch(CinchParams),
    /// Needle handover.
    Handover(HandoverParams),
    /// Needle pose correction.
    Correct(CorrectParams),
    /// Needle pose estimate (perception query).
    EstimateNeedle(EstimateParams),
    /// Thread trace (perception query).
    TrackThread(TrackThreadParams),
}

/// The primitive names scripts use, in the order of a throw.
pub const STEP_NAMES: [&str; 8] = [
    "insert",
    "sweep",
    "extract",
    "cinch",
    "handover",
    "correct",
    "estimate_needle",
    "track_thread",
];

impl StepKind {
    /// The name scripts and the journal use.
    pub fn name(&self) -> &'static str {
        match self {
            StepKind::Insert(_) => "insert",
            StepKind::Sweep(_) => "sweep",
            StepKind::Extract(_) => "extract",
            StepKind::Cinch(_) => "cinch",
            StepKind::Handover(_) => "handover",
            StepKind::Correct(_) => "correct",
            StepKind::EstimateNeedle(_) => "estimate_needle",
            StepKind::TrackThread(_) => "track_thread",
        }
    }

    /// The step with default parameters, by script name.
    pub fn default_for(name: &str) -> Option<StepKind> {
        Some(match name {
            "insert" => StepKind::Insert(InsertParams::default()),
            "sweep" => StepKind::Sweep(SweepParams::default()),
            "extract" => StepKind::Extract(ExtractParams::default()),
            "cinch" => StepKind::Cinch(CinchParams::default()),
            "handover" => StepKind::Handover(HandoverParams::default()),
            "correct" => StepKind::Correct(CorrectParams::default()),
            "estimate_needle" => StepKind::EstimateNeedle(EstimateParams::default()),
            "track_thread" => StepKind::TrackThread(TrackThreadParams::default()),
            _ => return None,
        })
    }

    /// The retries the plan asks for (before the engine's hard cap), if the step retries.
    pub fn retries(&self) -> Option<u8> {
        match self {
            StepKind::Extract(p) => Some(p.retries),
            StepKind::Handover(p) => Some(p.retries),
            StepKind::EstimateNeedle(p) => Some(p.retries),
            StepKind::TrackThread(p) => Some(p.retries),
            _ => None,
        }
    }

    /// Whether this step is a perception query rather than a motion.
    pub fn is_perception(&self) -> bool {
        matches!(self, StepKind::EstimateNeedle(_) | StepKind::TrackThread(_))
    }

    /// The parameters this step accepts, with their quantities and ranges.
    pub fn param_specs(&self) -> &'static [ParamSpec] {
        param_specs(self.name())
    }

    /// Read a parameter by script name, in SI units.
    pub fn get(&self, name: &str) -> Option<Value> {
        use Value::{Angle as A, Count as C, Length as L};
        Some(match (self, name) {
            (StepKind::Insert(p), "rotation") => A(p.rotation_rad),
            (StepKind::Insert(p), "push") => L(p.push_m),
            (StepKind::Insert(p), "standoff") => L(p.standoff_m),
            (StepKind::Insert(p), "samples") => C(i64::from(p.samples)),
            (StepKind::Sweep(p), "distance") => L(p.distance_m),
            (StepKind::Sweep(p), "jaw_open") => A(p.jaw_open_rad),
            (StepKind::Extract(p), "retries") => C(i64::from(p.retries)),
            (StepKind::Extract(p), "offset") => L(p.offset_m),
            (StepKind::Extract(p), "approach") => L(p.approach_m),
            (StepKind::Extract(p), "rotation") => A(p.rotation_rad),
            (StepKind::Extract(p), "min_travel") => L(p.min_travel_m),
            (StepKind::Extract(p), "pull") => L(p.pull_m),
            (StepKind::Cinch(p), "l_des") => L(p.l_des_m),
            (StepKind::Cinch(p), "l_each") => L(p.l_each_m),
            (StepKind::Cinch(p), "clear") => L(p.clear_m),
            (StepKind::Handover(p), "retries") => C(i64::from(p.retries)),
            (StepKind::Handover(p), "offset") => L(p.offset_m),
            (StepKind::Handover(p), "jitter") => L(p.jitter_m),
            (StepKind::Handover(p), "normal_tolerance") => A(p.normal_tolerance_rad),
            (StepKind::Handover(p), "tug") => A(p.tug_rad),
            (StepKind::Handover(p), "inset") => A(p.inset_rad),
            (StepKind::Handover(p), "thread_margin") => L(p.thread_margin_m),
            (StepKind::Correct(p), "samples") => C(i64::from(p.samples)),
            (StepKind::Correct(p), "final_rotation") => A(p.final_rotation_rad),
            (StepKind::EstimateNeedle(p), "samples") => C(i64::from(p.samples)),
            (StepKind::EstimateNeedle(p), "retries") => C(i64::from(p.retries)),
            (StepKind::TrackThread(p), "retries") => C(i64::from(p.retries)),
            _ => return None,
        })
    }

    /// Set a parameter by script name. The value's quantity must match the parameter's
    /// (the caller checks units and reports them); ranges are checked separately so that one
    /// place (the engine's validation) reports them with the script position. A negative
    /// count is refused here (no field could carry it to validation); a count too large for
    /// its field is saturated, so that it still reaches validation and is refused there.
    pub fn set(&mut self, name: &str, value: Value) -> Result<(), SetParamError> {
        use Value::{Angle as A, Count as C, Length as L};
        if let C(n) = value
            && n < 0
        {
            return Err(SetParamError::Negative {
                step: self.name(),
                param: name.to_string(),
                value: n,
            });
        }
        let sat8 = |n: i64| u8::try_from(n).unwrap_or(u8::MAX);
        let sat32 = |n: i64| u32::try_from(n).unwrap_or(u32::MAX);
        match (self, name, value) {
            (StepKind::Insert(p), "rotation", A(v)) => p.rotation_rad = v,
            (StepKind::Insert(p), "push", L(v)) => p.push_m = v,
            (StepKind::Insert(p), "standoff", L(v)) => p.standoff_m = v,
            (StepKind::Insert(p), "samples", C(v)) => p.samples = sat32(v),
            (StepKind::Sweep(p), "distance", L(v)) => p.distance_m = v,
            (StepKind::Sweep(p), "jaw_open", A(v)) => p.jaw_open_rad = v,
            (StepKind::Extract(p), "retries", C(v)) => p.retries = sat8(v),
            (StepKind::Extract(p), "offset", L(v)) => p.offset_m = v,
            (StepKind::Extract(p), "approach", L(v)) => p.approach_m = v,
            (StepKind::Extract(p), "rotation", A(v)) => p.rotation_rad = v,
            (StepKind::Extract(p), "min_travel", L(v)) => p.min_travel_m = v,
            (StepKind::Extract(p), "pull", L(v)) => p.pull_m = v,
            (StepKind::Cinch(p), "l_des", L(v)) => p.l_des_m = v,
            (StepKind::Cinch(p), "l_each", L(v)) => p.l_each_m = v,
            (StepKind::Cinch(p), "clear", L(v)) => p.clear_m = v,
            (StepKind::Handover(p), "retries", C(v)) => p.retries = sat8(v),
            (StepKind::Handover(p), "offset", L(v)) => p.offset_m = v,
            (StepKind::Handover(p), "jitter", L(v)) => p.jitter_m = v,
            (StepKind::Handover(p), "normal_tolerance", A(v)) => p.normal_tolerance_rad = v,
            (StepKind::Handover(p), "tug", A(v)) => p.tug_rad = v,
            (StepKind::Handover(p), "inset", A(v)) => p.inset_rad = v,
            (StepKind::Handover(p), "thread_margin", L(v)) => p.thread_margin_m = v,
            (StepKind::Correct(p), "samples", C(v)) => p.samples = sat32(v),
            (StepKind::Correct(p), "final_rotation", A(v)) => p.final_rotation_rad = v,
            (StepKind::EstimateNeedle(p), "samples", C(v)) => p.samples = sat32(v),
            (StepKind::EstimateNeedle(p), "retries", C(v)) => p.retries = sat8(v),
            (StepKind::TrackThread(p), "retries", C(v)) => p.retries = sat8(v),
            (step, name, _) => {
                return Err(SetParamError::NoSuchParam {
                    step: step.name(),
                    param: name.to_string(),
                });
            }
        }
        Ok(())
    }
}

/// Why a parameter cannot be set.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum SetParamError {
    /// A parameter name a step does not have, or a value of the wrong quantity.
    #[error("{step} has no parameter `{param}` of that kind")]
    NoSuchParam {
        /// The step's script name.
        step: &'static str,
        /// The parameter asked for.
        param: String,
    },
    /// A count below zero.
    #[error("{step}: `{param}` is a count and cannot be negative, found {value}")]
    Negative {
        /// The step's script name.
        step: &'static str,
        /// The parameter.
        param: String,
        /// The value given.
        value: i64,
    },
}

const LENGTH_MAX_M: f64 = 0.10;

/// The parameters of the step called `name` in scripts (empty for an unknown name).
pub fn param_specs(name: &str) -> &'static [ParamSpec] {
    const INSERT: &[ParamSpec] = &[
        spec!(
            "rotation",
            Angle,
            deg(10.0),
            deg(120.0),
            "rotation about the estimated needle normal"
        ),
        spec!(
            "push",
            Length,
            0.0005,
            0.02,
            "straight push of the tip along entry→exit"
        ),
        spec!(
            "standoff",
            Length,
            0.002,
            0.03,
            "stand-off of the tip from the entry before it goes in"
        ),
        spec!(
            "samples",
            Count,
            0.0,
            20.0,
            "fresh needle pose estimates averaged right before inserting (0: the correction's)"
        ),
    ];
    const SWEEP: &[ParamSpec] = &[
        spec!(
            "distance",
            Length,
            0.005,
            LENGTH_MAX_M,
            "travel of the open jaw along +y"
        ),
        spec!(
            "jaw_open",
            Angle,
            deg(20.0),
            deg(80.0),
            "jaw opening during the sweep"
        ),
    ];
    const EXTRACT: &[ParamSpec] = &[
        spec!(
            "retries",
            Count,
            0.0,
            5.0,
            "retries while the endpoint moved less than min_travel"
        ),
        spec!(
            "offset",
            Length,
            0.002,
            0.03,
            "horizontal stand-off from the re-grasp point"
        ),
        spec!(
            "approach",
            Length,
            0.002,
            0.03,
            "approach towards the re-grasp point"
        ),
        spec!(
            "rotation",
            Angle,
            deg(20.0),
            deg(120.0),
            "rotation about the needle axis"
        ),
        spec!(
            "min_travel",
            Length,
            0.002,
            0.05,
            "endpoint travel below which extraction is retried"
        ),
        spec!("pull", Length, 0.005, 0.06, "final linear pull away and up"),
    ];
    const CINCH: &[ParamSpec] = &[
        spec!(
            "l_des",
            Length,
            0.01,
            0.40,
            "thread pulled for the first suture (β for i = 1)"
        ),
        spec!("l_each", Length, 0.0, 0.10, "thread one suture uses"),
        spec!(
            "clear",
            Length,
            0.0,
            0.05,
            "then, the thread hung vertical from the swage over the last stitch, the right jaw pushes it this far past the vertical (0: no push)"
        ),
    ];
    const HANDOVER: &[ParamSpec] = &[
        spec!(
            "retries",
            Count,
            0.0,
            5.0,
            "re-attempts while the needle normal did not change"
        ),
        spec!(
            "offset",
            Length,
            0.002,
            0.03,
            "horizontal stand-off from the re-grasp point"
        ),
        spec!(
            "jitter",
            Length,
            0.0,
            0.005,
            "largest random horizontal offset on a re-attempt"
        ),
        spec!(
            "normal_tolerance",
            Angle,
            deg(0.1),
            deg(20.0),
            "a normal change below this is \"unchanged\""
        ),
        spec!(
            "tug",
            Angle,
            deg(5.0),
            deg(45.0),
            "test rotation after closing"
        ),
        spec!(
            "inset",
            Angle,
            deg(0.0),
            deg(60.0),
            "grasp this far in from the end, along the arc"
        ),
        spec!(
            "thread_margin",
            Length,
            0.0,
            0.01,
            "before each grasp, keep the blades this clear of the traced thread (0: no look)"
        ),
    ];
    const CORRECT: &[ParamSpec] = &[
        spec!(
            "samples",
            Count,
            1.0,
            100.0,
            "normal samples averaged at the corner"
        ),
        spec!(
            "final_rotation",
            Angle,
            deg(-180.0),
            deg(180.0),
            "final rotation about +y"
        ),
    ];
    const ESTIMATE: &[ParamSpec] = &[
        spec!("samples", Count, 1.0, 100.0, "pose samples averaged"),
        spec!(
            "retries",
            Count,
            0.0,
            5.0,
            "retries after a perception dropout"
        ),
    ];
    const TRACK: &[ParamSpec] = &[spec!(
        "retries",
        Count,
        0.0,
        5.0,
        "retries after a perception dropout"
    )];
    match name {
        "insert" => INSERT,
        "sweep" => SWEEP,
        "extract" => EXTRACT,
        "cinch" => CINCH,
        "handover" => HANDOVER,
        "correct" => CORRECT,
        "estimate_needle" => ESTIMATE,
        "track_thread" => TRACK,
        _ => &[],
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_default_lies_within_its_range() {
        for name in STEP_NAMES {
            let step = StepKind::default_for(name).expect("known name");
            for spec in step.param_specs() {
                let v = match step.get(spec.name).expect("spec names a real parameter") {
                    Value::Length(v) | Value::Angle(v) => v,
                    Value::Count(n) => n as f64,
                };
                assert!(spec.range.contains(v), "{name}.{} = {v}", spec.name);
            }
        }
    }

    #[test]
    fn set_then_get_round_trips_and_rejects_wrong_quantities() {
        let mut s = StepKind::default_for("extract").expect("known");
        s.set("retries", Value::Count(3)).expect("count");
        assert_eq!(s.get("retries"), Some(Value::Count(3)));
        s.set("retries", Value::Count(900)).expect("saturates");
        assert_eq!(s.get("retries"), Some(Value::Count(255)));
        assert!(s.set("retries", Value::Length(0.01)).is_err());
        assert!(s.set("retires", Value::Count(1)).is_err());
    }

    #[test]
    fn beta_follows_the_papers_formula() {
        let c = CinchParams {
            l_des_m: 0.12,
            l_each_m: 0.02,
            clear_m: 0.0,
        };
        assert!((c.beta_m(1) - 0.12).abs() < 1e-12);
        assert!((c.beta_m(6) - 0.02).abs() < 1e-12);
    }
}
