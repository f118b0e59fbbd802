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

const TIME_MSG: &str = "int32 sec\nuint32 nanosec\n";

/// One channel of a recorded run.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Channel {
    /// Topic.
    pub topic: &'static str,
    /// ROS 2 type, `pkg/msg/Type`.
    pub schema: &'static str,
    /// The type's `.msg` text.
    pub msg: &'static str,
    /// `offered_qos_profiles`, in the integer form Humble writes (read by Humble, Jazzy and
    /// `rosbags`): reliable, keep last, transient local (events are latched state of a run).
    pub qos: &'static str,
}

const EVENT_QOS: &str = "- history: 1\n  depth: 1000\n  reliability: 1\n  durability: 1\n  \
deadline:\n    sec: 0\n    nsec: 0\n  lifespan:\n    sec: 0\n    nsec: 0\n  liveliness: 1\n  \
liveliness_lease_duration:\n    sec: 0\n    nsec: 0\n  avoid_ros_namespace_conventions: false\n";

/// Every channel a recording has, in the order they are added.
pub const CHANNELS: [Channel; 2] = [
    Channel {
        topic: "/stitch/events",
        schema: "stitch_msgs/msg/Event",
        msg: include_str!("../msg/Event.msg"),
        qos: EVENT_QOS,
    },
    Channel {
        topic: "/stitch/transitions",
        schema: "stitch_msgs/msg/Transition",
        msg: include_str!("../msg/Transition.msg"),
        qos: EVENT_QOS,
    },
];

/// The `ros2msg` schema text of `channel`'s type: its definition, then each dependency's.
pub fn schema_text(channel: &Channel) -> String {
    let rule = "=".repeat(80);
    format!(
        "{}\n{rule}\nMSG: builtin_interfaces/Time\n{TIME_MSG}",
        channel.msg.trim_end()
    )
}

/// A run time, s, as a ROS stamp (run times are never negative).
pub(crate) fn stamp(t_s: f64) -> Time {
    let ns = nanos(t_s);
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
