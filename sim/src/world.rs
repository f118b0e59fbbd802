//! The simulated world: two kinematic PSMs with jaws on one simulated clock, and the needle
//! they carry. Arms and jaws are handed out as [`stitch_robot::Arm`] and
//! [`stitch_robot::Jaw`] implementations that share this world.

use crate::SimError;
use crate::faults::{FaultConfig, FaultKind, Faults};
use crate::phantom::{Phantom, PhantomGeometry};
use crate::streams::{Streams, Subsystem};
use crate::thread::{Capsule, Ground, Thread, ThreadConfig, tool_capsules};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use stitch_robot::nalgebra::Rotation3;
use stitch_robot::nalgebra::{Translation3, UnitQuaternion};
use stitch_robot::{
    Arm, Clock, Jaw, MotionTracker, MoveHandle, Needle, Point, Pose, RobotError, SimClock,
    SpeedLimits, Vector, Wound, WoundSpec,
};

/// Where a step needs the needle, for a recovery.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeedlePlace {
    /// In the right jaw.
    Right,
    /// In the tissue.
    Tissue,
    /// In the left jaw.
    Left,
}

/// Which needle driver.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Side {
    /// PSM1, the right needle driver: inserts.
    Right,
    /// PSM2, the left needle driver: extracts.
    Left,
}

impl Side {
    fn index(self) -> usize {
        match self {
            Side::Right => 0,
            Side::Left => 1,
        }
    }

    /// The arm's CRTK name.
    pub fn arm_name(self) -> &'static str {
        match self {
            Side::Right => "PSM1",
            Side::Left => "PSM2",
        }
    }

    /// The other driver.
    pub fn other(self) -> Side {
        match self {
            Side::Right => Side::Left,
            Side::Left => Side::Right,
        }
    }
}

/// The PSMs' kinematic limits and the grasp model's tolerances.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PsmConfig {
    /// Fastest tool-tip speed of a `move_cp` trajectory, m/s (modelling choice: a careful
    /// 2 cm/s, well under the dVRK's limits).
    pub max_linear_m_per_s: f64,
    /// Fastest tool rotation, rad/s (modelling choice: 0.5 rad/s).
    pub max_angular_rad_per_s: f64,
    /// Jaw opening and closing speed, rad/s (modelling choice: 1 rad/s).
    pub jaw_rad_per_s: f64,
    /// Widest jaw opening, rad (dVRK large needle driver: about 80°).
    pub jaw_max_rad: f64,
    /// A closing jaw grasps the needle if its tip is within this distance of the needle's
    /// wire, m (modelling choice: 2 mm).
    pub grasp_tolerance_m: f64,
    /// Standard deviation of the position perturbation each grasp adds to the needle in the
    /// jaw, m (modelling choice: 0.5 mm).
    pub grasp_position_sigma_m: f64,
    /// Standard deviation of the rotation perturbation each grasp adds, rad (modelling
    /// choice: 3°).
    pub grasp_rotation_sigma_rad: f64,
}

impl Default for PsmConfig {
    fn default() -> Self {
        Self {
            max_linear_m_per_s: 0.02,
            max_angular_rad_per_s: 0.5,
            jaw_rad_per_s: 1.0,
            jaw_max_rad: 80f64.to_radians(),
            grasp_tolerance_m: 0.002,
            grasp_position_sigma_m: 0.0005,
            grasp_rotation_sigma_rad: 3f64.to_radians(),
        }
    }
}

impl PsmConfig {
    /// Refuse limits no arm has.
    pub fn validate(&self) -> Result<(), SimError> {
        let checks = [
            ("max_linear_m_per_s", self.max_linear_m_per_s, 1e-4, 1.0),
            (
                "max_angular_rad_per_s",
                self.max_angular_rad_per_s,
                1e-3,
                10.0,
            ),
            ("jaw_rad_per_s", self.jaw_rad_per_s, 1e-3, 20.0),
            ("jaw_max_rad", self.jaw_max_rad, 0.1, 1.6),
            ("grasp_tolerance_m", self.grasp_tolerance_m, 1e-5, 0.01),
            (
                "grasp_position_sigma_m",
                self.grasp_position_sigma_m,
                0.0,
                0.01,
            ),
            (
                "grasp_rotation_sigma_rad",
                self.grasp_rotation_sigma_rad,
                0.0,
                0.5,
            ),
        ];
        for (name, v, lo, hi) in checks {
            if !(v.is_finite() && (lo..=hi).contains(&v)) {
                return Err(SimError::Config {
                    what: format!("psm.{name}"),
                    why: format!("{v}; expected {lo} to {hi}"),
                });
            }
        }
        Ok(())
    }
}

/// One PSM's state.
#[derive(Clone, Debug, PartialEq)]
struct Psm {
    setpoint: Pose,
    jaw_rad: f64,
    speed: SpeedLimits,
    commands: u64,
}

/// Where the needle is, in truth.
#[derive(Clone, Debug, PartialEq)]
pub struct NeedleTruth {
    /// The needle frame in the world (see [`stitch_robot::Needle`] for the frame), m.
    pub pose: Pose,
    /// For each side (right, left), the needle frame in that jaw's tool frame if it holds it.
    pub grips: [Option<Pose>; 2],
    /// Whether it fell.
    pub dropped: bool,
}

impl NeedleTruth {
    /// Whether `side` holds the needle.
    pub fn held_by(&self, side: Side) -> bool {
        self.grips[side.index()].is_some()
    }
}

/// Everything the world knows; shared by the arm and jaw handles.
#[derive(Debug)]
struct State {
    config: PsmConfig,
    psms: [Psm; 2],
    needle_model: Needle,
    needle: NeedleTruth,
    /// The needle tip's true positions since the last [`MockDvrk::take_tip_path`], m.
    tip_path: Vec<Point>,
    grasp_rng: ChaCha8Rng,
    phantom: Phantom,
    thread: Thread,
    thread_rng: ChaCha8Rng,
    /// The wound point whose tissue holds the needle, if any.
    lodged: Option<usize>,
    /// The wound point the needle last went into.
    last_point: Option<usize>,
    /// The needle's pose when it was last left in the tissue.
    last_lodged_pose: Option<Pose>,
    /// The arms' start poses.
    home: [Pose; 2],
    faults: Faults,
    /// Each PSM's remote centre of motion, m.
    rcm: [Point; 2],
    /// Each PSM's setpoint before its last move (what a stale measurement reports).
    previous: [Pose; 2],
    /// Where along the arc the right jaw first held the needle, rad.
    initial_grasp_angle: f64,
    /// Each PSM's Cartesian motion under way, if any.
    motions: [Option<ArmMotion>; 2],
    /// Each jaw's motion under way: its id and when it ends.
    jaw_motions: [Option<(u64, Duration)>; 2],
    /// The id the next motion gets.
    next_motion: u64,
}

