//! The six primitives over the `robot/` traits and a needle estimator, with the paper's
//! geometry ("Augmented Dexterity Suturing Motion Controller"). The same code drives the mock
//! dVRK and a real one.
//!
//! Frames and conventions: the robot frame has +z up and +y towards the camera; the wound runs
//! along +y; the right driver (PSM1) inserts from the entry towards the exit, the left (PSM2)
//! extracts. A tool frame's +z points from the wrist to the jaw tip; the blades lie along −z
//! from the tip. The needle frame is `stitch_robot::Needle`'s: centre at the origin, normal
//! +z, tip at +x·r, swage at −x·r, the arc through +y·r.

use crate::{
    CinchParams, Control, CorrectParams, ExtractParams, Failure, FailureKind, HandoverParams,
    InsertParams, Measurements, NeedleAt, NeedleSeen, Observation, ObserveRequest, PrimitiveError,
    Primitives, StepControl, StepKind, StepOutcome, StepRequest, SweepParams, ThreadSeen,
};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use std::sync::Arc;
use stitch_perception::{
    JawHint, NeedleEnd, NeedleEstimate, NeedleEstimator, NeedleHint, PerceptionError, TissueHint,
};
use stitch_robot::nalgebra::{Rotation3, Translation3, Unit, UnitQuaternion};
use stitch_robot::{
    Arm, JAW_CLOSED_RAD, JAW_OPEN_RAD, Jaw, MoveHandle, Needle, Point, Pose, RobotError, Vector,
    WoundPoint,
};

/// Rotations are streamed as move_cp waypoints this far apart, so the tool follows the arc
/// closely (chord error r·(1 − cos 2.5°) ≈ 0.01 mm for the 12 mm needle), rad.
pub const ROTATION_STEP_RAD: f64 = 5.0 * std::f64::consts::PI / 180.0;
/// A primitive waits up to this many estimator cycles for a needle estimate before it
/// reports a perception dropout (the paper's estimator ran continuously at 0.67 Hz;
/// modelling choice: 3 cycles, 4.5 s).
pub const ESTIMATE_TRIES: usize = 3;
/// The longest a primitive waits for one motion to finish before it reports an arm fault
/// (modelling choice: the slowest move of the workspace at the mock's 2 cm/s is about 10 s).
pub const MOTION_TIMEOUT: std::time::Duration = std::time::Duration::from_secs(30);
/// How far a driver backs off after letting go or after a failed grasp (modelling choice), m.
pub const RETREAT_M: f64 = 0.02;
/// A needle driver's blade length (dVRK large needle driver: about 9 mm), m.
pub const BLADE_LENGTH_M: f64 = 0.009;
/// The wound's top above its holes, where a sweep's blades run (modelling choice, the mock's
/// phantom: 4 mm), m.
const SWEEP_TOP_ABOVE_HOLE_M: f64 = 0.004;
/// How far above the wound's top the open blades' tips run in a sweep (modelling choice), m.
const SWEEP_CLEARANCE_M: f64 = 0.0003;
/// How far before the stitch, along the sweep, it starts (modelling choice), m.
const SWEEP_BEHIND_M: f64 = 0.005;
/// How far a sweep backs off from the thread it pushed before lifting (modelling choice), m.
const SWEEP_BACK_OFF_M: f64 = 0.005;

/// Where a cinch's clearing push starts, on the right jaw's side of the swage (modelling
/// choice), m.
const CLEAR_START_M: f64 = 0.015;
/// The clearing push runs at least this far below the swage (modelling choice), m.
const CLEAR_BELOW_SWAGE_M: f64 = 0.02;
/// The clearing push's least height above the tissue (modelling choice), m.
const CLEAR_ABOVE_TISSUE_M: f64 = 0.006;
/// The swage's least height above the tissue while the thread hangs for the push, room for
/// the jaw under the needle's arc (modelling choice), m.
const CLEAR_SWAGE_ABOVE_TISSUE_M: f64 = 0.03;

/// The longest pull a cinch makes in one motion (modelling choice: a PSM's comfortable reach
/// above the phantom), m.
pub const CINCH_MAX_PULL_M: f64 = 0.15;

/// What an observer of the real scene can tell that the robot's sensors cannot: the
/// Surgical Robotics Challenge-style score of a needle pass, and problems such as a dropped
/// needle or tangled thread. The mock dVRK implements it from its ground truth; on a real
/// robot it is absent (or a person's report).
pub trait Observer: Send {
    /// An insertion begins: start watching the tip.
    fn begin_pass(&mut self);
    /// The insertion ended: how the tip went through `point`'s holes.
    fn end_pass(&mut self, point: &WoundPoint) -> PassObservation;
    /// A problem the scene shows now, if any: a dropped needle, thread caught, tangled or
    /// short.
    fn problem(&mut self) -> Option<FailureKind>;
    /// Whether the needle is still in the tissue.
    fn needle_in_tissue(&mut self) -> bool;
    /// A cinch left `beta_m` of free thread.
    fn cinched(&mut self, beta_m: f64);
    /// Thread not yet used in sutures nor pulled free, m (NaN where it cannot tell: then it is
    /// not measured, and the observer says why as a problem).
    fn thread_left_m(&mut self) -> f64;
}

/// How a needle pass went.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PassObservation {
    /// Lateral offset at the entry hole, m.
    pub entry_error_m: Option<f64>,
    /// Lateral offset at the exit hole, m.
    pub exit_error_m: Option<f64>,
    /// Tip beyond the exit plane, m.
    pub protrusion_m: f64,
    /// Whether every criterion passed.
    pub passed: bool,
}

/// Where the primitives go in the workspace, robot frame, m.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Layout {
    /// The lower back right corner where the needle pose is corrected ("Needle Pose
    /// Correction": chosen for consistent estimates).
    pub correction_point: Point,
    /// Where the left driver waits between extractions ("the upper left edge of the
    /// workspace").
    pub left_ready: Point,
    /// Where the left driver presents the needle for handover.
    pub handover_point: Point,
    /// Where the right driver waits out of the camera's view of the wound while the left
    /// extracts (modelling choice: its start).
    pub right_ready: Point,
}

/// The robot the primitives act on.
pub struct Rig {
    /// PSM1, the right needle driver.
    pub right: Arc<dyn Arm>,
    /// PSM2, the left needle driver.
    pub left: Arc<dyn Arm>,
    /// PSM1's jaw.
    pub right_jaw: Arc<dyn Jaw>,
    /// PSM2's jaw.
    pub left_jaw: Arc<dyn Jaw>,
    /// The needle pose estimator.
    pub estimator: Box<dyn NeedleEstimator>,
    /// What the scene shows, where something can tell (the mock's ground truth).
    pub observer: Option<Box<dyn Observer>>,
    /// The needle's shape.
    pub needle: Needle,
    /// Where things happen.
    pub layout: Layout,
    /// Random offsets (handover jitter), from the seed's primitives stream.
    pub rng: ChaCha8Rng,
}

impl std::fmt::Debug for Rig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Rig")
            .field("needle", &self.needle)
            .field("layout", &self.layout)
            .finish_non_exhaustive()
    }
}

