//! The arm: CRTK Cartesian commands and measurements, as the dVRK names them.

use crate::{Pose, RobotError};
use serde::{Deserialize, Serialize};
use std::fmt::Debug;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::Duration;

/// Tracks one motion a backend is executing.
pub trait MotionTracker: Send + Sync + Debug {
    /// Whether the motion is still running.
    fn is_busy(&self) -> bool;
    /// Wait until it ends, at most `timeout`.
    fn wait(&self, timeout: Duration) -> Result<(), RobotError>;
    /// Stop it where it is.
    fn stop(&self) -> Result<(), RobotError>;
}

/// A handle on a motion. Dropping it does **not** stop the motion; [`MoveHandle::stop`] does.
#[must_use = "a motion runs on after its handle is dropped: wait for it, or stop it"]
#[derive(Clone, Debug)]
pub struct MoveHandle {
    tracker: Option<Arc<dyn MotionTracker>>,
}

impl MoveHandle {
    /// A handle on a motion the backend tracks.
    pub fn new(tracker: Arc<dyn MotionTracker>) -> Self {
        Self {
            tracker: Some(tracker),
        }
    }

    /// A handle on a motion that already ended.
    pub fn done() -> Self {
        Self { tracker: None }
    }

    /// Whether the motion is still running.
    pub fn is_busy(&self) -> bool {
        self.tracker.as_ref().is_some_and(|t| t.is_busy())
    }

    /// Wait until the motion ends, at most `timeout`.
    pub fn wait(&self, timeout: Duration) -> Result<(), RobotError> {
        self.tracker.as_ref().map_or(Ok(()), |t| t.wait(timeout))
    }

    /// Stop the motion where it is.
    pub fn stop(&self) -> Result<(), RobotError> {
        self.tracker.as_ref().map_or(Ok(()), |t| t.stop())
    }
}

/// Limits on Cartesian speed.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SpeedLimits {
    /// Tool-tip linear speed, m/s.
    pub linear_m_per_s: f64,
    /// Tool rotation speed, rad/s.
    pub angular_rad_per_s: f64,
}

/// An arm (a PSM), CRTK-named. Poses are the tool tip in the robot frame, SI units.
pub trait Arm: Send + Sync {
    /// The arm's name, e.g. `PSM1`.
    fn name(&self) -> &str;
    /// Measured Cartesian position of the tool tip.
    fn measured_cp(&self) -> Result<Pose, RobotError>;
    /// The last commanded Cartesian setpoint.
    fn setpoint_cp(&self) -> Result<Pose, RobotError>;
    /// Start a trajectory to `goal`; returns at once.
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError>;
    /// Set `goal` as the immediate setpoint (streamed, e.g. at 100 Hz–1 kHz).
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError>;
    /// Stop any motion and hold the current pose.
    fn hold(&self) -> Result<(), RobotError>;
    /// Bound the speed of the trajectories `move_cp` runs. Backends that cannot bound it
    /// say so, and [`crate::SpeedLimit`] then refuses `move_cp`.
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        let _ = limits;
        Err(RobotError::Unsupported {
            what: format!("{}: trajectory speed limits", self.name()),
        })
    }
}

/// Forwards every call, so `Arc<dyn Arm>` (and `Box`, `&`) can be wrapped in
/// [`crate::WorkspaceLimit`] and [`crate::SpeedLimit`].
macro_rules! forward_arm {
    ($($ptr:ty),*) => {$(
        impl<T: Arm + ?Sized> Arm for $ptr {
            fn name(&self) -> &str {
                (**self).name()
            }
            fn measured_cp(&self) -> Result<Pose, RobotError> {
                (**self).measured_cp()
            }
            fn setpoint_cp(&self) -> Result<Pose, RobotError> {
                (**self).setpoint_cp()
            }
            fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
                (**self).move_cp(goal)
            }
            fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
                (**self).servo_cp(goal)
            }
            fn hold(&self) -> Result<(), RobotError> {
                (**self).hold()
            }
            fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
                (**self).set_max_speed(limits)
            }
        }
    )*};
}
forward_arm!(Arc<T>, Box<T>, &T);

/// A command a [`DummyArm`] received.
#[derive(Clone, Debug, PartialEq)]
pub enum ArmCommand {
    /// `move_cp(goal)`.
    MoveCp(Pose),
    /// `servo_cp(goal)`.
    ServoCp(Pose),
    /// `hold()`.
    Hold,
    /// `set_max_speed(limits)`.
    SetMaxSpeed(SpeedLimits),
}

/// An arm that records what it is told and is wherever it was last told to be.
#[derive(Debug)]
pub struct DummyArm {
    /// The arm's name.
    pub name: String,
    /// Every command, in order.
    pub commands: Mutex<Vec<ArmCommand>>,
    /// The current pose (measured = setpoint).
    pub pose: Mutex<Pose>,
}

impl DummyArm {
    /// A dummy arm at the identity pose.
    pub fn new(name: &str) -> Self {
        Self {
            name: name.into(),
            commands: Mutex::new(Vec::new()),
            pose: Mutex::new(Pose::identity()),
        }
    }

    /// The commands received so far.
    pub fn commands(&self) -> Vec<ArmCommand> {
        self.commands
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    fn record(&self, c: ArmCommand) {
        self.commands
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(c);
    }
}

impl Arm for DummyArm {
    fn name(&self) -> &str {
        &self.name
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        Ok(*self.pose.lock().unwrap_or_else(PoisonError::into_inner))
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        self.measured_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        self.record(ArmCommand::MoveCp(*goal));
        *self.pose.lock().unwrap_or_else(PoisonError::into_inner) = *goal;
        Ok(MoveHandle::done())
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        self.record(ArmCommand::ServoCp(*goal));
        *self.pose.lock().unwrap_or_else(PoisonError::into_inner) = *goal;
        Ok(())
    }
    fn hold(&self) -> Result<(), RobotError> {
        self.record(ArmCommand::Hold);
        Ok(())
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        self.record(ArmCommand::SetMaxSpeed(limits));
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::{AtomicBool, Ordering};

    #[derive(Debug, Default)]
    struct Flag {
        busy: AtomicBool,
    }
    impl MotionTracker for Flag {
        fn is_busy(&self) -> bool {
            self.busy.load(Ordering::SeqCst)
        }
        fn wait(&self, timeout: Duration) -> Result<(), RobotError> {
            if self.is_busy() {
                Err(RobotError::Timeout {
                    arm: "t".into(),
                    after_s: timeout.as_secs_f64(),
                })
            } else {
                Ok(())
            }
        }
        fn stop(&self) -> Result<(), RobotError> {
            self.busy.store(false, Ordering::SeqCst);
            Ok(())
        }
    }

    #[test]
    fn dropping_a_handle_does_not_stop_the_motion_and_stop_does() {
        let flag = Arc::new(Flag::default());
        flag.busy.store(true, Ordering::SeqCst);
        drop(MoveHandle::new(flag.clone()));
        assert!(flag.is_busy());
        let h = MoveHandle::new(flag.clone());
        assert!(h.wait(Duration::from_millis(1)).is_err());
        h.stop().expect("stops");
        assert!(!flag.is_busy());
        assert!(!MoveHandle::done().is_busy());
    }
}
