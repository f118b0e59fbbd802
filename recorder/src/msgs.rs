//! The `stitch_msgs` messages a run is recorded as, in their ROS 2 definitions' field order
//! (the CDR layout), and the `ros2msg` schema text of each (its `.msg` file, then each
//! dependency after a line of 80 `=`, as ROS 2 writes them).

use serde::{Deserialize, Serialize};
use stitch_dvrk::msg::Time;

/// `stitch_msgs/msg/Event` (`recorder/msg/Event.msg`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Event {
    /// Run time since the run began.
    pub stamp: Time,
    /// The journal's sequence number.
    pub seq: u64,
    /// The event's kind (`transition`, `step_end`, ...).
    pub event: String,
    /// The journal record as JSON.
    pub record_json: String,
}

/// `stitch_msgs/msg/Transition` (`recorder/msg/Transition.msg`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Transition {
    /// Run time since the run began.
    pub stamp: Time,
    /// The journal's sequence number.
    pub seq: u64,
    /// Source state.
    pub from_state: String,
    /// Target state.
    pub to_state: String,
}

/// `stitch_msgs/msg/StepEnd` (`recorder/msg/StepEnd.msg`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StepEnd {
    /// Run time since the run began.
    pub stamp: Time,
    /// The journal's sequence number.
    pub seq: u64,
    /// Throw, from 0.
    pub throw_index: u32,
    /// Step, from 0.
    pub step: u32,
    /// Attempt, from 0.
    pub attempt: u32,
    /// The step's name.
    pub primitive: String,
    /// Whether it succeeded.
    pub ok: bool,
    /// The failure's kind, empty on success.
    pub failure: String,
    /// Entry error, m (NaN: not measured).
    pub entry_error_m: f64,
    /// Exit error, m.
    pub exit_error_m: f64,
    /// Endpoint travel, m.
    pub endpoint_travel_m: f64,
    /// Normal change, rad.
    pub normal_change_rad: f64,
    /// Thread used, m.
    pub thread_used_m: f64,
    /// Thread left, m.
    pub thread_left_m: f64,
    /// A handover's thread clearance at the blades, m.
    pub thread_clearance_m: f64,
}

/// `stitch_msgs/msg/NeedleEstimate` (`recorder/msg/NeedleEstimate.msg`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct NeedleEstimate {
    /// Run time when it was asked.
    pub stamp: Time,
    /// The step that asked (`t0 s2 insert a0`), empty outside a step.
    pub step: String,
    /// Where the estimator was told to look.
    pub hint: String,
    /// Whether there is an estimate.
    pub ok: bool,
    /// The needle frame in the robot frame, m (identity without an estimate).
    pub pose: stitch_dvrk::msg::Pose,
    /// Confidence, 0 to 1.
    pub confidence: f64,
    /// When its images were taken, run time.
    pub image_stamp: Time,
    /// The typed failure as JSON, empty when ok.
    pub failure: String,
}

/// `stitch_msgs/msg/ThreadTrace` (`recorder/msg/ThreadTrace.msg`).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct ThreadTrace {
    /// Run time when it was asked.
    pub stamp: Time,
    /// The step that asked, empty outside a step.
    pub step: String,
    /// Whether `start` was given (false before the first stitch).
    pub has_start: bool,
    /// The last stitch's exit point, robot frame, m (zero when not given).
    pub start: stitch_dvrk::msg::Point,
    /// The needle's swage, robot frame, m.
    pub swage: stitch_dvrk::msg::Point,
    /// The length prior, m (NaN: none).
    pub length_prior_m: f64,
    /// Whether there is a trace.
    pub ok: bool,
    /// The fitted curve, robot frame, m.
    pub points: Vec<stitch_dvrk::msg::Point>,
    /// Each point's uncertainty, m.
    pub sigma_m: Vec<f64>,
    /// The curve's length, m.
    pub length_m: f64,
    /// Where each hidden stretch begins, m along the curve.
    pub hidden_from_m: Vec<f64>,
    /// Where each hidden stretch ends, m along the curve.
    pub hidden_to_m: Vec<f64>,
    /// The share of the left-image path that was thread.
    pub seen_share: f64,
    /// Points matched between the two views.
    pub matched: u32,
    /// The typed failure as JSON, empty when ok.
    pub failure: String,
}

