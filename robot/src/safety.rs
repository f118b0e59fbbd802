//! Safety wrappers that implement the same [`Arm`] trait, so the mock and the real robot get
//! the same limits: a workspace box and a maximum speed, each with an error or clamp policy.

use crate::{Arm, Clock, MoveHandle, Point, Pose, RobotError, SpeedLimits};
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

/// What a wrapper does with a command beyond its limit.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LimitPolicy {
    /// Refuse it with an error; nothing reaches the arm.
    Error,
    /// Bring it within the limit and send that.
    Clamp,
}

/// An axis-aligned box the tool tip must stay in, robot frame, m. Deserialising validates it
/// as [`Workspace::new`] does.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "WorkspaceFields")]
pub struct Workspace {
    /// Lower corner, m.
    pub min: Point,
    /// Upper corner, m.
    pub max: Point,
}

impl Workspace {
    /// A box; `min` must be below `max` on every axis and both finite.
    pub fn new(min: Point, max: Point) -> Result<Self, RobotError> {
        let ok =
            min.iter().chain(max.iter()).all(|v| v.is_finite()) && (0..3).all(|i| min[i] < max[i]);
        if ok {
            Ok(Self { min, max })
        } else {
            Err(RobotError::InvalidConfig {
                what: "workspace box".into(),
                why: format!("min {min} must be finite and below max {max} on every axis"),
            })
        }
    }

    /// Whether `p` is inside (boundary included).
    pub fn contains(&self, p: &Point) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    /// The nearest point inside.
    pub fn clamp(&self, p: &Point) -> Point {
        Point::new(
            p.x.clamp(self.min.x, self.max.x),
            p.y.clamp(self.min.y, self.max.y),
            p.z.clamp(self.min.z, self.max.z),
        )
    }
}

/// A [`Workspace`] as read, before it is checked.
#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WorkspaceFields {
    min: Point,
    max: Point,
}

impl TryFrom<WorkspaceFields> for Workspace {
    type Error = RobotError;
    fn try_from(f: WorkspaceFields) -> Result<Self, RobotError> {
        Workspace::new(f.min, f.max)
    }
}

/// Refuse a goal pose with a NaN or infinite value, naming the arm.
pub fn finite_pose(arm: &str, p: &Pose) -> Result<(), RobotError> {
    let ok = p.translation.vector.iter().all(|v| v.is_finite())
        && p.rotation.quaternion().coords.iter().all(|v| v.is_finite());
    if ok {
        Ok(())
    } else {
        Err(RobotError::NonFinite {
            arm: arm.into(),
            what: "goal pose".into(),
        })
    }
}

/// Keeps an arm's goals inside a [`Workspace`].
#[derive(Debug)]
pub struct WorkspaceLimit<A> {
    inner: A,
    workspace: Workspace,
    policy: LimitPolicy,
}

impl<A: Arm> WorkspaceLimit<A> {
    /// Wrap `inner`.
    pub fn new(inner: A, workspace: Workspace, policy: LimitPolicy) -> Self {
        Self {
            inner,
            workspace,
            policy,
        }
    }

    /// The wrapped arm.
    pub fn inner(&self) -> &A {
        &self.inner
    }

    fn admit(&self, goal: &Pose) -> Result<Pose, RobotError> {
        finite_pose(self.inner.name(), goal)?;
        let p = Point::from(goal.translation.vector);
        if self.workspace.contains(&p) {
            return Ok(*goal);
        }
        match self.policy {
            LimitPolicy::Error => Err(RobotError::OutOfWorkspace {
                arm: self.inner.name().into(),
                position: [p.x, p.y, p.z],
                min: self.workspace.min.into(),
                max: self.workspace.max.into(),
            }),
            LimitPolicy::Clamp => {
                let mut g = *goal;
                g.translation.vector = self.workspace.clamp(&p).coords;
                Ok(g)
            }
        }
    }
}