/// A Cartesian motion under way on the simulated clock: a straight line at the arm's speed,
/// sampled every [`SAMPLE_SPACING_M`] for the carried needle's path. It progresses as the
/// clock does ([`State::settle`]); its effects on the needle and thread are those of the
/// path it has run, so a motion stopped halfway has done half of what it would have.
#[derive(Clone, Debug)]
struct ArmMotion {
    id: u64,
    start: Pose,
    goal: Pose,
    begin: Duration,
    end: Duration,
    steps: usize,
    /// Samples of the path applied so far.
    applied: usize,
    /// The needle in this jaw's frame, if the jaw held it when the motion began.
    carried: Option<Pose>,
}

impl ArmMotion {
    /// The fraction of the path run at `now`, 0 to 1.
    fn fraction(&self, now: Duration) -> f64 {
        if now >= self.end {
            1.0
        } else {
            let total = (self.end - self.begin).as_secs_f64();
            (now.saturating_sub(self.begin).as_secs_f64() / total).clamp(0.0, 1.0)
        }
    }

    /// The pose a fraction `t` of the way (interpolated even at 1, as the path's samples
    /// always were; the setpoint at the end is the goal itself).
    fn at(&self, t: f64) -> Pose {
        Pose::from_parts(
            Translation3::from(
                self.start
                    .translation
                    .vector
                    .lerp(&self.goal.translation.vector, t),
            ),
            self.start.rotation.slerp(&self.goal.rotation, t),
        )
    }
}

impl State {
    /// Bring every motion under way up to `now`: the path run since the last settle is
    /// applied, and a motion that reached its end completes.
    fn settle(&mut self, now: Duration) {
        for i in 0..2 {
            let Some(m) = self.motions[i].take() else {
                continue;
            };
            let t = m.fraction(now);
            let mut m = self.advance_motion(i, m, t);
            if t >= 1.0 {
                self.complete(i, &m, m.goal);
            } else {
                self.psms[i].setpoint = m.at(t);
                m.applied = m.applied.min(m.steps);
                self.motions[i] = Some(m);
            }
        }
        for j in &mut self.jaw_motions {
            if j.is_some_and(|(_, end)| end <= now) {
                *j = None;
            }
        }
    }

    /// Apply the samples of `m`'s path up to the fraction `t` (all of them at 1).
    fn advance_motion(&mut self, i: usize, mut m: ArmMotion, t: f64) -> ArmMotion {
        let upto = if t >= 1.0 {
            m.steps
        } else {
            ((t * m.steps as f64).floor() as usize).min(m.steps)
        };
        for k in (m.applied + 1)..=upto {
            let pose = m.at(k as f64 / m.steps as f64);
            let actual = self.faults.actual_pose(i, &self.rcm[i], &pose);
            if let Some(grasp) = m.carried {
                self.needle.pose = actual * grasp;
                let tip = self.needle.pose * self.needle_model.tip();
                self.tip_path.push(tip);
            }
            // The thread follows every third sample (1.5 mm of tool travel), and every sample
            // (0.5 mm, half a blade's radius) while a tool that does not carry the needle is
            // near it, so that a link pushed ahead of a blade stays ahead of it.
            let tools = self.tool_bodies(Some((i, actual)));
            let pushing = m.carried.is_none() && self.thread.near(&tools[5 * i..5 * i + 5]);
            if k % THREAD_EVERY == 0 || k == m.steps || pushing {
                let swage = self.needle.pose * self.needle_model.swage();
                self.thread.follow(swage, &tools);
            }
        }
        m.applied = m.applied.max(upto);
        m
    }

    /// Both tools' capsules where they are (the actual poses, joint offsets included), arm
    /// `moving` at the pose given.
    fn tool_bodies(&self, moving: Option<(usize, Pose)>) -> [Capsule; 10] {
        let at = |j: usize| match moving {
            Some((i, pose)) if i == j => pose,
            _ => self
                .faults
                .actual_pose(j, &self.rcm[j], &self.psms[j].setpoint),
        };
        let [a, b] = [0, 1].map(|j| tool_capsules(&at(j), self.psms[j].jaw_rad));
        let mut out = [a[0]; 10];
        out[..5].copy_from_slice(&a);
        out[5..].copy_from_slice(&b);
        out
    }

    /// Stop arm `i`'s motion, if one is under way, where it is now; and its jaw's, if `jaw`.
    fn stop(&mut self, i: usize, now: Duration, jaw: bool) {
        self.settle(now);
        if let Some(m) = self.motions[i].take() {
            let at = m.at(m.fraction(now));
            if let Some(grasp) = m.carried {
                let actual = self.faults.actual_pose(i, &self.rcm[i], &at);
                self.needle.pose = actual * grasp;
            }
            self.complete(i, &m, at);
        }
        if jaw {
            self.jaw_motions[i] = None;
        }
    }

    /// A motion of arm `i` ends at `at` (its goal, or where it was stopped): the needle may
    /// slip, the other jaw lets go of a needle carried away from it, the needle lodges in or
    /// leaves the tissue, the thread follows, a sweep pushes it.
    fn complete(&mut self, i: usize, m: &ArmMotion, at: Pose) {
        let side = if i == 0 { Side::Right } else { Side::Left };
        if let Some(grasp) = m.carried {
            if self.faults.fires(FaultKind::NeedleSlip) {
                let slipped = grasp * self.faults.slip();
                let actual = self.faults.actual_pose(i, &self.rcm[i], &at);
                self.needle.grips[i] = Some(slipped);
                self.needle.pose = actual * slipped;
            }
            // The other jaw cannot hold a needle that moved away from it: it slips out.
            let other = side.other().index();
            self.needle.grips[other] = None;
            let was = self.lodged;
            self.lodged = tissue_holding(self);
            if let (Some(p), None) = (was, self.lodged) {
                // Out of the tissue: the thread followed the swage through this stitch.
                let wp = &self.phantom.wound.points[p];
                let (entry, exit) = (wp.entry, wp.exit);
                let r = self.needle_model.radius_m;
                let chord = (exit - entry).norm();
                let in_tissue = 2.0 * r * (chord / (2.0 * r)).clamp(0.0, 1.0).asin();
                let swage = self.needle.pose * self.needle_model.swage();
                self.thread.on_extraction(entry, exit, in_tissue, swage);
            }
        }
        self.psms[i].setpoint = at;
        let tools = self.tool_bodies(None);
        let swage = self.needle.pose * self.needle_model.swage();
        self.thread.settle(swage, &tools);
        self.thread.check_tangle(&tools);
    }
}