/// The primitives over a [`Rig`].
#[derive(Debug)]
pub struct RobotPrimitives {
    rig: Rig,
    /// The needle in the right tool's frame, as the last pose correction measured it: the
    /// next insertion uses it open loop, as the paper does.
    corrected_grasp: Option<Pose>,
    /// The wound point the needle last went into (where extraction finds it).
    last_point: Option<WoundPoint>,
    /// The one before it: the stitch already made, the side a sweep pushes the thread to.
    previous_point: Option<WoundPoint>,
    /// The latest needle estimate any step or condition obtained (a condition's age reads it).
    last_estimate: Option<NeedleEstimate>,
    /// The end the left jaw grasped at the last extraction.
    left_end: NeedleEnd,
    /// Where the swage sat in the left tool's frame when the last extraction ended (from its
    /// last needle estimate): a cinch's clearing push finds the hanging thread from it.
    left_swage: Option<Point>,
    /// Why the estimator gave no estimate, each cycle of the current step it gave none.
    unseen: Vec<String>,
    /// Where the free thread leaves the suture line: the exit of the last stitch the needle
    /// was drawn out of (none before the first).
    thread_from: Option<Point>,
}

/// Why a step stops before its end: it failed (boxed: a failure carries its measurements), or
/// the supervisor ended it.
#[derive(Debug)]
enum Halt {
    Failed(Box<Failure>),
    Interrupted,
}

impl Halt {
    fn with(kind: FailureKind, measured: Measurements) -> Self {
        Halt::Failed(Box::new(Failure { kind, measured }))
    }
}

/// A step that cannot go on, and why.
type Step<T> = Result<T, Halt>;

fn fault(e: RobotError) -> Halt {
    failed(FailureKind::ArmFault {
        message: e.to_string(),
    })
}

/// Stop every motion and hold both arms; every refusal is said.
fn hold_both(right: &dyn Arm, left: &dyn Arm) -> Result<(), PrimitiveError> {
    // Both are told to hold whatever the other answered.
    let failed: Vec<String> = [right.hold(), left.hold()]
        .into_iter()
        .filter_map(|r| r.err().map(|e| e.to_string()))
        .collect();
    if failed.is_empty() {
        Ok(())
    } else {
        Err(PrimitiveError::Robot {
            message: failed.join("; "),
        })
    }
}

/// One motion a primitive commands, so that it can be commanded again after a pause.
#[derive(Clone, Copy, Debug)]
enum Motion {
    Arm(Hand, Pose),
    Jaw(Hand, f64),
}

/// Which arm, for perception hints.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Hand {
    Right,
    Left,
}

/// The right jaw drives the needle holding it near the swage (the paper's grasp for
/// insertion, and where the handover puts it back).
const RIGHT_AT_SWAGE: Option<(Hand, NeedleEnd)> = Some((Hand::Right, NeedleEnd::Swage));

fn failed(kind: FailureKind) -> Halt {
    Halt::with(kind, Measurements::default())
}

/// The hint for a needle held by a jaw at `jaw`, nearer `end`.
fn held_at(jaw: Point, end: NeedleEnd) -> NeedleHint {
    NeedleHint::Held(JawHint { jaw, end })
}

/// A pose at `p` with rotation `r`.
fn pose(p: Point, r: UnitQuaternion<f64>) -> Pose {
    Pose::from_parts(Translation3::from(p.coords), r)
}

/// `t` moved by `v` (robot frame).
fn shifted(t: &Pose, v: Vector) -> Pose {
    Pose::from_parts(Translation3::from(t.translation.vector + v), t.rotation)
}

/// `t` rotated by `angle` about the axis through `center` along `axis` (robot frame).
pub fn rotated_about(t: &Pose, center: &Point, axis: &Vector, angle: f64) -> Pose {
    let Some(axis) = Unit::try_new(*axis, 1e-12) else {
        return *t;
    };
    let r = UnitQuaternion::from_axis_angle(&axis, angle);
    let p = center + r * (Point::from(t.translation.vector) - center);
    pose(p, r * t.rotation)
}

/// The horizontal unit vector along `v`, if it has a horizontal part.
fn horizontal(v: Vector) -> Option<Vector> {
    Vector::new(v.x, v.y, 0.0).try_normalize(1e-9)
}

/// A tool orientation whose jaw points along `dir` (tool +z = `dir`), blades level.
fn pointing(dir: &Vector) -> UnitQuaternion<f64> {
    let z = dir.normalize();
    let x = Vector::z()
        .cross(&z)
        .try_normalize(1e-9)
        .unwrap_or_else(Vector::x);
    let y = z.cross(&x);
    UnitQuaternion::from_rotation_matrix(&Rotation3::from_basis_unchecked(&[x, y, z]))
}

/// The needle pose that starts an insertion at `entry` towards `exit`: tip at the entry,
/// the needle leading with its tip along entry→exit (horizontally; the tip leads along the
/// needle frame's −y), the centre one radius above. For a wound along +x its normal is +y,
/// as pose correction leaves it.
pub fn insertion_start(needle: &Needle, entry: &Point, exit: &Point) -> Pose {
    let u = horizontal(exit - entry).unwrap_or_else(Vector::x);
    let up = Vector::z();
    let x = -up;
    let y = -u;
    let z = x.cross(&y);
    let r = UnitQuaternion::from_rotation_matrix(&Rotation3::from_basis_unchecked(&[x, y, z]));
    pose(entry + up * needle.radius_m, r)
}

/// The tool poses of an insertion, in order: the stand-off, the start (tip at the entry), the
/// end of the push, then the rotation's waypoints. `grasp` is the needle in the tool frame.
pub fn insertion_waypoints(
    needle: &Needle,
    grasp: &Pose,
    point: &WoundPoint,
    p: &InsertParams,
) -> Vec<Pose> {
    let start = insertion_start(needle, &point.entry, &point.exit) * grasp.inverse();
    let u = horizontal(point.exit - point.entry).unwrap_or_else(Vector::x);
    let standoff = shifted(
        &start,
        -u * p.standoff_m + Vector::z() * (p.standoff_m / 2.0),
    );
    let pushed = shifted(&start, u * p.push_m);
    let needle_pushed = pushed * grasp;
    let center = needle_pushed * Point::origin();
    let normal = needle_pushed * Vector::z();
    let steps = (p.rotation_rad.abs() / ROTATION_STEP_RAD).ceil().max(1.0) as usize;
    let mut out = vec![standoff, start, pushed];
    // The tip leads along −y of the needle frame, so driving it forward along its arc is a
    // rotation about the normal by −angle.
    out.extend((1..=steps).map(|k| {
        rotated_about(
            &pushed,
            &center,
            &normal,
            -p.rotation_rad * k as f64 / steps as f64,
        )
    }));
    out
}

/// The left driver's poses for an extraction grasp: the stand-off (`offset` horizontally from
/// the re-grasp point, on the driver's side) and the end of the approach (`approach` towards
/// and past it), jaw pointing at it.
pub fn regrasp_waypoints(
    regrasp: &Point,
    from: &Point,
    offset_m: f64,
    approach_m: f64,
) -> [Pose; 2] {
    let h = horizontal(from - regrasp).unwrap_or_else(Vector::x);
    let rot = pointing(&-h);
    let off = regrasp + h * offset_m;
    [pose(off, rot), pose(off - h * approach_m, rot)]
}

impl RobotPrimitives {
    /// Primitives over `rig`.
    pub fn new(rig: Rig) -> Self {
        Self {
            rig,
            corrected_grasp: None,
            last_point: None,
            thread_from: None,
            previous_point: None,
            last_estimate: None,
            left_end: NeedleEnd::Tip,
            left_swage: None,
            unseen: Vec::new(),
        }
    }

    /// The rig.
    pub fn rig(&self) -> &Rig {
        &self.rig
    }

    /// The same primitives over `f(rig)`: its arms, jaws or estimator wrapped (a recorder's
    /// tap), before anything runs.
    pub fn map_rig(self, f: impl FnOnce(Rig) -> Rig) -> Self {
        Self {
            rig: f(self.rig),
            ..self
        }
    }