impl<A: Arm> Arm for WorkspaceLimit<A> {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        self.inner.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        self.inner.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        let g = self.admit(goal)?;
        self.inner.move_cp(&g)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        let g = self.admit(goal)?;
        self.inner.servo_cp(&g)
    }
    fn hold(&self) -> Result<(), RobotError> {
        self.inner.hold()
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        self.inner.set_max_speed(limits)
    }
}

/// Bounds an arm's speed.
///
/// - `servo_cp`: the step from the previous servo setpoint divided by the clock time since it
///   is checked against the limits. The first servo command of a stream (after construction,
///   `move_cp` or `hold`) is measured from the arm's current setpoint over one
///   `nominal_period` (default 10 ms, the dVRK's 100 Hz state rate).
/// - `move_cp`: the backend runs the trajectory, so the wrapper asks it to bound its speed
///   (`Arm::set_max_speed`) before every move; a backend that cannot is refused the move.
#[derive(Debug)]
pub struct SpeedLimit<A> {
    inner: A,
    clock: Arc<dyn Clock>,
    limits: SpeedLimits,
    policy: LimitPolicy,
    nominal_period: Duration,
    last_servo: Mutex<Option<(Duration, Pose)>>,
}

impl<A: Arm> SpeedLimit<A> {
    /// Wrap `inner`; limits must be positive and finite.
    pub fn new(
        inner: A,
        clock: Arc<dyn Clock>,
        limits: SpeedLimits,
        policy: LimitPolicy,
    ) -> Result<Self, RobotError> {
        let ok = |v: f64| v.is_finite() && v > 0.0;
        if !(ok(limits.linear_m_per_s) && ok(limits.angular_rad_per_s)) {
            return Err(RobotError::InvalidConfig {
                what: "speed limits".into(),
                why: format!("{limits:?}; expected positive, finite speeds"),
            });
        }
        Ok(Self {
            inner,
            clock,
            limits,
            policy,
            nominal_period: Duration::from_millis(10),
            last_servo: Mutex::new(None),
        })
    }

    /// The wrapped arm.
    pub fn inner(&self) -> &A {
        &self.inner
    }

    fn last(&self) -> std::sync::MutexGuard<'_, Option<(Duration, Pose)>> {
        self.last_servo
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
    }
}