/// Where things are at the start, and the models' parameters. Poses in the robot frame, m.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SceneConfig {
    /// The PSMs' limits and the grasp model.
    pub psm: PsmConfig,
    /// The needle (the paper's 12 mm half circle by default).
    pub needle: Needle,
    /// The wound's points.
    pub wound: WoundSpec,
    /// The raised edges around the holes.
    pub phantom: PhantomGeometry,
    /// The thread model.
    pub thread: ThreadConfig,
    /// The right tool tip's start, m (modelling choice: above the wound's right side, −x).
    pub right_home: [f64; 3],
    /// The left tool tip's start, m (the paper: "the upper left edge of the workspace").
    pub left_home: [f64; 3],
    /// Where along the arc the right jaw first holds the needle, rad from the tip (modelling
    /// choice: 150°, near the swage, leaving the tip free).
    pub grasp_angle_rad: f64,
    /// Each PSM's remote centre of motion, m (modelling choice: 9 cm above its home).
    pub rcm: [[f64; 3]; 2],
    /// Injected faults (none by default).
    #[serde(default)]
    pub faults: FaultConfig,
}

impl Default for SceneConfig {
    fn default() -> Self {
        Self {
            psm: PsmConfig::default(),
            needle: Needle::default(),
            wound: WoundSpec::default(),
            phantom: PhantomGeometry::default(),
            thread: ThreadConfig::default(),
            right_home: [-0.03, 0.0, -0.09],
            left_home: [0.04, 0.02, -0.09],
            grasp_angle_rad: 150f64.to_radians(),
            rcm: [[-0.03, 0.0, 0.0], [0.04, 0.02, 0.0]],
            faults: FaultConfig::default(),
        }
    }
}

/// The length of a jaw's blades: a closing jaw grasps what lies along this segment, from the
/// tool tip back along the tool's −z axis (dVRK large needle driver: about 9 mm), m.
pub const JAW_LENGTH_M: f64 = 0.009;
/// A closing jaw grasps the wire only across it: not if the jaw lies within this angle of the
/// wire's direction (modelling choice), rad.
pub const GRASP_MIN_CROSSING_RAD: f64 = 20.0 * std::f64::consts::PI / 180.0;