    /// Ask the control whether to go on; when it says so, both arms hold first.
    fn heed(&self, c: &mut dyn StepControl) -> Control {
        let (right, left) = (&self.rig.right, &self.rig.left);
        c.check(&mut || hold_both(&**right, &**left))
    }

    /// Between two things a step does that are not motions (estimator cycles): go on, or stop
    /// if the supervisor ended the step. A pause here holds, waits, and goes on.
    fn go_on(&self, c: &mut dyn StepControl) -> Step<()> {
        match self.heed(c) {
            Control::Go | Control::Resumed => Ok(()),
            Control::Stop => Err(Halt::Interrupted),
        }
    }

    fn command(&self, m: Motion) -> Result<MoveHandle, RobotError> {
        match m {
            Motion::Arm(Hand::Right, p) => self.rig.right.move_cp(&p),
            Motion::Arm(Hand::Left, p) => self.rig.left.move_cp(&p),
            Motion::Jaw(Hand::Right, a) => self.rig.right_jaw.move_jp(a),
            Motion::Jaw(Hand::Left, a) => self.rig.left_jaw.move_jp(a),
        }
    }

    /// Command a motion and wait for it to end, at most [`MOTION_TIMEOUT`], asking the control
    /// every slice whether to go on: a pause holds the arms, waits, and commands the motion
    /// again from where it stopped; a take-over, abort or e-stop holds them and ends the step.
    /// A robot error or a timeout is an arm fault.
    fn motion(&self, c: &mut dyn StepControl, m: Motion) -> Step<()> {
        let mut handle = self.command(m).map_err(fault)?;
        let mut waited = std::time::Duration::ZERO;
        loop {
            if handle.is_busy() {
                let left = MOTION_TIMEOUT.saturating_sub(waited);
                let slice = c.slice().filter(|s| *s < left);
                match handle.wait(slice.unwrap_or(left)) {
                    Ok(()) => {}
                    // A slice ended with the motion under way: ask, then wait on.
                    Err(RobotError::Timeout { .. }) if slice.is_some() => {
                        waited += slice.unwrap_or_default();
                    }
                    Err(e) => return Err(fault(e)),
                }
            }
            match self.heed(c) {
                Control::Go if !handle.is_busy() => return Ok(()),
                Control::Go => {}
                Control::Resumed => {
                    handle = self.command(m).map_err(fault)?;
                    waited = std::time::Duration::ZERO;
                }
                Control::Stop => return Err(Halt::Interrupted),
            }
        }
    }

    /// Move `hand`'s arm through `poses` in order, each waited on.
    fn go(&self, c: &mut dyn StepControl, hand: Hand, poses: &[Pose]) -> Step<()> {
        for p in poses {
            self.motion(c, Motion::Arm(hand, *p))?;
        }
        Ok(())
    }

    /// Move `hand`'s jaw to `angle_rad`, waited on.
    fn jaw(&self, c: &mut dyn StepControl, hand: Hand, angle_rad: f64) -> Step<()> {
        self.motion(c, Motion::Jaw(hand, angle_rad))
    }

    /// A needle estimate, waiting up to [`ESTIMATE_TRIES`] estimator cycles for one; `held`
    /// says which arm holds the needle nearer which end, if one does.
    fn estimate(
        &mut self,
        c: &mut dyn StepControl,
        held: Option<(Hand, NeedleEnd)>,
    ) -> Step<NeedleEstimate> {
        let hint = match held {
            Some((hand, end)) => Some(self.held_hint(hand, end)?),
            None => None,
        };
        self.estimate_with(c, hint)
    }

    /// Where the jaw of `hand` is, holding the needle nearer `end`. An arm that cannot say
    /// where it is (a stale or failed `measured_cp`) stops the step as an arm fault: the
    /// estimate is never made without the jaw it was meant to use.
    fn held_hint(&self, hand: Hand, end: NeedleEnd) -> Step<NeedleHint> {
        let arm = match hand {
            Hand::Right => &self.rig.right,
            Hand::Left => &self.rig.left,
        };
        let p = arm.measured_cp().map_err(fault)?;
        Ok(held_at(Point::from(p.translation.vector), end))
    }

    /// One estimator cycle: an estimate, or none this cycle (nothing seen, too uncertain:
    /// the reason is kept for the step's measurements); a camera that fails (no frames,
    /// unusable images) is a fault of the robot, not a needle out of sight, and stops the
    /// step. The supervisor is heard before each cycle.
    fn sample(
        &mut self,
        c: &mut dyn StepControl,
        hint: Option<&NeedleHint>,
    ) -> Step<Option<NeedleEstimate>> {
        self.go_on(c)?;
        match self.rig.estimator.estimate_needle_with(hint) {
            Ok(e) => {
                self.last_estimate = Some(e);
                Ok(Some(e))
            }
            Err(PerceptionError::Camera { message }) => Err(failed(FailureKind::ArmFault {
                message: format!("perception: {message}"),
            })),
            // A segmentation model that cannot run is as much a fault as a failing camera.
            Err(e @ PerceptionError::Model { .. }) => Err(failed(FailureKind::ArmFault {
                message: format!("perception: {e}"),
            })),
            Err(e) => {
                self.unseen.push(e.to_string());
                Ok(None)
            }
        }
    }

    /// A needle estimate with this hint, waiting up to [`ESTIMATE_TRIES`] cycles.
    fn estimate_with(
        &mut self,
        c: &mut dyn StepControl,
        hint: Option<NeedleHint>,
    ) -> Step<NeedleEstimate> {
        for _ in 0..ESTIMATE_TRIES {
            if let Some(e) = self.sample(c, hint.as_ref())? {
                return Ok(e);
            }
        }
        // Where an observer can tell why nothing is seen (the needle fell), say that.
        Err(failed(
            self.problem().unwrap_or(FailureKind::PerceptionDropout),
        ))
    }

    fn problem(&mut self) -> Option<FailureKind> {
        self.rig.observer.as_mut().and_then(|o| o.problem())
    }

    /// Insertion. Commit point: the right jaw opening to let go of the needle in the tissue.
    fn insert(
        &mut self,
        c: &mut dyn StepControl,
        point: &WoundPoint,
        p: &InsertParams,
    ) -> Step<Measurements> {
        if self.last_point.as_ref() != Some(point) {
            self.previous_point = self.last_point.replace(point.clone());
        }
        let tool = self.rig.right.measured_cp().map_err(fault)?;
        let corrected = self.corrected_grasp.take();
        let grasp = match corrected {
            Some(g) if p.samples == 0 => g,
            _ => {
                // Average the fresh estimates of the needle in the jaw (positions by mean,
                // rotations by the normalised quaternion sum); one must come.
                let mut grasps = vec![tool.inverse() * self.estimate(c, RIGHT_AT_SWAGE)?.pose];
                let hint = self.held_hint(Hand::Right, NeedleEnd::Swage)?;
                for _ in 1..p.samples.max(1) {
                    if let Some(e) = self.sample(c, Some(&hint))? {
                        grasps.push(tool.inverse() * e.pose);
                    }
                }
                mean_pose(&grasps)
            }
        };
        let waypoints = insertion_waypoints(&self.rig.needle, &grasp, point, p);
        let pushed = self.go(c, Hand::Right, &waypoints[..1]).and_then(|()| {
            if let Some(o) = self.rig.observer.as_mut() {
                o.begin_pass();
            }
            self.go(c, Hand::Right, &waypoints[1..])
        });
        if let Err(e) = pushed {
            // Stopped by the supervisor before the needle was let go: a re-run after the
            // hand-back inserts with the same corrected grasp.
            if matches!(e, Halt::Interrupted) {
                self.corrected_grasp = corrected;
            }
            return Err(e);
        }
        c.commit();
        self.jaw(c, Hand::Right, JAW_OPEN_RAD)?;
        let last = waypoints.last().copied().unwrap_or(tool);
        self.go(c, Hand::Right, &[shifted(&last, Vector::z() * RETREAT_M)])?;
        let mut measured = Measurements::default();
        if let Some(o) = self.rig.observer.as_mut() {
            let pass = o.end_pass(point);
            measured.entry_error_m = pass.entry_error_m;
            measured.exit_error_m = pass.exit_error_m;
            measured.thread_left_m = Some(o.thread_left_m()).filter(|m| m.is_finite());
            if let Some(kind) = o.problem() {
                return Err(Halt::with(kind, measured));
            }
            if !pass.passed {
                return Err(Halt::with(FailureKind::Missed, measured));
            }
        }
        Ok(measured)
    }

