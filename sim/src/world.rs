//! The simulated world: two kinematic PSMs with jaws on one simulated clock, and the needle
//! they carry. Arms and jaws are handed out as [`stitch_robot::Arm`] and
//! [`stitch_robot::Jaw`] implementations that share this world.

use crate::SimError;
use crate::streams::{Streams, Subsystem};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, MutexGuard, PoisonError};
use std::time::Duration;
use stitch_robot::nalgebra::{Translation3, UnitQuaternion};
use stitch_robot::{
    Arm, Jaw, MoveHandle, Needle, Point, Pose, RobotError, SimClock, SpeedLimits, Vector,
};

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

impl MockDvrk {
    /// A world with both arms at `home` poses, the needle held by the right jaw through
    /// `grasp` (the needle frame in the right tool frame), and this seed's streams.
    pub fn new(
        config: PsmConfig,
        needle_model: Needle,
        home: [Pose; 2],
        grasp: Pose,
        streams: Streams,
        clock: SimClock,
    ) -> Result<Self, SimError> {
        config.validate()?;
        let speed = SpeedLimits {
            linear_m_per_s: config.max_linear_m_per_s,
            angular_rad_per_s: config.max_angular_rad_per_s,
        };
        let psm = |p: Pose| Psm {
            setpoint: p,
            jaw_rad: 0.0,
            speed,
            commands: 0,
        };
        let needle = NeedleTruth {
            pose: home[0] * grasp,
            grips: [Some(grasp), None],
            dropped: false,
        };
        let state = State {
            config,
            psms: [psm(home[0]), psm(home[1])],
            needle_model,
            tip_path: vec![(home[0] * grasp) * needle_model.tip()],
            needle,
            grasp_rng: streams.rng(Subsystem::Grasp),
        };
        Ok(Self {
            state: Arc::new(Mutex::new(state)),
            clock,
        })
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// The simulated clock.
    pub fn clock(&self) -> &SimClock {
        &self.clock
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

    /// Let go of the needle wherever it is (a slip, a fault): no jaw holds it.
    pub fn release_needle(&self, dropped: bool) {
        let mut s = self.lock();
        s.needle.grips = [None, None];
        s.needle.dropped = dropped;
    }

    fn move_to(&self, side: Side, goal: &Pose) -> Result<(), RobotError> {
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
        let psm = &s.psms[side.index()];
        let start = psm.setpoint;
        let distance = (goal.translation.vector - start.translation.vector).norm();
        let angle = start.rotation.angle_to(&goal.rotation);
        let secs = (distance / psm.speed.linear_m_per_s).max(angle / psm.speed.angular_rad_per_s);
        let steps = MIN_SAMPLES.max((distance / SAMPLE_SPACING_M).ceil() as usize);
        let carried = s.needle.grips[side.index()];
        for i in 1..=steps {
            let t = i as f64 / steps as f64;
            let pose = Pose::from_parts(
                Translation3::from(start.translation.vector.lerp(&goal.translation.vector, t)),
                start.rotation.slerp(&goal.rotation, t),
            );
            if let Some(grasp) = carried {
                s.needle.pose = pose * grasp;
                let tip = s.needle.pose * s.needle_model.tip();
                s.tip_path.push(tip);
            }
        }
        if carried.is_some() {
            // The other jaw cannot hold a needle that moved away from it: it slips out.
            let other = side.other().index();
            s.needle.grips[other] = None;
        }
        let psm = &mut s.psms[side.index()];
        psm.setpoint = *goal;
        psm.commands += 1;
        drop(s);
        self.clock.advance(Duration::from_secs_f64(secs));
        Ok(())
    }

    fn move_jaw(&self, side: Side, angle_rad: f64) -> Result<(), RobotError> {
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
            // Opening lets go. Whether a needle no jaw holds rests in tissue or falls is the
            // phantom's to say, not the jaw's.
            s.needle.grips[i] = None;
        } else if angle_rad < before && s.needle.grips[i].is_none() && !s.needle.dropped {
            // Closing: grasp the needle if the jaw tip is on its wire.
            let tool = s.psms[i].setpoint;
            let jaw_tip = tool * Point::origin();
            let (_, distance) = nearest_on_needle(&s.needle_model, &s.needle.pose, &jaw_tip);
            if distance <= s.config.grasp_tolerance_m {
                let (sigma_p, sigma_r) = (
                    s.config.grasp_position_sigma_m,
                    s.config.grasp_rotation_sigma_rad,
                );
                let noise = perturbation(&mut s.grasp_rng, sigma_p, sigma_r);
                let grasp = tool.inverse() * s.needle.pose * noise;
                s.needle.grips[i] = Some(grasp);
                s.needle.pose = tool * grasp;
            }
        }
        drop(s);
        self.clock.advance(Duration::from_secs_f64(secs));
        Ok(())
    }
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
fn perturbation(rng: &mut ChaCha8Rng, sigma_p: f64, sigma_r: f64) -> Pose {
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
        self.setpoint_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        Ok(self.world.lock().psms[self.side.index()].setpoint)
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        self.world.move_to(self.side, goal)?;
        Ok(MoveHandle::done())
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        self.world.move_to(self.side, goal)
    }
    fn hold(&self) -> Result<(), RobotError> {
        self.world.lock().psms[self.side.index()].commands += 1;
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
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        self.world.move_jaw(self.side, angle_rad)?;
        Ok(MoveHandle::done())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stitch_robot::{Clock, JAW_OPEN_RAD};

    fn at(x: f64, y: f64, z: f64) -> Pose {
        Pose::from_parts(Translation3::new(x, y, z), UnitQuaternion::identity())
    }

    fn world(sigma: f64) -> MockDvrk {
        let config = PsmConfig {
            grasp_position_sigma_m: sigma,
            grasp_rotation_sigma_rad: sigma,
            ..PsmConfig::default()
        };
        // The needle's swage end in the right jaw: the tool tip at the swage.
        let grasp = at(0.012, 0.0, 0.0);
        MockDvrk::new(
            config,
            Needle::default(),
            [at(0.0, 0.0, 0.0), at(0.05, 0.0, 0.0)],
            grasp,
            Streams::new(1),
            SimClock::new(),
        )
        .expect("world")
    }

    #[test]
    fn a_move_takes_time_by_distance_and_speed_and_carries_the_needle() {
        let w = world(0.0);
        let _ = w
            .arm(Side::Right)
            .move_cp(&at(0.0, 0.02, 0.0))
            .expect("moves");
        // 2 cm at 2 cm/s.
        assert_eq!(w.clock().now(), Duration::from_secs(1));
        let truth = w.needle_truth();
        assert!((truth.pose.translation.vector - Vector::new(0.012, 0.02, 0.0)).norm() < 1e-12);
        let path = w.take_tip_path();
        assert!(path.len() >= 41, "sampled every 0.5 mm: {}", path.len());
        // The tip (needle frame +x·r) is 12 mm beyond the needle frame origin.
        assert!((path.last().expect("tip") - Point::new(0.024, 0.02, 0.0)).norm() < 1e-12);
    }

    #[test]
    fn rotations_take_time_by_angle() {
        let w = world(0.0);
        let goal = Pose::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_euler_angles(0.0, 0.0, 0.25),
        );
        let _ = w.arm(Side::Right).move_cp(&goal).expect("turns");
        assert!((w.clock().now().as_secs_f64() - 0.5).abs() < 1e-9);
    }

    #[test]
    fn a_closing_jaw_on_the_wire_grasps_and_one_off_it_does_not() {
        let w = world(0.0);
        let left = w.arm(Side::Left);
        let jaw = w.jaw(Side::Left);
        let _ = jaw.open().expect("opens");
        // The needle's arc top is at (0.012, 0.012, 0) in the world: 1 mm off it grasps.
        let _ = left.move_cp(&at(0.012, 0.013, 0.0)).expect("moves");
        let _ = jaw.close().expect("closes");
        assert!(w.needle_truth().held_by(Side::Left));
        // Opening the right jaw now leaves it in the left.
        let _ = w.jaw(Side::Right).move_jp(JAW_OPEN_RAD).expect("opens");
        let t = w.needle_truth();
        assert!(t.held_by(Side::Left) && !t.held_by(Side::Right));

        let w = world(0.0);
        let _ = w.jaw(Side::Left).open().expect("opens");
        let _ = w
            .arm(Side::Left)
            .move_cp(&at(0.012, 0.016, 0.0))
            .expect("moves");
        let _ = w.jaw(Side::Left).close().expect("closes");
        assert!(
            !w.needle_truth().held_by(Side::Left),
            "4 mm off the wire misses"
        );
    }

    #[test]
    fn each_grasp_perturbs_the_needle_by_the_seeded_stream() {
        let grasp_after = |seed| {
            let config = PsmConfig::default();
            let w = MockDvrk::new(
                config,
                Needle::default(),
                [at(0.0, 0.0, 0.0), at(0.05, 0.0, 0.0)],
                at(0.012, 0.0, 0.0),
                Streams::new(seed),
                SimClock::new(),
            )
            .expect("world");
            let _ = w.jaw(Side::Left).open().expect("opens");
            let _ = w
                .arm(Side::Left)
                .move_cp(&at(0.012, 0.012, 0.0))
                .expect("moves");
            let _ = w.jaw(Side::Left).close().expect("closes");
            w.needle_truth().grips[1].expect("held")
        };
        assert_eq!(grasp_after(3), grasp_after(3));
        assert_ne!(grasp_after(3), grasp_after(4));
    }

    #[test]
    fn bad_commands_are_refused_without_moving() {
        let w = world(0.0);
        assert!(w.arm(Side::Right).move_cp(&at(f64::NAN, 0.0, 0.0)).is_err());
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