/// The tool pose, in the needle frame, of a jaw holding the needle at `angle` along the arc
/// with the jaw across the needle's plane (tool z = −needle normal, tool x = the wire's
/// direction towards the swage).
pub fn grasp_in_needle_frame(needle: &Needle, angle: f64) -> Pose {
    let p = needle.point_at(angle);
    let x = Vector::new(-angle.sin(), angle.cos(), 0.0);
    let z = -Vector::z();
    let y = z.cross(&x);
    let r = Rotation3::from_basis_unchecked(&[x, y, z]);
    Pose::from_parts(
        Translation3::from(p.coords),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

/// The mock dVRK.
#[derive(Clone, Debug)]
pub struct MockDvrk {
    state: Arc<Mutex<State>>,
    clock: SimClock,
}

/// Interpolation steps per `move_cp`, at least: the tip path is sampled this finely (and at
/// least every 0.5 mm of tool travel) so that hole crossings are scored accurately.
const MIN_SAMPLES: usize = 8;
const SAMPLE_SPACING_M: f64 = 0.0005;
/// The thread follows a motion every this many samples.
const THREAD_EVERY: usize = 3;

impl MockDvrk {
    /// A world laid out by `scene`: both arms at their homes (tool frames aligned with the
    /// robot frame), the needle in the right jaw at `scene.grasp_angle_rad`, this seed's
    /// streams, time from `clock`.
    pub fn new(scene: &SceneConfig, streams: Streams, clock: SimClock) -> Result<Self, SimError> {
        scene.psm.validate()?;
        let wound = Wound::linear(&scene.wound).map_err(|e| SimError::Config {
            what: "wound".into(),
            why: e.to_string(),
        })?;
        let phantom = Phantom::new(wound, scene.phantom)?;
        let mut thread_rng = streams.rng(Subsystem::Thread);
        let at = |p: [f64; 3]| {
            Pose::from_parts(
                Translation3::new(p[0], p[1], p[2]),
                UnitQuaternion::identity(),
            )
        };
        let home = [at(scene.right_home), at(scene.left_home)];
        if !home
            .iter()
            .all(|h| h.translation.vector.iter().all(|v| v.is_finite()))
        {
            return Err(SimError::Config {
                what: "home".into(),
                why: "not finite".into(),
            });
        }
        let grasp = grasp_in_needle_frame(&scene.needle, scene.grasp_angle_rad).inverse();
        let speed = SpeedLimits {
            linear_m_per_s: scene.psm.max_linear_m_per_s,
            angular_rad_per_s: scene.psm.max_angular_rad_per_s,
        };
        let psm = |p: Pose| Psm {
            setpoint: p,
            jaw_rad: 0.0,
            speed,
            commands: 0,
        };
        let pose = home[0] * grasp;
        // The thread's tail: a stopper knot 1 cm out from the first entry on its own side, on
        // the pad, the slack laid to a side drawn from the seed (modelling choice).
        let ground = ground_of(&phantom);
        let first = &phantom.wound.points[0];
        let out = (first.entry - first.exit)
            .try_normalize(1e-12)
            .unwrap_or_else(|| -Vector::x());
        let tail = first.entry + out * 0.01;
        let angle = thread_rng.random_range(0.0..std::f64::consts::TAU);
        let thread = Thread::new(
            scene.thread,
            ground,
            Point::new(tail.x, tail.y, ground.floor_z),
            pose * scene.needle.swage(),
            Vector::new(angle.cos(), angle.sin(), 0.0),
        )?;
        let state = State {
            config: scene.psm,
            psms: [psm(home[0]), psm(home[1])],
            needle_model: scene.needle,
            tip_path: vec![pose * scene.needle.tip()],
            needle: NeedleTruth {
                pose,
                grips: [Some(grasp), None],
                dropped: false,
            },
            grasp_rng: streams.rng(Subsystem::Grasp),
            phantom,
            thread,
            thread_rng,
            lodged: None,
            last_point: None,
            last_lodged_pose: None,
            home,
            faults: Faults::new(scene.faults.clone(), streams.rng(Subsystem::Faults))?,
            rcm: scene.rcm.map(|p| Point::new(p[0], p[1], p[2])),
            previous: home,
            initial_grasp_angle: scene.grasp_angle_rad,
            motions: [None, None],
            jaw_motions: [None, None],
            next_motion: 0,
        };
        Ok(Self {
            state: Arc::new(Mutex::new(state)),
            clock,
        })
    }

    /// Whether an injected perception dropout fires for this estimate, and the hand-eye
    /// error to apply to it.
    pub(crate) fn perception_faults(&self) -> (bool, Pose) {
        let mut s = self.lock();
        (
            s.faults.fires(FaultKind::PerceptionDropout),
            s.faults.hand_eye(),
        )
    }

    /// The phantom.
    pub fn phantom(&self) -> Phantom {
        self.lock().phantom.clone()
    }

    /// The needle's shape.
    pub fn needle_model(&self) -> Needle {
        self.lock().needle_model
    }

    /// The thread's state.
    pub fn thread(&self) -> Thread {
        self.lock().thread.clone()
    }

    /// The free thread as the camera would see it: its links from where it leaves the suture
    /// line to the swage, each with whether a tool hides it (a jaw, wrist or shaft within the
    /// occlusion radius of it: the camera looks down on the tools), m.
    pub fn thread_in_view(&self) -> Vec<(Point, bool)> {
        let s = self.lock();
        let tools = s.tool_bodies(None);
        let r = s.thread.config.occlusion_radius_m;
        s.thread
            .free
            .points
            .iter()
            .map(|p| (*p, tools.iter().any(|c| c.axis_distance(p) <= r + c.radius)))
            .collect()
    }

    /// The wound point whose tissue holds the needle, if any.
    pub fn lodged(&self) -> Option<usize> {
        self.lock().lodged
    }

    /// The world's state, every motion under way brought up to the clock's time.
    fn lock(&self) -> MutexGuard<'_, State> {
        let now = self.clock.now();
        let mut s = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        s.settle(now);
        s
    }

    /// The simulated clock.
    pub fn clock(&self) -> &SimClock {
        &self.clock
    }

    /// How many events of `kind` have happened so far (estimates, closing jaws, carrying
    /// moves, measurements, motion commands): where a scheduled fault's `nth` counts from.
    pub fn fault_events(&self, kind: FaultKind) -> u32 {
        self.lock().faults.events(kind)
    }

    /// An arm handle.
    pub fn arm(&self, side: Side) -> MockArm {
        MockArm {
            world: self.clone(),
            side,
        }
    }

    /// A jaw handle.
    pub fn jaw(&self, side: Side) -> MockJaw {
        MockJaw {
            world: self.clone(),
            side,
            name: format!("{}/jaw", side.arm_name()),
        }
    }

    /// What the camera sees now: the needle (unless it fell out of view), the free thread
    /// and both tools, from the truth.
    pub fn scene_view(&self) -> crate::SceneView {
        scene_of(&self.lock())
    }

    /// The same as the world last settled, without settling it to now and without a draw:
    /// for a viewer on another thread (the web console), which must change nothing in the run.
    /// At most one motion slice old.
    pub fn peek_scene_view(&self) -> crate::SceneView {
        scene_of(&self.state.lock().unwrap_or_else(PoisonError::into_inner))
    }

    /// The static phantom as the camera draws it.
    pub fn phantom_view(&self) -> crate::PhantomView {
        let s = self.lock();
        let points = &s.phantom.wound.points;
        let first = &points[0];
        let last = &points[points.len() - 1];
        let mid =
            |wp: &stitch_robot::WoundPoint| Point::from((wp.entry.coords + wp.exit.coords) / 2.0);
        let along = mid(last) - mid(first);
        let length = along.norm();
        let dir = if length > 1e-9 {
            along / length
        } else {
            Vector::y()
        };
        let surface_z = first.entry.z + s.phantom.geometry.top_above_hole_m;
        let mut start = mid(first);
        start.z = surface_z;
        crate::PhantomView {
            surface_z,
            hole_z: first.entry.z,
            floor_z: first.entry.z - s.phantom.geometry.bottom_below_hole_m,
            wound_start: start,
            wound_dir: dir,
            wound_length_m: length,
            half_bite_m: (first.exit - first.entry).norm() / 2.0,
            spacing_m: if points.len() > 1 {
                length / (points.len() - 1) as f64
            } else {
                0.0
            },
        }
    }

    /// The hand-eye error injected as a fault (identity without one).
    pub fn hand_eye_fault(&self) -> Pose {
        self.lock().faults.hand_eye()
    }

    /// Whether an injected perception dropout fires now (draws from the fault stream).
    pub fn perception_dropout_fires(&self) -> bool {
        self.lock().faults.fires(FaultKind::PerceptionDropout)
    }

    /// The needle's true state (hidden from the primitives; for scoring and perception).
    pub fn needle_truth(&self) -> NeedleTruth {
        self.lock().needle.clone()
    }

    /// The tip's true path since the last call, and start a new one at the tip's position.
    pub fn take_tip_path(&self) -> Vec<Point> {
        let mut s = self.lock();
        let tip = s.needle.pose * s.needle_model.tip();
        std::mem::replace(&mut s.tip_path, vec![tip])
    }

    /// The supervising surgeon's single recovery motion, returning the workspace to a safe
    /// configuration for a step that needs the needle `needs`: the thread untangled and freed
    /// from the jaws, both arms back home with their jaws open, and the needle held by the
    /// right jaw at the scene's starting grasp, by the left jaw (likewise, near its tip), or
    /// back in the tissue as it was last left there. Thread that ran short stays short.
    pub fn recover(&self, needs: NeedlePlace) {
        let mut s = self.lock();
        // The surgeon's hands replace whatever the robot was doing.
        s.motions = [None, None];
        s.jaw_motions = [None, None];
        for i in 0..2 {
            s.psms[i].setpoint = s.home[i];
            s.psms[i].jaw_rad = 0.0;
        }
        s.needle.dropped = false;
        s.needle.grips = [None, None];
        let grasp_at = |angle: f64, needle: &Needle| grasp_in_needle_frame(needle, angle).inverse();
        match needs {
            NeedlePlace::Right => {
                let g = grasp_at(s.initial_grasp_angle, &s.needle_model);
                s.needle.grips[0] = Some(g);
                s.needle.pose = s.home[0] * g;
                s.lodged = None;
            }
            NeedlePlace::Left => {
                let g = grasp_at(
                    std::f64::consts::PI - s.initial_grasp_angle,
                    &s.needle_model,
                );
                s.needle.grips[1] = Some(g);
                s.needle.pose = s.home[1] * g;
                s.lodged = None;
            }
            NeedlePlace::Tissue => {
                if let Some(p) = s.last_lodged_pose {
                    s.needle.pose = p;
                    s.lodged = s.last_point;
                } else {
                    let g = grasp_at(s.initial_grasp_angle, &s.needle_model);
                    s.needle.grips[0] = Some(g);
                    s.needle.pose = s.home[0] * g;
                }
            }
        }
        let tip = s.needle.pose * s.needle_model.tip();
        s.tip_path = vec![tip];
        // The surgeon frees the thread and lays the slack back, away from the camera.
        let swage = s.needle.pose * s.needle_model.swage();
        s.thread.lay_aside(swage, -Vector::y());
    }

    /// Let go of the needle wherever it is (a slip, a fault): no jaw holds it.
    pub fn release_needle(&self, dropped: bool) {
        let mut s = self.lock();
        s.needle.grips = [None, None];
        s.needle.dropped = dropped;
    }

    /// Begin a motion of `side`'s arm to `goal` (a motion under way there stops where it is,
    /// as a new `move_cp` preempts a trajectory); its id.
    fn move_to(&self, side: Side, goal: &Pose) -> Result<u64, RobotError> {
        let now = self.clock.now();
        let mut s = self.lock();
        let name = side.arm_name();
        let finite = goal.translation.vector.iter().all(|v| v.is_finite())
            && goal
                .rotation
                .quaternion()
                .coords
                .iter()
                .all(|v| v.is_finite());
        if !finite {
            return Err(RobotError::NonFinite {
                arm: name.into(),
                what: "goal pose".into(),
            });
        }
        let norm = goal.rotation.quaternion().norm();
        if (norm - 1.0).abs() > 1e-6 {
            // As the dVRK (and the sim-node) refuse it: not a rotation.
            return Err(RobotError::Fault {
                arm: name.into(),
                message: format!("move_cp refused: quaternion of norm {norm:.4}, not a rotation"),
            });
        }
        if s.faults.fires(FaultKind::ArmFault) {
            return Err(RobotError::Fault {
                arm: name.into(),
                message: "injected arm fault".into(),
            });
        }
        let i = side.index();
        s.stop(i, now, false);
        let psm = &s.psms[i];
        let start = psm.setpoint;
        let distance = (goal.translation.vector - start.translation.vector).norm();
        let angle = start.rotation.angle_to(&goal.rotation);
        let secs = (distance / psm.speed.linear_m_per_s).max(angle / psm.speed.angular_rad_per_s);
        let steps = MIN_SAMPLES.max((distance / SAMPLE_SPACING_M).ceil() as usize);
        let id = s.next_motion;
        s.next_motion += 1;
        let motion = ArmMotion {
            id,
            start,
            goal: *goal,
            begin: now,
            end: now + Duration::from_secs_f64(secs),
            steps,
            applied: 0,
            carried: s.needle.grips[i],
        };
        s.previous[i] = start;
        s.psms[i].commands += 1;
        s.motions[i] = Some(motion);
        // A motion of no length ends at once.
        s.settle(now);
        Ok(id)
    }

    /// Run a motion to its end now: the clock advances by what it takes.
    fn finish_now(&self, side: Side, id: u64) {
        let tracker = MockMotion {
            world: self.clone(),
            side,
            id,
            jaw: false,
        };
        let _ = tracker.wait(Duration::MAX);
    }

    /// Begin a motion of `side`'s jaw to `angle_rad`; its id.
    fn move_jaw(&self, side: Side, angle_rad: f64) -> Result<u64, RobotError> {
        let mut s = self.lock();
        let name = format!("{}/jaw", side.arm_name());
        if !angle_rad.is_finite() || angle_rad < 0.0 || angle_rad > s.config.jaw_max_rad {
            return Err(RobotError::InvalidConfig {
                what: format!("{name} angle"),
                why: format!(
                    "{:.1}°; expected 0° to {:.1}°",
                    angle_rad.to_degrees(),
                    s.config.jaw_max_rad.to_degrees()
                ),
            });
        }
        let i = side.index();
        let before = s.psms[i].jaw_rad;
        let secs = (angle_rad - before).abs() / s.config.jaw_rad_per_s;
        s.psms[i].jaw_rad = angle_rad;
        s.psms[i].commands += 1;
        if angle_rad > before {
            // Opening lets go. A needle no jaw holds stays if tissue holds it, else it falls.
            let held_before = s.needle.grips.iter().any(Option::is_some);
            s.needle.grips[i] = None;
            if held_before && s.needle.grips.iter().all(Option::is_none) {
                match tissue_holding(&s) {
                    Some(point) => {
                        if s.lodged.is_none() || s.last_point != Some(point) {
                            let swage = s.needle.pose * s.needle_model.swage();
                            let State {
                                thread, thread_rng, ..
                            } = &mut *s;
                            thread.on_insertion(swage, thread_rng);
                        }
                        s.lodged = Some(point);
                        s.last_point = Some(point);
                        s.last_lodged_pose = Some(s.needle.pose);
                    }
                    None => s.needle.dropped = true,
                }
            }
        } else if angle_rad < before && !s.needle.dropped {
            let tool = s.faults.actual_pose(i, &s.rcm[i], &s.psms[i].setpoint);
            let missed = s.faults.fires(FaultKind::MissedGrasp);
            if !missed
                && s.needle.grips[i].is_none()
                && jaw_reaches_needle(
                    &s.needle_model,
                    &s.needle.pose,
                    &tool,
                    s.config.grasp_tolerance_m,
                )
            {
                let (sigma_p, sigma_r) = (
                    s.config.grasp_position_sigma_m,
                    s.config.grasp_rotation_sigma_rad,
                );
                let noise = perturbation(&mut s.grasp_rng, sigma_p, sigma_r);
                let grasp = tool.inverse() * s.needle.pose * noise;
                s.needle.grips[i] = Some(grasp);
                s.needle.pose = tool * grasp;
            }
            // Closing on thread lying between the blades catches it.
            let blades = tool_capsules(&tool, 0.0)[0];
            let holds = s.needle.grips[i].is_some();
            s.thread.on_grasp(&blades, holds);
        }
        let id = s.next_motion;
        s.next_motion += 1;
        let now = self.clock.now();
        s.jaw_motions[i] = Some((id, now + Duration::from_secs_f64(secs)));
        s.settle(now);
        Ok(id)
    }
}

/// A motion of the mock, on the simulated clock: waiting on it advances the clock (at the
/// clock's pace, if it has one) up to its end, or the end of the wait, whichever comes first.
#[derive(Clone, Debug)]
struct MockMotion {
    world: MockDvrk,
    side: Side,
    id: u64,
    jaw: bool,
}

impl MockMotion {
    /// When the motion ends, if it is under way.
    fn end(&self) -> Option<Duration> {
        let s = self.world.lock();
        let i = self.side.index();
        if self.jaw {
            s.jaw_motions[i]
                .filter(|(id, _)| *id == self.id)
                .map(|(_, e)| e)
        } else {
            s.motions[i]
                .as_ref()
                .filter(|m| m.id == self.id)
                .map(|m| m.end)
        }
    }
}

impl MotionTracker for MockMotion {
    fn is_busy(&self) -> bool {
        self.end().is_some()
    }

    fn wait(&self, timeout: Duration) -> Result<(), RobotError> {
        let Some(end) = self.end() else {
            return Ok(());
        };
        let now = self.world.clock.now();
        let until = end.min(now.saturating_add(timeout));
        self.world.clock.advance(until.saturating_sub(now));
        if self.is_busy() {
            Err(RobotError::Timeout {
                arm: self.side.arm_name().into(),
                after_s: timeout.as_secs_f64(),
            })
        } else {
            Ok(())
        }
    }

    fn stop(&self) -> Result<(), RobotError> {
        if self.is_busy() {
            let now = self.world.clock.now();
            let mut s = self.world.lock();
            let i = self.side.index();
            if self.jaw {
                s.jaw_motions[i] = None;
            } else {
                s.stop(i, now, false);
            }
        }
        Ok(())
    }
}

/// Samples of the needle's arc, world frame.
fn arc_points(needle: Needle, pose: Pose) -> impl Iterator<Item = Point> {
    (0..=48).map(move |k| pose * needle.point_at(std::f64::consts::PI * f64::from(k) / 48.0))
}

/// The wound point whose tissue some part of the needle is in, if any.
fn tissue_holding(s: &State) -> Option<usize> {
    let g = s.phantom.geometry;
    let half_gap = s
        .phantom
        .wound
        .points
        .windows(2)
        .map(|w| (w[1].entry - w[0].entry).norm() / 2.0)
        .fold(0.004, f64::min);
    s.phantom.wound.points.iter().position(|wp| {
        let (entry, exit) = s.phantom.holes(wp);
        let top = wp.entry.z.max(wp.exit.z) + g.top_above_hole_m;
        let bottom = wp.entry.z.min(wp.exit.z) - g.bottom_below_hole_m;
        arc_points(s.needle_model, s.needle.pose).any(|p| {
            entry.distance(&p) < 0.0
                && exit.distance(&p) < 0.0
                && (p.y - wp.entry.y).abs() <= half_gap
                && p.z <= top
                && p.z >= bottom
        })
    })
}

/// Whether a closing jaw at `tool` grasps the needle: some point of the wire lies within
/// `tolerance` of the blades (the segment from the tool tip back along −z, [`JAW_LENGTH_M`]
/// long), and the blades cross the wire there at more than [`GRASP_MIN_CROSSING_RAD`].
pub fn jaw_reaches_needle(
    needle: &Needle,
    needle_pose: &Pose,
    tool: &Pose,
    tolerance: f64,
) -> bool {
    let a = tool * Point::origin();
    let axis = tool * -Vector::z();
    let b = a + axis * JAW_LENGTH_M;
    (0..=96).any(|k| {
        let angle = std::f64::consts::PI * f64::from(k) / 96.0;
        let p = needle_pose * needle.point_at(angle);
        let t = ((p - a).dot(&(b - a)) / JAW_LENGTH_M.powi(2)).clamp(0.0, 1.0);
        let distance = (p - (a + (b - a) * t)).norm();
        let wire = needle_pose * Vector::new(-angle.sin(), angle.cos(), 0.0);
        let crossing = axis.angle(&wire);
        distance <= tolerance
            && crossing > GRASP_MIN_CROSSING_RAD
            && crossing < std::f64::consts::PI - GRASP_MIN_CROSSING_RAD
    })
}

/// The point of the needle's arc nearest to `p`, and its distance, m.
pub fn nearest_on_needle(needle: &Needle, needle_pose: &Pose, p: &Point) -> (Point, f64) {
    let local = needle_pose.inverse() * p;
    // Angle of the point's projection in the needle plane, clamped to the half circle [0, π].
    let angle = local.y.atan2(local.x).clamp(0.0, std::f64::consts::PI);
    let on_arc = needle.point_at(angle);
    let world = needle_pose * on_arc;
    (world, (world - p).norm())
}

/// A small random rigid motion: Gaussian-like position (sum of uniforms) and rotation.
pub(crate) fn perturbation(rng: &mut ChaCha8Rng, sigma_p: f64, sigma_r: f64) -> Pose {
    // The sum of three uniforms on [-1, 1] has standard deviation 1: close enough to a normal
    // for a perturbation, and needs no extra dependency.
    let mut normal = || (0..3).map(|_| rng.random_range(-1.0..=1.0)).sum::<f64>();
    let t = Vector::new(normal(), normal(), normal()) * sigma_p;
    let r = Vector::new(normal(), normal(), normal()) * sigma_r;
    Pose::from_parts(Translation3::from(t), UnitQuaternion::from_scaled_axis(r))
}

/// A PSM as a [`stitch_robot::Arm`].
#[derive(Clone, Debug)]
pub struct MockArm {
    world: MockDvrk,
    side: Side,
}

impl Arm for MockArm {
    fn name(&self) -> &str {
        self.side.arm_name()
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        let mut s = self.world.lock();
        let i = self.side.index();
        // The encoders cannot see joint offsets: the measured pose is the commanded one. A
        // stale measurement (the pose from before the last move) is refused, as the dVRK
        // backend refuses data older than its bound.
        if s.faults.fires(FaultKind::StaleMeasurement) {
            let age_s = (s.psms[i].setpoint.translation.vector - s.previous[i].translation.vector)
                .norm()
                / s.config.max_linear_m_per_s;
            Err(RobotError::Stale {
                arm: self.side.arm_name().into(),
                age_s,
            })
        } else {
            Ok(s.psms[i].setpoint)
        }
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        Ok(self.world.lock().psms[self.side.index()].setpoint)
    }
    /// Begins the motion; waiting on the handle runs it on the simulated clock.
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        let id = self.world.move_to(self.side, goal)?;
        Ok(MoveHandle::new(Arc::new(MockMotion {
            world: self.world.clone(),
            side: self.side,
            id,
            jaw: false,
        })))
    }
    /// The mock has no servo loop: the setpoint is reached as a motion would, at once.
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        let id = self.world.move_to(self.side, goal)?;
        self.world.finish_now(self.side, id);
        Ok(())
    }
    /// Stops the arm's motion where it is now, and its jaw's.
    fn hold(&self) -> Result<(), RobotError> {
        let now = self.world.clock.now();
        let mut s = self.world.lock();
        let i = self.side.index();
        s.stop(i, now, true);
        s.psms[i].commands += 1;
        Ok(())
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        let mut s = self.world.lock();
        let hw = (s.config.max_linear_m_per_s, s.config.max_angular_rad_per_s);
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(limits.linear_m_per_s) && ok(limits.angular_rad_per_s)) {
            return Err(RobotError::InvalidConfig {
                what: "speed limits".into(),
                why: format!("{limits:?}"),
            });
        }
        s.psms[self.side.index()].speed = SpeedLimits {
            linear_m_per_s: limits.linear_m_per_s.min(hw.0),
            angular_rad_per_s: limits.angular_rad_per_s.min(hw.1),
        };
        Ok(())
    }
}