/// `nav_msgs/msg/Path`: a traced thread as a line Foxglove's 3D panel draws.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Path {
    /// Stamp and frame.
    pub header: stitch_dvrk::msg::Header,
    /// The points, each as a pose (identity orientation).
    pub poses: Vec<stitch_dvrk::msg::PoseStamped>,
}

/// `rcl_interfaces/msg/Log`: what `/rosout` carries (errors, warnings, notes of a run).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Log {
    /// When.
    pub stamp: Time,
    /// [`Log::ERROR`], [`Log::WARN`], [`Log::INFO`].
    pub level: u8,
    /// Who: an arm (`PSM1`), `estimator`, `recorder`.
    pub name: String,
    /// What.
    pub msg: String,
    /// Source file (empty: not a source location).
    pub file: String,
    /// Source function (empty).
    pub function: String,
    /// Source line (0).
    pub line: u32,
}

impl Log {
    /// Information.
    pub const INFO: u8 = 20;
    /// A warning.
    pub const WARN: u8 = 30;
    /// An error.
    pub const ERROR: u8 = 40;
}

/// `sensor_msgs/msg/CompressedImage`: a recorded camera frame (JPEG).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompressedImage {
    /// Stamp and camera frame.
    pub header: stitch_dvrk::msg::Header,
    /// `jpeg`.
    pub format: String,
    /// The encoded image.
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `foxglove_msgs/msg/Point2`: a point in an image, pixels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Point2 {
    /// Column, pixels.
    pub x: f64,
    /// Row, pixels.
    pub y: f64,
}

/// `foxglove_msgs/msg/Color`, 0 to 1.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct Color {
    /// Red.
    pub r: f64,
    /// Green.
    pub g: f64,
    /// Blue.
    pub b: f64,
    /// Opacity.
    pub a: f64,
}

/// `foxglove_msgs/msg/CircleAnnotation`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct CircleAnnotation {
    /// The image it belongs to.
    pub timestamp: Time,
    /// Centre, pixels.
    pub position: Point2,
    /// Diameter, pixels.
    pub diameter: f64,
    /// Line width, pixels.
    pub thickness: f64,
    /// Fill.
    pub fill_color: Color,
    /// Outline.
    pub outline_color: Color,
}

/// `foxglove_msgs/msg/PointsAnnotation`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct PointsAnnotation {
    /// The image it belongs to.
    pub timestamp: Time,
    /// [`PointsAnnotation::LINE_STRIP`], ...
    #[serde(rename = "type")]
    pub kind: u8,
    /// The points, pixels.
    pub points: Vec<Point2>,
    /// Line colour.
    pub outline_color: Color,
    /// Per-point colours (none: `outline_color`).
    pub outline_colors: Vec<Color>,
    /// Fill.
    pub fill_color: Color,
    /// Line width, pixels.
    pub thickness: f64,
}

impl PointsAnnotation {
    /// Consecutive points joined.
    pub const LINE_STRIP: u8 = 3;
}

/// `foxglove_msgs/msg/TextAnnotation`.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct TextAnnotation {
    /// The image it belongs to.
    pub timestamp: Time,
    /// Where, pixels.
    pub position: Point2,
    /// What.
    pub text: String,
    /// Size, pixels.
    pub font_size: f64,
    /// Text colour.
    pub text_color: Color,
    /// Background.
    pub background_color: Color,
}