    /// Thread sweep. No commit point: a sweep run again sweeps again.
    fn sweep(
        &mut self,
        c: &mut dyn StepControl,
        point: &WoundPoint,
        p: &SweepParams,
    ) -> Step<Measurements> {
        let mid = Point::from((point.entry.coords + point.exit.coords) / 2.0);
        // Wide open across the wound, a broom: the blades spread across it (tool y along the
        // wound's across direction), their tips just above the wound's top, from a little
        // behind the stitch so that thread draped over the wound at the stitch goes ahead.
        let across = horizontal(point.exit - point.entry).unwrap_or_else(Vector::x);
        let down = -Vector::z();
        let x = across.cross(&down);
        let broom = UnitQuaternion::from_rotation_matrix(&Rotation3::from_basis_unchecked(&[
            x, across, down,
        ]));
        let lift = SWEEP_TOP_ABOVE_HOLE_M - BLADE_LENGTH_M * (1.0 - (p.jaw_open_rad / 2.0).cos())
            + SWEEP_CLEARANCE_M;
        // Towards the stitch already made (the thread runs back to it), from a little beyond
        // this one; the first throw, towards the wound's start.
        let along = self
            .previous_point
            .as_ref()
            .and_then(|prev| horizontal(prev.exit - point.exit))
            .unwrap_or(-Vector::y());
        let start = pose(mid + along * -SWEEP_BEHIND_M + Vector::z() * lift, broom);
        self.jaw(c, Hand::Right, p.jaw_open_rad)?;
        self.go(
            c,
            Hand::Right,
            &[start, shifted(&start, along * p.distance_m)],
        )?;
        // Back off from the thread pushed ahead of the blades, then lift clear of it, before
        // closing the jaw: lifting straight away would carry thread lying against the blades.
        let back = shifted(&start, along * (p.distance_m - SWEEP_BACK_OFF_M));
        let end = shifted(&back, Vector::z() * RETREAT_M);
        self.go(c, Hand::Right, &[back, end])?;
        self.jaw(c, Hand::Right, JAW_CLOSED_RAD)?;
        match self.problem() {
            Some(kind) => Err(failed(kind)),
            None => Ok(Measurements::default()),
        }
    }

    /// Extraction. Commit point: the left jaw, closed on the needle, beginning to turn it out
    /// along its arc (from there, opening that jaw again may drop it).
    fn extract(&mut self, c: &mut dyn StepControl, p: &ExtractParams) -> Step<Measurements> {
        // Clear the camera's view of the wound: the right driver, just released from the
        // needle, would hide it.
        let right = self.rig.right.measured_cp().map_err(fault)?;
        if (Point::from(right.translation.vector) - self.rig.layout.right_ready).norm() > 0.005 {
            let ready = Pose::from_parts(
                Translation3::from(self.rig.layout.right_ready.coords),
                right.rotation,
            );
            self.go(c, Hand::Right, &[ready])?;
        }
        // The needle is in the tissue through the last wound point's holes, held by neither
        // jaw.
        let holes = self.last_point.as_ref().map(|wp| {
            NeedleHint::InTissue(TissueHint {
                entry: wp.entry,
                exit: wp.exit,
            })
        });
        let before = self.estimate_with(c, holes)?;
        let (center, normal, tip, swage) = before.features(&self.rig.needle);
        let left = self.rig.left.measured_cp().map_err(fault)?;
        let from = Point::from(left.translation.vector);
        let (regrasp, is_tip) = if (tip - from).norm() <= (swage - from).norm() {
            (tip, true)
        } else {
            (swage, false)
        };
        self.left_end = if is_tip {
            NeedleEnd::Tip
        } else {
            NeedleEnd::Swage
        };
        let [off, grasp] = regrasp_waypoints(&regrasp, &from, p.offset_m, p.approach_m);
        self.jaw(c, Hand::Left, JAW_OPEN_RAD)?;
        self.go(c, Hand::Left, &[off, grasp])?;
        self.jaw(c, Hand::Left, JAW_CLOSED_RAD)?;
        let steps = (p.rotation_rad.abs() / ROTATION_STEP_RAD).ceil().max(1.0) as usize;
        let turn: Vec<Pose> = (1..=steps)
            .map(|k| {
                rotated_about(
                    &grasp,
                    &center,
                    &normal,
                    -p.rotation_rad * k as f64 / steps as f64,
                )
            })
            .collect();
        c.commit();
        self.go(c, Hand::Left, &turn)?;
        let last = turn.last().copied().unwrap_or(grasp);
        let away = horizontal(from - regrasp).unwrap_or_else(Vector::x);
        let pull = (away + Vector::z()).normalize() * p.pull_m;
        self.go(c, Hand::Left, &[shifted(&last, pull)])?;
        // If no estimate comes, the left jaw keeps whatever it holds: the needle may be out.
        let after = self.estimate(
            c,
            Some((
                Hand::Left,
                if is_tip {
                    NeedleEnd::Tip
                } else {
                    NeedleEnd::Swage
                },
            )),
        )?;
        let (_, _, tip2, swage2) = after.features(&self.rig.needle);
        let travel = if is_tip {
            (tip2 - tip).norm()
        } else {
            (swage2 - swage).norm()
        };
        let measured = Measurements {
            endpoint_travel_m: Some(travel),
            ..Measurements::default()
        };
        // Asked before the problems: an observer that cannot answer says so as a problem.
        let still_in = self
            .rig
            .observer
            .as_mut()
            .is_some_and(|o| o.needle_in_tissue());
        let problem = self.problem();
        if let Some(kind) = problem {
            return Err(Halt::with(kind, measured));
        }
        if still_in || travel < p.min_travel_m {
            // Let go and back off, ready for a retry.
            self.jaw(c, Hand::Left, JAW_OPEN_RAD)?;
            self.go(c, Hand::Left, &[off])?;
            let kind = if travel < p.min_travel_m {
                FailureKind::NoProgress
            } else {
                FailureKind::Missed
            };
            return Err(Halt::with(kind, measured));
        }
        self.thread_from = self.last_point.as_ref().map(|wp| wp.exit);
        let left = self.rig.left.measured_cp().map_err(fault)?;
        self.left_swage = Some(left.inverse() * swage2);
        Ok(measured)
    }