/// A PSM's jaw as a [`stitch_robot::Jaw`].
#[derive(Clone, Debug)]
pub struct MockJaw {
    world: MockDvrk,
    side: Side,
    name: String,
}

impl Jaw for MockJaw {
    fn name(&self) -> &str {
        &self.name
    }
    fn measured_jp(&self) -> Result<f64, RobotError> {
        Ok(self.world.lock().psms[self.side.index()].jaw_rad)
    }
    /// The jaw's opening (and what it grasps or lets go) is decided when commanded; the
    /// handle's wait runs the time it takes, which a hold cuts short.
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        let id = self.world.move_jaw(self.side, angle_rad)?;
        Ok(MoveHandle::new(Arc::new(MockMotion {
            world: self.world.clone(),
            side: self.side,
            id,
            jaw: true,
        })))
    }
}

/// What the thread rests on: the pad and the raised wound, as the renderer draws them.
/// What the thread rests on: the pad and the raised wound of `phantom`.
pub fn ground_of(phantom: &Phantom) -> Ground {
    let points = &phantom.wound.points;
    let (first, last) = (&points[0], &points[points.len() - 1]);
    let mid = |wp: &stitch_robot::WoundPoint| Point::from((wp.entry.coords + wp.exit.coords) / 2.0);
    let along = mid(last) - mid(first);
    let length = along.xy().norm();
    let dir = if length > 1e-9 {
        Vector::new(along.x, along.y, 0.0) / length
    } else {
        Vector::y()
    };
    let top_z = first.entry.z + phantom.geometry.top_above_hole_m;
    let mut start = mid(first);
    start.z = top_z;
    Ground {
        floor_z: first.entry.z - phantom.geometry.bottom_below_hole_m,
        top_z,
        start,
        along: dir,
        half_width_m: (first.exit - first.entry).norm() / 2.0,
        length_m: length,
        margin_m: crate::render::WOUND_MARGIN_M,
    }
}