/// `foxglove_msgs/msg/ImageAnnotations`: the needle estimate (and the truth, on the mock)
/// drawn on the left image, for Foxglove's Image panel.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
pub struct ImageAnnotations {
    /// Circles.
    pub circles: Vec<CircleAnnotation>,
    /// Lines and points.
    pub points: Vec<PointsAnnotation>,
    /// Labels.
    pub texts: Vec<TextAnnotation>,
}

/// A message type of a recording: its ROS 2 name and `.msg` text, and the types it uses.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct MsgType {
    /// `pkg/msg/Type`.
    pub name: &'static str,
    /// The `.msg` definition.
    pub msg: &'static str,
    /// The types its fields use, directly or not, each once.
    pub uses: &'static [&'static MsgType],
}

/// `builtin_interfaces/msg/Time`.
pub static TIME: MsgType = MsgType {
    name: "builtin_interfaces/msg/Time",
    msg: "int32 sec\nuint32 nanosec\n",
    uses: &[],
};
/// `std_msgs/msg/Header`.
pub static HEADER: MsgType = MsgType {
    name: "std_msgs/msg/Header",
    msg: "builtin_interfaces/Time stamp\nstring frame_id\n",
    uses: &[&TIME],
};
/// `geometry_msgs/msg/Point`.
pub static POINT: MsgType = MsgType {
    name: "geometry_msgs/msg/Point",
    msg: "float64 x\nfloat64 y\nfloat64 z\n",
    uses: &[],
};
/// `geometry_msgs/msg/Quaternion`.
pub static QUATERNION: MsgType = MsgType {
    name: "geometry_msgs/msg/Quaternion",
    msg: "float64 x 0\nfloat64 y 0\nfloat64 z 0\nfloat64 w 1\n",
    uses: &[],
};
/// `geometry_msgs/msg/Pose`.
pub static POSE: MsgType = MsgType {
    name: "geometry_msgs/msg/Pose",
    msg: "geometry_msgs/Point position\ngeometry_msgs/Quaternion orientation\n",
    uses: &[&POINT, &QUATERNION],
};
/// `geometry_msgs/msg/PoseStamped`: poses measured, set and commanded.
pub static POSE_STAMPED: MsgType = MsgType {
    name: "geometry_msgs/msg/PoseStamped",
    msg: "std_msgs/Header header\ngeometry_msgs/Pose pose\n",
    uses: &[&HEADER, &TIME, &POSE, &POINT, &QUATERNION],
};
/// `sensor_msgs/msg/JointState`: jaw openings measured and commanded.
pub static JOINT_STATE: MsgType = MsgType {
    name: "sensor_msgs/msg/JointState",
    msg: "std_msgs/Header header\nstring[] name\nfloat64[] position\nfloat64[] velocity\n\
          float64[] effort\n",
    uses: &[&HEADER, &TIME],
};
/// `crtk_msgs/msg/OperatingState`: an arm's state on a dVRK.
pub static OPERATING_STATE: MsgType = MsgType {
    name: "crtk_msgs/msg/OperatingState",
    msg: "std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
    uses: &[&HEADER, &TIME],
};
/// `rcl_interfaces/msg/Log`.
pub static LOG: MsgType = MsgType {
    name: "rcl_interfaces/msg/Log",
    msg: "byte DEBUG=10\nbyte INFO=20\nbyte WARN=30\nbyte ERROR=40\nbyte FATAL=50\n\
          builtin_interfaces/Time stamp\nuint8 level\nstring name\nstring msg\nstring file\n\
          string function\nuint32 line\n",
    uses: &[&TIME],
};
/// `sensor_msgs/msg/CompressedImage`.
pub static COMPRESSED_IMAGE: MsgType = MsgType {
    name: "sensor_msgs/msg/CompressedImage",
    msg: "std_msgs/Header header\nstring format\nuint8[] data\n",
    uses: &[&HEADER, &TIME],
};
/// `stitch_msgs/msg/Event`.
pub static EVENT: MsgType = MsgType {
    name: "stitch_msgs/msg/Event",
    msg: include_str!("../msg/Event.msg"),
    uses: &[&TIME],
};
/// `stitch_msgs/msg/Transition`.
pub static TRANSITION: MsgType = MsgType {
    name: "stitch_msgs/msg/Transition",
    msg: include_str!("../msg/Transition.msg"),
    uses: &[&TIME],
};
/// `foxglove_msgs/msg/Point2`.
pub static POINT2: MsgType = MsgType {
    name: "foxglove_msgs/msg/Point2",
    msg: "float64 x\nfloat64 y\n",
    uses: &[],
};
/// `foxglove_msgs/msg/Color`.
pub static COLOR: MsgType = MsgType {
    name: "foxglove_msgs/msg/Color",
    msg: "float64 r\nfloat64 g\nfloat64 b\nfloat64 a\n",
    uses: &[],
};
/// `foxglove_msgs/msg/CircleAnnotation`.
pub static CIRCLE_ANNOTATION: MsgType = MsgType {
    name: "foxglove_msgs/msg/CircleAnnotation",
    msg: "builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\nfloat64 diameter\n\
          float64 thickness\nfoxglove_msgs/Color fill_color\nfoxglove_msgs/Color outline_color\n",
    uses: &[&TIME, &POINT2, &COLOR],
};
/// `foxglove_msgs/msg/PointsAnnotation`.
pub static POINTS_ANNOTATION: MsgType = MsgType {
    name: "foxglove_msgs/msg/PointsAnnotation",
    msg: "builtin_interfaces/Time timestamp\nuint8 UNKNOWN=0\nuint8 POINTS=1\nuint8 LINE_LOOP=2\n\
          uint8 LINE_STRIP=3\nuint8 LINE_LIST=4\nuint8 type\nfoxglove_msgs/Point2[] points\n\
          foxglove_msgs/Color outline_color\nfoxglove_msgs/Color[] outline_colors\n\
          foxglove_msgs/Color fill_color\nfloat64 thickness\n",
    uses: &[&TIME, &POINT2, &COLOR],
};
/// `foxglove_msgs/msg/TextAnnotation`.
pub static TEXT_ANNOTATION: MsgType = MsgType {
    name: "foxglove_msgs/msg/TextAnnotation",
    msg: "builtin_interfaces/Time timestamp\nfoxglove_msgs/Point2 position\nstring text\n\
          float64 font_size\nfoxglove_msgs/Color text_color\nfoxglove_msgs/Color background_color\n",
    uses: &[&TIME, &POINT2, &COLOR],
};
/// `foxglove_msgs/msg/ImageAnnotations`.
pub static IMAGE_ANNOTATIONS: MsgType = MsgType {
    name: "foxglove_msgs/msg/ImageAnnotations",
    msg: "foxglove_msgs/CircleAnnotation[] circles\nfoxglove_msgs/PointsAnnotation[] points\n\
          foxglove_msgs/TextAnnotation[] texts\n",
    uses: &[
        &CIRCLE_ANNOTATION,
        &POINTS_ANNOTATION,
        &TEXT_ANNOTATION,
        &TIME,
        &POINT2,
        &COLOR,
    ],
};
/// `stitch_msgs/msg/StepEnd`.
pub static STEP_END: MsgType = MsgType {
    name: "stitch_msgs/msg/StepEnd",
    msg: include_str!("../msg/StepEnd.msg"),
    uses: &[&TIME],
};
/// `stitch_msgs/msg/NeedleEstimate`.
pub static NEEDLE_ESTIMATE: MsgType = MsgType {
    name: "stitch_msgs/msg/NeedleEstimate",
    msg: include_str!("../msg/NeedleEstimate.msg"),
    uses: &[&TIME, &POSE, &POINT, &QUATERNION],
};
/// `stitch_msgs/msg/ThreadTrace`.
pub static THREAD_TRACE: MsgType = MsgType {
    name: "stitch_msgs/msg/ThreadTrace",
    msg: include_str!("../msg/ThreadTrace.msg"),
    uses: &[&TIME, &POINT],
};
/// `nav_msgs/msg/Path`.
pub static PATH: MsgType = MsgType {
    name: "nav_msgs/msg/Path",
    msg: "std_msgs/Header header\ngeometry_msgs/PoseStamped[] poses\n",
    uses: &[&HEADER, &TIME, &POSE_STAMPED, &POSE, &POINT, &QUATERNION],
};