    /// Cinch. Commit point: the pull on the thread beginning (pulled twice, a suture is
    /// over-tightened).
    fn cinch(
        &mut self,
        c: &mut dyn StepControl,
        suture: usize,
        p: &CinchParams,
    ) -> Step<Measurements> {
        let beta = p.beta_m(suture).max(0.0);
        let tool = self.rig.left.measured_cp().map_err(fault)?;
        let here = Point::from(tool.translation.vector);
        let away =
            horizontal(here - self.rig.layout.handover_point).unwrap_or_else(|| -Vector::x());
        let pull = away * beta.min(CINCH_MAX_PULL_M);
        c.commit();
        self.go(c, Hand::Left, &[shifted(&tool, pull)])?;
        let mut measured = Measurements {
            thread_used_m: Some(beta),
            ..Measurements::default()
        };
        if let Some(o) = self.rig.observer.as_mut() {
            o.cinched(beta);
        }
        let present = pose(self.rig.layout.handover_point, tool.rotation);
        if p.clear_m > 0.0 {
            self.clear_thread(c, p.clear_m, present)?;
        } else {
            self.go(c, Hand::Left, &[present])?;
        }
        if let Some(o) = self.rig.observer.as_mut() {
            measured.thread_left_m = Some(o.thread_left_m()).filter(|m| m.is_finite());
        }
        match self.problem() {
            Some(kind) => Err(Halt::with(kind, measured)),
            None => Ok(measured),
        }
    }

    /// The paper's future work, a cinch before the handover ("the left gripper holds the
    /// needle at the handover position such that a portion of the thread would be vertical;
    /// the other gripper would then move horizontally to push the vertical thread component
    /// to pull out additional thread and clear it from the grasping workspace"). The left
    /// holds the needle at the handover height (higher if the swage would be less than 3 cm
    /// above the tissue) with its swage straight above the stitch the thread leaves, so the
    /// thread hangs vertical; the closed right jaw comes in below the
    /// needle from its own side and pushes it horizontally, `clear_m` past the swage's
    /// vertical; it backs off, lifts and goes back to its ready position, and the left brings
    /// the needle to `present`, the handover point. The swage is where the last extraction's
    /// estimate put it in the left jaw (no new perception query: a dropout here would end the
    /// cinch). Without a stitch to hang over (none known), the push runs straight below the
    /// swage at the handover point.
    fn clear_thread(&mut self, c: &mut dyn StepControl, clear_m: f64, present: Pose) -> Step<()> {
        let in_jaw = self.left_swage.unwrap_or_else(Point::origin);
        let at_present = present * in_jaw;
        // Raised where the swage would hang too low for the jaw to pass between the needle
        // and the tissue.
        let hold = match self.thread_from {
            Some(exit) => shifted(
                &present,
                Vector::new(
                    exit.x - at_present.x,
                    exit.y - at_present.y,
                    (exit.z + CLEAR_SWAGE_ABOVE_TISSUE_M - at_present.z).max(0.0),
                ),
            ),
            None => present,
        };
        self.go(c, Hand::Left, &[hold])?;
        let swage = hold * in_jaw;
        let right = self.rig.right.measured_cp().map_err(fault)?;
        let from_right =
            horizontal(Point::from(right.translation.vector) - swage).unwrap_or_else(Vector::x);
        // 40 % of the way up from the tissue to the swage, at least 2 cm below the swage
        // (under the needle's arc), and never less than 6 mm above the tissue.
        let tissue_z = self
            .thread_from
            .map_or(swage.z - 2.0 * CLEAR_BELOW_SWAGE_M, |e| e.z);
        let z = (tissue_z + 0.4 * (swage.z - tissue_z))
            .min(swage.z - CLEAR_BELOW_SWAGE_M)
            .max(tissue_z + CLEAR_ABOVE_TISSUE_M);
        let under = Point::new(swage.x, swage.y, z);
        let rot = right.rotation;
        let start = pose(under + from_right * CLEAR_START_M, rot);
        let end = pose(under - from_right * clear_m, rot);
        // Closed before it moves (a plan without a sweep leaves it open): a jaw closing near
        // the thread would catch it.
        self.jaw(c, Hand::Right, JAW_CLOSED_RAD)?;
        self.go(
            c,
            Hand::Right,
            &[shifted(&start, Vector::z() * RETREAT_M), start, end],
        )?;
        // Back off from the thread before lifting, as a sweep does: lifting at once would
        // carry thread lying against the jaw.
        let back = shifted(&end, from_right * SWEEP_BACK_OFF_M);
        let ready = pose(self.rig.layout.right_ready, rot);
        self.go(
            c,
            Hand::Right,
            &[back, shifted(&back, Vector::z() * RETREAT_M), ready],
        )?;
        self.go(c, Hand::Left, &[present])?;
        Ok(())
    }

    /// The free thread traced from where the last stitch left it to `swage`, or why it
    /// could not be (the thread hidden, not found); a failing camera or model, or a
    /// perception with no tracer, is a fault.
    fn trace_to(
        &mut self,
        c: &mut dyn StepControl,
        swage: Point,
    ) -> Step<Result<stitch_perception::ThreadTrace, PerceptionError>> {
        let hint = stitch_perception::ThreadHint {
            start: self.thread_from,
            swage,
            length_m: None,
        };
        self.go_on(c)?;
        match self.rig.estimator.trace_thread(&hint) {
            Err(
                e @ (PerceptionError::Camera { .. }
                | PerceptionError::Model { .. }
                | PerceptionError::Config { .. }),
            ) => Err(failed(FailureKind::ArmFault {
                message: format!("perception: {e}"),
            })),
            other => Ok(other),
        }
    }

    /// Handover. Commit point: the left jaw opening to let go of the needle the right jaw
    /// now holds.
    fn handover(
        &mut self,
        c: &mut dyn StepControl,
        attempt: u32,
        p: &HandoverParams,
    ) -> Step<Measurements> {
        let before = self.estimate(c, Some((Hand::Left, NeedleEnd::Tip)))?;
        let (_, n0, tip, swage) = before.features(&self.rig.needle);
        let left = Point::from(
            self.rig
                .left
                .measured_cp()
                .map_err(fault)?
                .translation
                .vector,
        );
        let right = Point::from(
            self.rig
                .right
                .measured_cp()
                .map_err(fault)?
                .translation
                .vector,
        );
        // The re-grasp point: near the endpoint farther from the left driver, a little way in
        // along the arc so the blades close on wire; approached across the needle's plane.
        let far_is_tip = (tip - left).norm() >= (swage - left).norm();
        let angle = if far_is_tip {
            p.inset_rad
        } else {
            std::f64::consts::PI - p.inset_rad
        };
        let regrasp = before.pose * self.rig.needle.point_at(angle);
        let h = horizontal(n0)
            .map(|n| {
                if n.dot(&(right - regrasp)) >= 0.0 {
                    n
                } else {
                    -n
                }
            })
            .or_else(|| horizontal(right - regrasp))
            .unwrap_or_else(Vector::x);
        let jitter = if attempt > 0 {
            let side = Vector::z().cross(&h);
            side * self.rig.rng.random_range(-p.jitter_m..=p.jitter_m)
        } else {
            Vector::zeros()
        };
        let mut target = regrasp + jitter;
        let mut measured = Measurements::default();
        // The look before the grasp (`thread_margin`): a thread that cannot be traced is said
        // and the offset left as drawn; the trace has nothing else to aim it by.
        let trace = if p.thread_margin_m > 0.0 {
            self.trace_to(c, swage)?
                .map_err(|e| self.unseen.push(format!("thread before the grasp: {e}")))
                .ok()
        } else {
            None
        };
        if let Some(trace) = trace {
            let (chosen, clearance) =
                grasp_clear_of_thread(&trace, regrasp, jitter, h, p.thread_margin_m);
            target = chosen;
            measured.thread_clearance_m = clearance;
        }
        let [off, at] = regrasp_waypoints(&target, &(target + h), p.offset_m, p.offset_m);
        self.jaw(c, Hand::Right, JAW_OPEN_RAD)?;
        self.go(c, Hand::Right, &[off, at])?;
        self.jaw(c, Hand::Right, JAW_CLOSED_RAD)?;
        // Tug: turn the right driver a little about a horizontal axis across its approach.
        let tug = rotated_about(&at, &target, &Vector::z().cross(&h), p.tug_rad);
        self.go(c, Hand::Right, &[tug])?;
        let after = self.estimate(c, RIGHT_AT_SWAGE)?;
        let n1 = after.features(&self.rig.needle).1;
        let change = n0.angle(&n1);
        measured.normal_change_rad = Some(change);
        if change <= p.normal_tolerance_rad {
            // The grasp did not take: let go, pull back.
            self.jaw(c, Hand::Right, JAW_OPEN_RAD)?;
            self.go(c, Hand::Right, &[off])?;
            return Err(Halt::with(FailureKind::NoProgress, measured));
        }
        c.commit();
        self.jaw(c, Hand::Left, JAW_OPEN_RAD)?;
        let ready = pose(self.rig.layout.left_ready, UnitQuaternion::identity());
        self.go(c, Hand::Left, &[ready])?;
        match self.problem() {
            Some(kind) => Err(Halt::with(kind, measured)),
            None => Ok(measured),
        }
    }

