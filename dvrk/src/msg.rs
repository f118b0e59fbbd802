//! The ROS 2 messages of the dVRK's CRTK interface, as serde structs whose field order and
//! types are the ROS 2 definitions' (that order is the CDR layout). Names follow ROS.

use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    /// Seconds.
    pub sec: i32,
    /// Nanoseconds, 0 to 999,999,999.
    pub nanosec: u32,
}

impl Time {
    /// Whether it is the zero stamp, which CRTK reserves for invalid data.
    pub fn is_zero(&self) -> bool {
        self.sec == 0 && self.nanosec == 0
    }

    /// Seconds as a float.
    pub fn as_secs_f64(&self) -> f64 {
        f64::from(self.sec) + f64::from(self.nanosec) * 1e-9
    }
}

/// `std_msgs/msg/Header`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    /// When the data was measured.
    pub stamp: Time,
    /// The frame the data is in.
    pub frame_id: String,
}

/// `std_msgs/msg/String`: the dVRK's `error`, `warning` and `status`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringMsg {
    /// The text.
    pub data: String,
}

/// `std_msgs/msg/Empty`: the dVRK's `hold`. ROS 2 encodes an empty structure as one byte.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Empty {
    /// The placeholder member ROS 2's IDL gives empty messages.
    pub structure_needs_at_least_one_member: u8,
}

/// `geometry_msgs/msg/Point`, m.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    /// x, m.
    pub x: f64,
    /// y, m.
    pub y: f64,
    /// z, m.
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    /// x.
    pub x: f64,
    /// y.
    pub y: f64,
    /// z.
    pub z: f64,
    /// w.
    pub w: f64,
}

impl Default for Quaternion {
    fn default() -> Self {
        Self {
            x: 0.0,
            y: 0.0,
            z: 0.0,
            w: 1.0,
        }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Position, m.
    pub position: Point,
    /// Orientation.
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseStamped`: `measured_cp`, `setpoint_cp`, `move_cp`, `servo_cp`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    /// Stamp and frame.
    pub header: Header,
    /// The pose.
    pub pose: Pose,
}

/// `sensor_msgs/msg/JointState`: `measured_js`, `jaw/measured_js`, `move_jp`, `jaw/move_jp`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct JointState {
    /// Stamp.
    pub header: Header,
    /// Joint names.
    pub name: Vec<String>,
    /// Positions, rad or m.
    pub position: Vec<f64>,
    /// Velocities.
    pub velocity: Vec<f64>,
    /// Efforts.
    pub effort: Vec<f64>,
}

/// `crtk_msgs/msg/OperatingState`: the arm's `operating_state` (latched).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct OperatingState {
    /// Stamp.
    pub header: Header,
    /// "DISABLED", "ENABLED", "PAUSED" or "FAULT".
    pub state: String,
    /// Whether the arm is homed.
    pub is_homed: bool,
    /// Whether a trajectory (`move_*`) is under way.
    pub is_busy: bool,
}

/// `crtk_msgs/msg/StringStamped`: `state_command` (enable, disable, home, unhome, pause,
/// resume).
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct StringStamped {
    /// Stamp.
    pub header: Header,
    /// The command.
    pub string: String,
}

/// `sensor_msgs/msg/Image`.
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Image {
    /// Stamp and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// Pixel encoding, e.g. "rgb8".
    pub encoding: String,
    /// Whether multi-byte pixels are big-endian.
    pub is_bigendian: u8,
    /// Bytes per row.
    pub step: u32,
    /// `step · height` bytes.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/RegionOfInterest`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    /// Left edge, pixels.
    pub x_offset: u32,
    /// Top edge, pixels.
    pub y_offset: u32,
    /// Height, pixels.
    pub height: u32,
    /// Width, pixels.
    pub width: u32,
    /// Whether a rectified image is wanted.
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    /// Stamp and camera frame.
    pub header: Header,
    /// Rows.
    pub height: u32,
    /// Columns.
    pub width: u32,
    /// "plumb_bob", ...
    pub distortion_model: String,
    /// Distortion coefficients.
    pub d: Vec<f64>,
    /// Intrinsics, row-major 3×3.
    pub k: [f64; 9],
    /// Rectification, row-major 3×3.
    pub r: [f64; 9],
    /// Projection, row-major 3×4 (for the right camera of a pair, P[0][3] = −fx·B).
    pub p: [f64; 12],
    /// Binning along x.
    pub binning_x: u32,
    /// Binning along y.
    pub binning_y: u32,
    /// Region of interest.
    pub roi: RegionOfInterest,
}

/// `std_msgs/msg/Float64`: the dVRK's `trajectory_j/set_ratio` (the fraction, 0 to 1, of
/// the arm's maximum joint speed and acceleration its trajectories use).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Float64 {
    /// The value.
    pub data: f64,
}