/// How a channel is offered, in the integer form Humble writes (read by Humble, Jazzy and
/// `rosbags`).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Qos {
    /// Reliable, keep last 1,000, transient local: the run's events, latched state.
    Latched,
    /// Reliable, keep last 100, volatile: telemetry, as the dVRK publishes it.
    Stream,
}

impl Qos {
    /// The `offered_qos_profiles` YAML.
    pub fn yaml(self) -> String {
        let (depth, durability) = match self {
            Qos::Latched => (1000, 1),
            Qos::Stream => (100, 2),
        };
        format!(
            "- history: 1\n  depth: {depth}\n  reliability: 1\n  durability: {durability}\n  \
             deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n  \
             liveliness: 1\n  liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n  \
             avoid_ros_namespace_conventions: false\n"
        )
    }
}

/// One channel of a recorded run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Channel {
    /// Topic.
    pub topic: &'static str,
    /// Its type.
    pub ty: &'static MsgType,
    /// How it is offered.
    pub qos: Qos,
}

/// The engine's channels, which every recording has; like the arms', the estimator's and the
/// cameras', each is added (with its schema) in the chunk of its first message.
pub const CHANNELS: [Channel; 3] = [
    Channel {
        topic: "/stitch/events",
        ty: &EVENT,
        qos: Qos::Latched,
    },
    Channel {
        topic: "/stitch/transitions",
        ty: &TRANSITION,
        qos: Qos::Latched,
    },
    Channel {
        topic: "/stitch/steps",
        ty: &STEP_END,
        qos: Qos::Latched,
    },
];