/// What the camera sees in `s`: the needle (unless it fell out of view), the free thread and
/// both tools, from the truth.
fn scene_of(s: &State) -> crate::SceneView {
    crate::SceneView {
        needle: (!s.needle.dropped).then_some((s.needle_model, s.needle.pose)),
        thread: s.thread.pieces(),
        tools: (0..2)
            .map(|i| crate::ToolView {
                pose: s.psms[i].setpoint,
                jaw_rad: s.psms[i].jaw_rad,
            })
            .collect(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stitch_robot::JAW_OPEN_RAD;
    use stitch_robot::nalgebra::Quaternion;

    fn world(seed: u64, sigma: f64) -> MockDvrk {
        let scene = SceneConfig {
            psm: PsmConfig {
                grasp_position_sigma_m: sigma,
                grasp_rotation_sigma_rad: sigma,
                ..PsmConfig::default()
            },
            ..SceneConfig::default()
        };
        MockDvrk::new(&scene, Streams::new(seed), SimClock::new()).expect("world")
    }

    fn moved(p: &Pose, by: Vector) -> Pose {
        Pose::from_parts(Translation3::from(p.translation.vector + by), p.rotation)
    }

    #[test]
    fn a_move_takes_time_by_distance_and_speed_and_carries_the_needle() {
        let w = world(1, 0.0);
        let arm = w.arm(Side::Right);
        let start = arm.setpoint_cp().expect("pose");
        let needle_before = w.needle_truth().pose;
        let _ = w.take_tip_path();
        arm.move_cp(&moved(&start, Vector::new(0.0, 0.02, 0.0)))
            .expect("moves")
            .wait(Duration::MAX)
            .expect("ends");
        // 2 cm at 2 cm/s.
        assert_eq!(w.clock().now(), Duration::from_secs(1));
        let after = w.needle_truth().pose;
        let shift = after.translation.vector - needle_before.translation.vector;
        assert!((shift - Vector::new(0.0, 0.02, 0.0)).norm() < 1e-12);
        let path = w.take_tip_path();
        assert!(path.len() >= 41, "sampled every 0.5 mm: {}", path.len());
        let tip = after * Needle::default().tip();
        assert!((path.last().expect("tip") - tip).norm() < 1e-12);
    }

    #[test]
    fn rotations_take_time_by_angle() {
        let w = world(1, 0.0);
        let arm = w.arm(Side::Right);
        let start = arm.setpoint_cp().expect("pose");
        let goal = Pose::from_parts(
            start.translation,
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.25),
        );
        arm.move_cp(&goal)
            .expect("turns")
            .wait(Duration::MAX)
            .expect("ends");
        assert!((w.clock().now().as_secs_f64() - 0.5).abs() < 1e-9);
    }

    /// The left tool placed across the wire at `angle` along the arc, shifted by `off`.
    fn left_across(w: &MockDvrk, angle: f64, off: Vector) -> Pose {
        let n = w.needle_truth().pose;
        moved(&(n * grasp_in_needle_frame(&Needle::default(), angle)), off)
    }

    #[test]
    fn a_jaw_closing_across_the_wire_grasps_and_one_beside_it_does_not() {
        let w = world(1, 0.0);
        let (left, jaw) = (w.arm(Side::Left), w.jaw(Side::Left));
        jaw.open()
            .expect("opens")
            .wait(Duration::MAX)
            .expect("ends");
        left.move_cp(&left_across(&w, 0.5, Vector::new(0.0, 0.0, 0.001)))
            .expect("moves")
            .wait(Duration::MAX)
            .expect("ends");
        jaw.close()
            .expect("closes")
            .wait(Duration::MAX)
            .expect("ends");
        assert!(w.needle_truth().held_by(Side::Left));
        // The right lets go: the left keeps it, nothing falls.
        w.jaw(Side::Right)
            .move_jp(JAW_OPEN_RAD)
            .expect("opens")
            .wait(Duration::MAX)
            .expect("ends");
        let t = w.needle_truth();
        assert!(t.held_by(Side::Left) && !t.held_by(Side::Right) && !t.dropped);

        let w = world(1, 0.0);
        w.jaw(Side::Left)
            .open()
            .expect("opens")
            .wait(Duration::MAX)
            .expect("ends");
        let n = w.needle_truth().pose;
        // 4 mm out of the needle's plane, beyond the blades' reach.
        let off = n * Vector::new(0.0, 0.0, 0.004 + JAW_LENGTH_M);
        w.arm(Side::Left)
            .move_cp(&left_across(&w, 0.5, off))
            .expect("moves")
            .wait(Duration::MAX)
            .expect("ends");
        w.jaw(Side::Left)
            .close()
            .expect("closes")
            .wait(Duration::MAX)
            .expect("ends");
        assert!(!w.needle_truth().held_by(Side::Left));
    }

    #[test]
    fn a_jaw_along_the_wire_does_not_grasp() {
        let w = world(1, 0.0);
        let n = w.needle_truth().pose;
        // Blades pointing along the wire's direction at the tip (+y of the needle frame).
        let at_tip = n * Needle::default().tip();
        let along =
            UnitQuaternion::rotation_between(&-Vector::z(), &(n * Vector::y())).expect("rotation");
        let tool = Pose::from_parts(
            Translation3::from((at_tip + n * Vector::y() * 0.002).coords),
            along,
        );
        // Within 0.5 mm the blades only touch the wire where it runs along them.
        assert!(!jaw_reaches_needle(&Needle::default(), &n, &tool, 0.0005));
        // The same spot with the blades across the wire grasps.
        let across = n * grasp_in_needle_frame(&Needle::default(), 0.0);
        assert!(jaw_reaches_needle(&Needle::default(), &n, &across, 0.0005));
    }

    #[test]
    fn each_grasp_perturbs_the_needle_by_the_seeded_stream() {
        let grasp_after = |seed| {
            let w = world(seed, 0.001);
            w.jaw(Side::Left)
                .open()
                .expect("opens")
                .wait(Duration::MAX)
                .expect("ends");
            w.arm(Side::Left)
                .move_cp(&left_across(&w, 0.5, Vector::zeros()))
                .expect("moves")
                .wait(Duration::MAX)
                .expect("ends");
            w.jaw(Side::Left)
                .close()
                .expect("closes")
                .wait(Duration::MAX)
                .expect("ends");
            w.needle_truth().grips[1].expect("held")
        };
        assert_eq!(grasp_after(3), grasp_after(3));
        assert_ne!(grasp_after(3), grasp_after(4));
    }

    #[test]
    fn a_needle_let_go_in_the_air_falls_and_one_let_go_in_tissue_stays() {
        let w = world(1, 0.0);
        w.jaw(Side::Right)
            .open()
            .expect("opens")
            .wait(Duration::MAX)
            .expect("ends");
        assert!(w.needle_truth().dropped);

        let w = world(1, 0.0);
        // The needle's plane vertical along x, its arc's middle at wound point 1's midpoint.
        let r = Rotation3::from_basis_unchecked(&[Vector::x(), -Vector::z(), Vector::y()]);
        let wanted = Pose::from_parts(
            Translation3::new(0.0, 0.0, -0.12 + 0.012),
            UnitQuaternion::from_rotation_matrix(&r),
        );
        let grasp = w.needle_truth().grips[0].expect("held");
        w.arm(Side::Right)
            .move_cp(&(wanted * grasp.inverse()))
            .expect("moves")
            .wait(Duration::MAX)
            .expect("ends");
        w.jaw(Side::Right)
            .open()
            .expect("opens")
            .wait(Duration::MAX)
            .expect("ends");
        let t = w.needle_truth();
        assert!(!t.dropped);
        assert_eq!(w.lodged(), Some(0));
        let thread = w.thread();
        assert!(
            thread.open_loop.is_none() && (thread.remaining_m() - 0.30).abs() < 1e-9,
            "the thread follows through only when the needle comes out"
        );
    }

    #[test]
    fn bad_commands_are_refused_without_moving() {
        let w = world(1, 0.0);
        let bad = Pose::from_parts(
            Translation3::new(f64::NAN, 0.0, 0.0),
            UnitQuaternion::identity(),
        );
        assert!(w.arm(Side::Right).move_cp(&bad).is_err());
        // A reflection is no rotation: its quaternion is not a unit one.
        let reflected = Pose::from_parts(
            Translation3::new(0.0, 0.0, -0.1),
            UnitQuaternion::new_unchecked(Quaternion::new(0.7, 0.0, 0.0, 0.0)),
        );
        let refused = w.arm(Side::Right).move_cp(&reflected).err();
        assert!(
            refused
                .as_ref()
                .is_some_and(|e| e.to_string().contains("not a rotation")),
            "{refused:?}"
        );
        assert!(w.jaw(Side::Right).move_jp(3.0).is_err());
        assert_eq!(w.clock().now(), Duration::ZERO);
        assert!(
            PsmConfig {
                max_linear_m_per_s: 0.0,
                ..PsmConfig::default()
            }
            .validate()
            .is_err()
        );
    }
}