    /// Needle pose correction. No commit point: run again from anywhere, it moves the needle
    /// in free space to the corner and measures it anew.
    fn correct(&mut self, c: &mut dyn StepControl, p: &CorrectParams) -> Step<Measurements> {
        let tool = self.rig.right.measured_cp().map_err(fault)?;
        let first = self.estimate(c, RIGHT_AT_SWAGE)?;
        let center = first.pose * Point::origin();
        let to_corner = shifted(&tool, self.rig.layout.correction_point - center);
        self.go(c, Hand::Right, &[to_corner])?;
        // Average the samples: positions by mean, rotations by the normalised quaternion sum.
        let hint = self.held_hint(Hand::Right, NeedleEnd::Swage)?;
        let mut grasps = Vec::new();
        for _ in 0..p.samples.max(1) {
            if let Some(e) = self.sample(c, Some(&hint))? {
                grasps.push(to_corner.inverse() * e.pose);
            }
        }
        if grasps.is_empty() {
            return Err(failed(FailureKind::PerceptionDropout));
        }
        let grasp = mean_pose(&grasps);
        let needle = to_corner * grasp;
        let (cn, n) = (needle * Point::origin(), needle * Vector::z());
        let align = UnitQuaternion::rotation_between(&n, &Vector::y())
            .unwrap_or_else(UnitQuaternion::identity);
        let (axis, angle) = align
            .axis_angle()
            .map_or((Vector::y(), 0.0), |(a, t)| (a.into_inner(), t));
        let aligned = rotated_about(&to_corner, &cn, &axis, angle);
        let turned = rotated_about(&aligned, &cn, &Vector::y(), p.final_rotation_rad);
        self.go(c, Hand::Right, &[aligned, turned])?;
        self.corrected_grasp = Some(grasp);
        match self.problem() {
            Some(kind) => Err(failed(kind)),
            None => Ok(Measurements::default()),
        }
    }

    /// A perception query. No commit point: nothing moves.
    fn perceive(&mut self, c: &mut dyn StepControl, kind: &StepKind) -> Step<Measurements> {
        let mut measured = Measurements::default();
        match kind {
            StepKind::EstimateNeedle(p) => {
                for _ in 0..p.samples.max(1) {
                    self.estimate(c, None)?;
                }
            }
            StepKind::TrackThread(_) => {
                measured.thread_left_m = Some(self.track_thread(c)?.length_m);
            }
            _ => {}
        }
        match self.problem() {
            Some(kind) => Err(Halt::with(kind, measured)),
            None => Ok(measured),
        }
    }

    /// Trace the free thread: the swage from a needle estimate, the other end where the last
    /// stitch left the thread. A trace that cannot be made (the thread hidden, not found) is
    /// a perception dropout, retried as the step's `retries` say; a failing camera or model,
    /// or a perception with no tracer, is a fault.
    fn track_thread(&mut self, c: &mut dyn StepControl) -> Step<stitch_perception::ThreadTrace> {
        let needle = self.estimate(c, None)?;
        let (_, _, _, swage) = needle.features(&self.rig.needle);
        self.trace_to(c, swage)?.map_err(|e| {
            self.unseen.push(format!("thread: {e}"));
            failed(FailureKind::PerceptionDropout)
        })
    }
}

/// A handover attempt's grasp point, `regrasp` moved by the re-attempt's random `jitter`,
/// kept clear of the traced thread: when the blades closing there (along `h`, from the grasp
/// point back towards the right arm) would come nearer the thread than `margin_m` — where the
/// jaw, missing the wire near the swage, would close on the thread that leaves it — the same
/// offset to the other side of `regrasp` instead, if the thread is farther from the blades
/// there. Returns the grasp point and the thread's clearance from its blades, m.
fn grasp_clear_of_thread(
    trace: &stitch_perception::ThreadTrace,
    regrasp: Point,
    jitter: Vector,
    h: Vector,
    margin_m: f64,
) -> (Point, Option<f64>) {
    let clear =
        |t: Point| nearest_to_blades(&trace.points, &trace.sigma_m, &[t, t + h * BLADE_LENGTH_M]);
    let (drawn, other) = (regrasp + jitter, regrasp - jitter);
    let here = clear(drawn);
    match (here, clear(other)) {
        (Some(d), Some(e)) if d < margin_m && jitter.norm() > 0.0 && e > d => (other, Some(e)),
        _ => (drawn, here),
    }
}

/// How far the traced thread stays from the `blades` segment, less twice the trace's
/// uncertainty where it comes nearest, m (negative: it may touch); `None` for an empty trace.
/// The trace is walked in steps of at most 0.5 mm, well under the 1.2 mm at which the mock's
/// closing jaw catches a link, so a segment passing between two of its points is not missed.
fn nearest_to_blades(points: &[Point], sigma_m: &[f64], blades: &[Point; 2]) -> Option<f64> {
    const STEP_M: f64 = 0.0005;
    let sigma = |i: usize| sigma_m.get(i).copied().unwrap_or(0.0);
    let at = |p: &Point, s: f64| {
        let (on, _) = stitch_robot::nearest_on_segment(p, &blades[0], &blades[1]);
        (p - on).norm() - 2.0 * s
    };
    let mut best = points.first().map(|p| at(p, sigma(0)));
    for (i, w) in points.windows(2).enumerate() {
        let steps = ((w[1] - w[0]).norm() / STEP_M).ceil().max(1.0) as usize;
        for k in 1..=steps {
            let t = k as f64 / steps as f64;
            let d = at(
                &(w[0] + (w[1] - w[0]) * t),
                sigma(i) + (sigma(i + 1) - sigma(i)) * t,
            );
            best = best.map(|b| b.min(d));
        }
    }
    best
}

/// The mean of nearby poses: mean translation, normalised sum of sign-aligned quaternions.
pub fn mean_pose(poses: &[Pose]) -> Pose {
    let n = poses.len().max(1) as f64;
    let t = poses
        .iter()
        .fold(Vector::zeros(), |acc, p| acc + p.translation.vector)
        / n;
    let first = poses
        .first()
        .map_or(UnitQuaternion::identity(), |p| p.rotation);
    let sum = poses
        .iter()
        .fold(stitch_robot::nalgebra::Vector4::zeros(), |acc, p| {
            let q = p.rotation.coords;
            if q.dot(&first.coords) < 0.0 {
                acc - q
            } else {
                acc + q
            }
        });
    let q = stitch_robot::nalgebra::Quaternion::from(sum);
    Pose::from_parts(Translation3::from(t), UnitQuaternion::from_quaternion(q))
}