/// The `ros2msg` schema text of `ty`: its definition, then each type it uses after a line of
/// 80 `=` and `MSG: pkg/Type`, as ROS 2 writes them.
pub fn schema_text(ty: &MsgType) -> String {
    let rule = "=".repeat(80);
    let mut out = ty.msg.trim_end().to_string();
    out.push('\n');
    for dep in ty.uses {
        out.push_str(&format!(
            "{rule}\nMSG: {}\n{}",
            dep.name.replacen("/msg/", "/", 1),
            dep.msg
        ));
    }
    out
}

/// A pose as its ROS message.
pub fn pose_msg(p: &stitch_robot::Pose) -> stitch_dvrk::msg::Pose {
    let t = p.translation.vector;
    let q = p.rotation.quaternion();
    stitch_dvrk::msg::Pose {
        position: stitch_dvrk::msg::Point {
            x: t.x,
            y: t.y,
            z: t.z,
        },
        orientation: stitch_dvrk::msg::Quaternion {
            x: q.i,
            y: q.j,
            z: q.k,
            w: q.w,
        },
    }
}

/// A run time, s, as a ROS stamp (run times are never negative).
pub(crate) fn stamp(t_s: f64) -> Time {
    stamp_ns(nanos(t_s))
}

/// A run time, ns, as a ROS stamp.
pub(crate) fn stamp_ns(ns: u64) -> Time {
    Time {
        sec: i32::try_from(ns / 1_000_000_000).unwrap_or(i32::MAX),
        nanosec: (ns % 1_000_000_000) as u32,
    }
}

/// A run time, s, in nanoseconds (MCAP's log time).
pub(crate) fn nanos(t_s: f64) -> u64 {
    if t_s.is_finite() && t_s > 0.0 {
        (t_s * 1e9).round() as u64
    } else {
        0
    }
}
