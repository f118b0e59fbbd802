#![doc = include_str!("../README.md")]

mod arm;
mod camera;
mod clock;
mod error;
mod jaw;
mod needle;
mod polyline;
mod safety;
mod wound;

pub use nalgebra;

pub use arm::{Arm, ArmCommand, DummyArm, MotionTracker, MoveHandle, SpeedLimits};
pub use camera::{
    DummyCamera, FrameObserver, ObservedCamera, RgbImage, StereoCalibration, StereoCamera,
    StereoFrame,
};
pub use clock::{Clock, SimClock, WallClock};
pub use error::RobotError;
pub use jaw::{DummyJaw, JAW_CLOSED_RAD, JAW_OPEN_RAD, Jaw};
pub use needle::{NEEDLE_RADIUS_M, NEEDLE_WIRE_DIAMETER_M, Needle, NeedleGeometry};
pub use polyline::{distance_to_polyline, nearest_on_polyline, nearest_on_segment};
pub use safety::{LimitPolicy, SpeedLimit, Workspace, WorkspaceLimit, finite_pose};
pub use wound::{Wound, WoundPoint, WoundSpec};

/// A rigid pose (rotation and translation, m) in the robot frame unless said otherwise.
pub type Pose = nalgebra::Isometry3<f64>;
/// A point, m.
pub type Point = nalgebra::Point3<f64>;
/// A vector, m or unitless.
pub type Vector = nalgebra::Vector3<f64>;