impl Primitives for RobotPrimitives {
    fn run(&mut self, req: &StepRequest<'_>, control: &mut dyn StepControl) -> StepOutcome {
        self.unseen.clear();
        let mut committed = false;
        let result = {
            let mut c = Committing {
                inner: control,
                committed: &mut committed,
            };
            let c: &mut dyn StepControl = &mut c;
            match req.kind {
                StepKind::Insert(p) => self.insert(c, req.point, p),
                StepKind::Sweep(p) => self.sweep(c, req.point, p),
                StepKind::Extract(p) => self.extract(c, p),
                StepKind::Cinch(p) => self.cinch(c, req.throw + 1, p),
                StepKind::Handover(p) => self.handover(c, req.attempt, p),
                StepKind::Correct(p) => self.correct(c, p),
                k @ (StepKind::EstimateNeedle(_) | StepKind::TrackThread(_)) => self.perceive(c, k),
            }
        };
        let unseen = std::mem::take(&mut self.unseen);
        match result {
            Ok(mut measured) => {
                measured.perception_failures = unseen;
                StepOutcome::Succeeded { measured }
            }
            Err(Halt::Failed(mut failure)) => {
                failure.measured.perception_failures = unseen;
                StepOutcome::Failed(*failure)
            }
            Err(Halt::Interrupted) => StepOutcome::Interrupted {
                committed,
                measured: Measurements {
                    perception_failures: unseen,
                    ..Measurements::default()
                },
            },
        }
    }

    fn observe(&mut self, req: &ObserveRequest<'_>) -> Observation {
        let mut obs = Observation::default();
        for (name, arm, slot) in [
            ("right arm", &self.rig.right, &mut obs.right_jaw),
            ("left arm", &self.rig.left, &mut obs.left_jaw),
        ] {
            match arm.measured_cp() {
                Ok(p) => *slot = Some(Point::from(p.translation.vector)),
                Err(e) => obs.faults.push(format!("{name}: {e}")),
            }
        }
        if req.needle {
            // The holding jaw's position, as read above: where that read failed (its fault
            // is listed), no estimate is made this time rather than one without the jaw.
            let hint = match req.needle_at {
                NeedleAt::RightJaw => obs.right_jaw.map(|p| held_at(p, NeedleEnd::Swage)),
                NeedleAt::LeftJaw => obs.left_jaw.map(|p| held_at(p, self.left_end)),
                NeedleAt::Tissue => {
                    let wp = self.last_point.as_ref().unwrap_or(req.point);
                    Some(NeedleHint::InTissue(TissueHint {
                        entry: wp.entry,
                        exit: wp.exit,
                    }))
                }
            };
            match hint {
                // One estimator cycle, as a step's sample takes it; the latest estimate is
                // kept whether or not this one sees the needle.
                Some(hint) => match self.rig.estimator.estimate_needle_with(Some(&hint)) {
                    Ok(e) => {
                        obs.needle_now = true;
                        self.last_estimate = Some(e);
                    }
                    // A failing camera is a fault of the robot, as in a step, not a needle
                    // out of sight.
                    Err(e @ (PerceptionError::Camera { .. } | PerceptionError::Model { .. })) => {
                        obs.faults.push(format!("perception: {e}"));
                        obs.needle_failure = Some(e.to_string());
                    }
                    Err(e) => obs.needle_failure = Some(e.to_string()),
                },
                None => {
                    obs.needle_failure = Some(
                        "not estimated: the arm holding the needle could not say where it is"
                            .into(),
                    );
                }
            }
        }
        if req.thread {
            self.observe_thread(&mut obs);
        }
        obs.needle = self.last_estimate.as_ref().map(|e| {
            let (center, normal, tip, swage) = e.features(&self.rig.needle);
            NeedleSeen {
                center,
                normal,
                tip,
                swage,
                confidence: e.confidence,
                stamp_s: e.stamp.as_secs_f64(),
            }
        });
        obs
    }

    fn hold_all(&mut self) -> Result<(), PrimitiveError> {
        hold_both(&*self.rig.right, &*self.rig.left)
    }
}

impl RobotPrimitives {
    /// A condition's thread trace: from the last stitch's exit to the swage of the needle
    /// query just made. Not traced (with the reason) when that query did not see the needle.
    fn observe_thread(&mut self, obs: &mut Observation) {
        let swage = match (&self.last_estimate, obs.needle_now) {
            (Some(e), true) => e.features(&self.rig.needle).3,
            _ => {
                obs.thread_failure = Some(
                    "not traced: the needle query did not see the needle, and the trace ends \
                     at its swage"
                        .into(),
                );
                return;
            }
        };
        let hint = stitch_perception::ThreadHint {
            start: self.thread_from,
            swage,
            length_m: None,
        };
        match self.rig.estimator.trace_thread(&hint) {
            Ok(t) => {
                obs.thread = Some(ThreadSeen::from_trace(
                    &t.points,
                    &t.sigma_m,
                    t.length_m,
                    t.seen_share,
                    0.005,
                ));
            }
            // A robot that cannot trace (a failing camera or model, a perception without a
            // tracer) has not looked: a fault, not a thread out of sight.
            Err(
                e @ (PerceptionError::Camera { .. }
                | PerceptionError::Model { .. }
                | PerceptionError::Config { .. }),
            ) => {
                obs.faults.push(format!("perception: {e}"));
                obs.thread_failure = Some(e.to_string());
            }
            Err(e) => obs.thread_failure = Some(e.to_string()),
        }
    }
}

/// Passes a control through, noting whether the step committed (for its outcome).
struct Committing<'a> {
    inner: &'a mut dyn StepControl,
    committed: &'a mut bool,
}