impl<A: Arm> Arm for SpeedLimit<A> {
    fn name(&self) -> &str {
        self.inner.name()
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        self.inner.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        self.inner.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        finite_pose(self.inner.name(), goal)?;
        self.inner.set_max_speed(self.limits)?;
        *self.last() = None;
        self.inner.move_cp(goal)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        finite_pose(self.inner.name(), goal)?;
        let now = self.clock.now();
        // Copy out of the lock before asking the arm anything.
        let last = *self.last();
        let (dt, prev) = match last {
            Some((prev_t, prev)) => (now.saturating_sub(prev_t), prev),
            // The clock may be at its epoch, so the first step's period is not `now − period`.
            None => (self.nominal_period, self.inner.setpoint_cp()?),
        };
        let dt = dt.as_secs_f64();
        let step = goal.translation.vector - prev.translation.vector;
        let turn = prev.rotation.angle_to(&goal.rotation);
        let (lin, ang) = if dt > 0.0 {
            (step.norm() / dt, turn / dt)
        } else if step.norm() > 0.0 || turn > 0.0 {
            (f64::INFINITY, f64::INFINITY)
        } else {
            (0.0, 0.0)
        };
        let mut scale: f64 = 1.0;
        for (what, speed, limit, unit) in [
            ("linear", lin, self.limits.linear_m_per_s, "m/s"),
            ("angular", ang, self.limits.angular_rad_per_s, "rad/s"),
        ] {
            if speed > limit {
                if self.policy == LimitPolicy::Error {
                    return Err(RobotError::TooFast {
                        arm: self.inner.name().into(),
                        what,
                        speed,
                        limit,
                        unit,
                    });
                }
                scale = scale.min(if speed.is_finite() {
                    limit / speed
                } else {
                    0.0
                });
            }
        }
        let sent = if scale < 1.0 {
            let mut g = prev;
            g.translation.vector = prev.translation.vector + step * scale;
            g.rotation = prev.rotation.slerp(&goal.rotation, scale);
            g
        } else {
            *goal
        };
        self.inner.servo_cp(&sent)?;
        *self.last() = Some((now, sent));
        Ok(())
    }
    fn hold(&self) -> Result<(), RobotError> {
        *self.last() = None;
        self.inner.hold()
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        // Never looser than this wrapper's own limits.
        self.inner.set_max_speed(SpeedLimits {
            linear_m_per_s: limits.linear_m_per_s.min(self.limits.linear_m_per_s),
            angular_rad_per_s: limits.angular_rad_per_s.min(self.limits.angular_rad_per_s),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{ArmCommand, DummyArm, SimClock};
    use nalgebra::Translation3;

    fn at(x: f64, y: f64, z: f64) -> Pose {
        Pose::from_parts(
            Translation3::new(x, y, z),
            nalgebra::UnitQuaternion::identity(),
        )
    }

    fn boxed(policy: LimitPolicy) -> WorkspaceLimit<DummyArm> {
        let ws =
            Workspace::new(Point::new(-0.1, -0.1, -0.2), Point::new(0.1, 0.1, 0.0)).expect("box");
        WorkspaceLimit::new(DummyArm::new("PSM1"), ws, policy)
    }

    #[test]
    fn a_goal_outside_the_box_is_refused_and_nothing_reaches_the_arm() {
        let arm = boxed(LimitPolicy::Error);
        let e = arm.move_cp(&at(0.12, 0.0, -0.1)).expect_err("outside");
        assert!(
            e.to_string()
                .starts_with("PSM1: goal (0.1200, 0.0000, -0.1000) m is outside"),
            "{e}"
        );
        assert!(arm.inner().commands().is_empty());
        let _ = arm.move_cp(&at(0.05, 0.0, -0.1)).expect("inside");
        assert_eq!(
            arm.inner().commands(),
            vec![ArmCommand::MoveCp(at(0.05, 0.0, -0.1))]
        );
    }

    #[test]
    fn under_clamp_the_goal_is_brought_to_the_boundary() {
        let arm = boxed(LimitPolicy::Clamp);
        arm.servo_cp(&at(0.3, -0.5, 0.2)).expect("clamped");
        assert_eq!(
            arm.inner().commands(),
            vec![ArmCommand::ServoCp(at(0.1, -0.1, 0.0))]
        );
    }

    #[test]
    fn non_finite_goals_are_always_refused() {
        let arm = boxed(LimitPolicy::Clamp);
        assert!(matches!(
            arm.servo_cp(&at(f64::NAN, 0.0, 0.0)),
            Err(RobotError::NonFinite { .. })
        ));
        assert!(arm.inner().commands().is_empty());
        assert!(Workspace::new(Point::new(0.0, 0.0, 0.0), Point::new(0.0, 1.0, 1.0)).is_err());
    }

    fn limited(policy: LimitPolicy) -> (SpeedLimit<DummyArm>, SimClock) {
        let clock = SimClock::new();
        let limits = SpeedLimits {
            linear_m_per_s: 0.05,
            angular_rad_per_s: 1.0,
        };
        let arm = SpeedLimit::new(
            DummyArm::new("PSM2"),
            Arc::new(clock.clone()),
            limits,
            policy,
        )
        .expect("limits");
        (arm, clock)
    }

    #[test]
    fn a_servo_step_too_fast_for_the_limit_is_refused() {
        let (arm, clock) = limited(LimitPolicy::Error);
        arm.servo_cp(&at(0.0, 0.0, 0.0)).expect("first, no motion");
        clock.advance(Duration::from_millis(100));
        // 1 cm in 0.1 s = 0.1 m/s against 0.05 m/s.
        let e = arm.servo_cp(&at(0.01, 0.0, 0.0)).expect_err("too fast");
        assert!(
            matches!(e, RobotError::TooFast { what: "linear", .. }),
            "{e}"
        );
        assert_eq!(arm.inner().commands().len(), 1);
        // 4 mm in 0.1 s is fine.
        arm.servo_cp(&at(0.004, 0.0, 0.0))
            .expect("within the limit");
    }

    #[test]
    fn under_clamp_a_fast_servo_step_is_scaled_to_the_limit() {
        let (arm, clock) = limited(LimitPolicy::Clamp);
        arm.servo_cp(&at(0.0, 0.0, 0.0)).expect("first");
        clock.advance(Duration::from_millis(100));
        arm.servo_cp(&at(0.01, 0.0, 0.0)).expect("clamped");
        match arm.inner().commands().last() {
            Some(ArmCommand::ServoCp(p)) => assert!((p.translation.vector.x - 0.005).abs() < 1e-12),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn move_cp_asks_the_backend_to_bound_its_speed_first() {
        let (arm, _) = limited(LimitPolicy::Error);
        let _ = arm.move_cp(&at(0.0, 0.05, 0.0)).expect("moves");
        let cmds = arm.inner().commands();
        assert!(
            matches!(cmds[0], ArmCommand::SetMaxSpeed(l) if (l.linear_m_per_s - 0.05).abs() < 1e-12)
        );
        assert!(matches!(cmds[1], ArmCommand::MoveCp(_)));
    }

    /// An arm whose backend cannot bound trajectory speed (the trait's default).
    #[derive(Debug)]
    struct NoSpeedBound(DummyArm);
    impl Arm for NoSpeedBound {
        fn name(&self) -> &str {
            self.0.name()
        }
        fn measured_cp(&self) -> Result<Pose, RobotError> {
            self.0.measured_cp()
        }
        fn setpoint_cp(&self) -> Result<Pose, RobotError> {
            self.0.setpoint_cp()
        }
        fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
            self.0.move_cp(goal)
        }
        fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
            self.0.servo_cp(goal)
        }
        fn hold(&self) -> Result<(), RobotError> {
            self.0.hold()
        }
    }

    #[test]
    fn move_cp_is_refused_when_the_backend_cannot_bound_its_speed() {
        let arm = SpeedLimit::new(
            NoSpeedBound(DummyArm::new("PSM1")),
            Arc::new(SimClock::new()),
            SpeedLimits {
                linear_m_per_s: 0.05,
                angular_rad_per_s: 1.0,
            },
            LimitPolicy::Clamp,
        )
        .expect("limits");
        let e = arm.move_cp(&at(0.0, 0.05, 0.0)).expect_err("unsupported");
        assert!(matches!(e, RobotError::Unsupported { .. }), "{e}");
        assert!(arm.inner().0.commands().is_empty());
        // Streaming still works: the wrapper checks each servo step itself.
        arm.servo_cp(&at(0.0, 0.0, 0.0)).expect("servo");
    }

    #[test]
    fn a_servo_turn_too_fast_for_the_angular_limit_is_refused_with_units() {
        let (arm, clock) = limited(LimitPolicy::Error);
        arm.servo_cp(&at(0.0, 0.0, 0.0)).expect("first");
        clock.advance(Duration::from_millis(100));
        // 0.2 rad in 0.1 s = 2 rad/s against 1 rad/s.
        let turned = Pose::from_parts(
            Translation3::identity(),
            nalgebra::UnitQuaternion::from_axis_angle(&crate::Vector::z_axis(), 0.2),
        );
        let e = arm.servo_cp(&turned).expect_err("too fast");
        assert_eq!(
            e.to_string(),
            "PSM2: commanded angular speed 2.0000 exceeds the limit 1.0000 (rad/s)"
        );
    }

    #[test]
    fn a_servo_step_with_no_time_elapsed_is_refused_or_held_in_place() {
        let (arm, _) = limited(LimitPolicy::Error);
        arm.servo_cp(&at(0.0, 0.0, 0.0)).expect("first");
        assert!(matches!(
            arm.servo_cp(&at(0.001, 0.0, 0.0)),
            Err(RobotError::TooFast { .. })
        ));
        let (arm, _) = limited(LimitPolicy::Clamp);
        arm.servo_cp(&at(0.0, 0.0, 0.0)).expect("first");
        arm.servo_cp(&at(0.001, 0.0, 0.0)).expect("clamped");
        assert_eq!(
            arm.inner().commands().last(),
            Some(&ArmCommand::ServoCp(at(0.0, 0.0, 0.0)))
        );
    }

    #[test]
    fn the_first_servo_step_is_measured_from_the_setpoint_over_one_nominal_period() {
        let (arm, _) = limited(LimitPolicy::Error);
        // 0.05 m/s over 10 ms allows 0.5 mm from the identity setpoint.
        arm.servo_cp(&at(0.0004, 0.0, 0.0)).expect("within");
        arm.hold().expect("hold");
        assert!(arm.servo_cp(&at(0.0008, 0.0, 0.0)).is_ok());
        arm.hold().expect("hold");
        // 0.6 mm from the setpoint at 0.8 mm is too far for one period.
        assert!(arm.servo_cp(&at(0.0014, 0.0, 0.0)).is_err());
    }

    #[test]
    fn wrappers_compose_over_a_shared_dyn_arm() {
        let dummy = Arc::new(DummyArm::new("PSM1"));
        let shared: Arc<dyn Arm> = dummy.clone();
        let clock = SimClock::new();
        let ws =
            Workspace::new(Point::new(-0.1, -0.1, -0.2), Point::new(0.1, 0.1, 0.0)).expect("box");
        let arm: Arc<dyn Arm> = Arc::new(
            SpeedLimit::new(
                WorkspaceLimit::new(shared, ws, LimitPolicy::Error),
                Arc::new(clock.clone()),
                SpeedLimits {
                    linear_m_per_s: 0.05,
                    angular_rad_per_s: 1.0,
                },
                LimitPolicy::Error,
            )
            .expect("limits"),
        );
        assert_eq!(arm.name(), "PSM1");
        assert!(matches!(
            arm.move_cp(&at(0.5, 0.0, -0.1)),
            Err(RobotError::OutOfWorkspace { .. })
        ));
        let _ = arm.move_cp(&at(0.05, 0.0, -0.1)).expect("inside");
        arm.hold().expect("hold");
        assert_eq!(arm.measured_cp().expect("pose"), at(0.05, 0.0, -0.1));
        // The refused goal reached nothing but the speed bound the wrapper set first.
        let sent: Vec<_> = dummy
            .commands()
            .into_iter()
            .filter(|c| !matches!(c, ArmCommand::SetMaxSpeed(_)))
            .collect();
        assert_eq!(
            sent,
            [ArmCommand::MoveCp(at(0.05, 0.0, -0.1)), ArmCommand::Hold]
        );
    }

    #[test]
    fn workspaces_are_checked_when_read() {
        assert!(Workspace::new(Point::new(0.0, 0.0, f64::NAN), Point::new(1.0, 1.0, 1.0)).is_err());
        assert!(Workspace::new(Point::new(0.0, 2.0, 0.0), Point::new(1.0, 1.0, 1.0)).is_err());
        let ws =
            Workspace::new(Point::new(-0.1, -0.1, -0.2), Point::new(0.1, 0.1, 0.0)).expect("box");
        assert!(ws.contains(&Point::new(0.1, -0.1, -0.2)));
        assert!(!ws.contains(&Point::new(0.0, 0.0, 0.01)));
    }
}