impl StepControl for Committing<'_> {
    fn slice(&mut self) -> Option<std::time::Duration> {
        self.inner.slice()
    }
    fn check(&mut self, hold: &mut dyn FnMut() -> Result<(), PrimitiveError>) -> Control {
        self.inner.check(hold)
    }
    fn commit(&mut self) {
        *self.committed = true;
        self.inner.commit();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const MM: f64 = 1e-3;

    fn point() -> WoundPoint {
        WoundPoint {
            index: 0,
            entry: Point::new(-0.005, 0.0, -0.12),
            exit: Point::new(0.005, 0.0, -0.12),
        }
    }

    fn close(a: &Point, b: &Point) -> bool {
        (a - b).norm() < 1e-9
    }

    fn trace(points: Vec<Point>, sigma_m: f64) -> stitch_perception::ThreadTrace {
        stitch_perception::ThreadTrace {
            sigma_m: vec![sigma_m; points.len()],
            points,
            length_m: 0.0,
            hidden: Vec::new(),
            seen_share: 1.0,
            matched: 0,
            left_path_px: Vec::new(),
        }
    }

    #[test]
    fn the_threads_clearance_from_the_blades_is_its_least_distance_less_two_sigma() {
        let blades = [Point::origin(), Point::new(9.0 * MM, 0.0, 0.0)];
        // A vertical strand 3 mm beside the blades' middle, given by two points 4 cm apart:
        // the walk between them finds where it passes.
        let strand = [
            Point::new(4.0 * MM, 3.0 * MM, -20.0 * MM),
            Point::new(4.0 * MM, 3.0 * MM, 20.0 * MM),
        ];
        let d = nearest_to_blades(&strand, &[0.5 * MM; 2], &blades).expect("a trace");
        assert!((d - 2.0 * MM).abs() < 1e-6, "{d}");
        let d = nearest_to_blades(&strand, &[0.0; 2], &blades).expect("a trace");
        assert!((d - 3.0 * MM).abs() < 1e-6, "{d}");
        // Past the blades' back end: measured from that end.
        let beyond = [
            Point::new(14.0 * MM, 0.0, 0.0),
            Point::new(20.0 * MM, 0.0, 0.0),
        ];
        let d = nearest_to_blades(&beyond, &[0.0; 2], &blades).expect("a trace");
        assert!((d - 5.0 * MM).abs() < 1e-9, "{d}");
        // A single point, and nothing.
        let d = nearest_to_blades(&[Point::new(0.0, 0.0, 2.0 * MM)], &[0.0], &blades);
        assert!((d.expect("a point") - 2.0 * MM).abs() < 1e-9);
        assert_eq!(nearest_to_blades(&[], &[], &blades), None);
    }

    #[test]
    fn a_re_attempts_grasp_goes_to_the_side_away_from_the_thread() {
        // The grasp point at the origin, the blades closing along +x back to the right arm,
        // a re-attempt's offset of 4 mm along +y.
        let (regrasp, h, jitter) = (Point::origin(), Vector::x(), Vector::y() * 4.0 * MM);
        let strand_at = |y: f64| {
            trace(
                vec![
                    Point::new(4.0 * MM, y, -20.0 * MM),
                    Point::new(4.0 * MM, y, 20.0 * MM),
                ],
                0.5 * MM,
            )
        };
        // The thread 1 mm beyond the drawn offset's blades: mirrored, 9 mm − 1 mm from it.
        let (at, d) = grasp_clear_of_thread(&strand_at(5.0 * MM), regrasp, jitter, h, 3.0 * MM);
        assert!(close(&at, &(regrasp - jitter)), "{at}");
        assert!((d.expect("traced") - 8.0 * MM).abs() < 1e-6, "{d:?}");
        // Clear of the drawn offset by the margin: kept.
        let (at, d) = grasp_clear_of_thread(&strand_at(9.0 * MM), regrasp, jitter, h, 3.0 * MM);
        assert!(close(&at, &(regrasp + jitter)), "{at}");
        assert!((d.expect("traced") - 4.0 * MM).abs() < 1e-6, "{d:?}");
        // Nearer the drawn offset's blades than the margin, but nearer still to the other
        // side's (a loop down past both): kept.
        let looped = trace(
            vec![
                Point::new(4.0 * MM, 5.5 * MM, -20.0 * MM),
                Point::new(4.0 * MM, 5.5 * MM, 20.0 * MM),
                Point::new(4.0 * MM, -4.5 * MM, 20.0 * MM),
                Point::new(4.0 * MM, -4.5 * MM, -20.0 * MM),
            ],
            0.5 * MM,
        );
        let (at, d) = grasp_clear_of_thread(&looped, regrasp, jitter, h, 3.0 * MM);
        assert!(close(&at, &(regrasp + jitter)), "{at}");
        assert!((d.expect("traced") - 0.5 * MM).abs() < 1e-6, "{d:?}");
        // The first attempt has no offset to turn round.
        let (at, _) =
            grasp_clear_of_thread(&strand_at(1.0 * MM), regrasp, Vector::zeros(), h, 3.0 * MM);
        assert!(close(&at, &regrasp), "{at}");
    }

    #[test]
    fn insertion_starts_with_the_tip_at_the_entry_pointing_at_the_exit() {
        let needle = Needle::default();
        let start = insertion_start(&needle, &point().entry, &point().exit);
        assert!(close(&(start * needle.tip()), &point().entry));
        // The tip leads along entry→exit (+x; the needle frame's −y), the centre 12 mm above.
        assert!(((start * -Vector::y()) - Vector::new(1.0, 0.0, 0.0)).norm() < 1e-12);
        assert!(close(
            &(start * Point::origin()),
            &Point::new(-0.005, 0.0, -0.108)
        ));
        // Its normal is +y, as pose correction leaves it.
        assert!(((start * Vector::z()) - Vector::y()).norm() < 1e-12);
    }

    #[test]
    fn insertion_waypoints_are_the_papers_push_and_45_degree_rotation() {
        let needle = Needle::default();
        let grasp = Pose::from_parts(
            Translation3::new(0.003, -0.002, 0.001),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 0.1),
        );
        let p = InsertParams {
            rotation_rad: 45f64.to_radians(),
            push_m: 7.0 * MM,
            standoff_m: 10.0 * MM,
            samples: 0,
        };
        let w = insertion_waypoints(&needle, &grasp, &point(), &p);
        assert_eq!(w.len(), 3 + 9, "stand-off, start, push, nine 5° steps");
        let tip = |t: &Pose| (t * grasp) * needle.tip();
        // Stand-off: 1 cm back from the entry against entry→exit (+x here) and 5 mm up.
        assert!(close(&tip(&w[0]), &Point::new(-0.015, 0.0, -0.115)));
        assert!(close(&tip(&w[1]), &point().entry));
        // Push: 7 mm along entry→exit.
        assert!(close(&tip(&w[2]), &Point::new(0.002, 0.0, -0.12)));
        // The rotation keeps the centre and turns the tip 45° along the arc.
        let c = (w[2] * grasp) * Point::origin();
        assert!(close(&((w[11] * grasp) * Point::origin()), &c));
        let r = 0.012;
        let expect = Point::new(
            c.x + r * 45f64.to_radians().sin(),
            0.0,
            c.z - r * 45f64.to_radians().cos(),
        );
        assert!(close(&tip(&w[11]), &expect), "{} vs {expect}", tip(&w[11]));
    }

    #[test]
    fn the_extraction_approach_is_one_centimetre_off_then_one_and_a_half_in() {
        let regrasp = Point::new(0.01, 0.0, -0.115);
        let from = Point::new(0.04, 0.02, -0.09);
        let [off, at] = regrasp_waypoints(&regrasp, &from, 0.01, 0.015);
        let h = horizontal(from - regrasp).expect("horizontal");
        assert!(close(
            &Point::from(off.translation.vector),
            &(regrasp + h * 0.01)
        ));
        assert!(close(
            &Point::from(at.translation.vector),
            &(regrasp - h * 0.005)
        ));
        // The jaw points at the re-grasp point, level.
        assert!(((off * Vector::z()) + h).norm() < 1e-12);
    }

    #[test]
    fn rotating_about_an_axis_keeps_points_on_it_and_turns_the_rest() {
        let t = Pose::from_parts(
            Translation3::new(0.01, 0.0, 0.0),
            UnitQuaternion::identity(),
        );
        let r = rotated_about(
            &t,
            &Point::origin(),
            &Vector::z(),
            std::f64::consts::FRAC_PI_2,
        );
        assert!(close(
            &Point::from(r.translation.vector),
            &Point::new(0.0, 0.01, 0.0)
        ));
    }

    #[test]
    fn the_mean_of_poses_averages_translation_and_rotation() {
        let a = Pose::from_parts(
            Translation3::new(0.0, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.1),
        );
        let b = Pose::from_parts(
            Translation3::new(0.002, 0.0, 0.0),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.3),
        );
        let m = mean_pose(&[a, b]);
        assert!((m.translation.vector.x - 0.001).abs() < 1e-12);
        assert!((m.rotation.euler_angles().2 - 0.2).abs() < 1e-9);
    }
}
