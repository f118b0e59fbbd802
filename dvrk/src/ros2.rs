//! The ROS 2 side, over `ros2-client` (pure-Rust DDS): contexts on a chosen domain and the
//! QoS profiles the dVRK's CRTK topics use. The arm and jaw backend builds on this.

use ros2_client::{
    Context, ContextOptions, QosProfile,
    qos::{Durability, History, WhenFull},
};

/// Where to meet the dVRK.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Ros2Options {
    /// `ROS_DOMAIN_ID`, 0 to 232.
    pub domain_id: u16,
}

impl Ros2Options {
    /// From the environment: `ROS_DOMAIN_ID` (default 0); a bad value is an error naming it.
    pub fn from_env() -> Result<Self, String> {
        match std::env::var("ROS_DOMAIN_ID") {
            Err(_) => Ok(Self { domain_id: 0 }),
            Ok(v) => match v.trim().parse::<u16>() {
                Ok(d) if d <= 232 => Ok(Self { domain_id: d }),
                _ => Err(format!("ROS_DOMAIN_ID={v:?}: expected 0 to 232")),
            },
        }
    }
}

/// A DDS participant on the options' domain.
pub fn context(options: &Ros2Options) -> Result<Context, String> {
    Context::with_options(ContextOptions::new().domain_id(options.domain_id))
        .map_err(|e| format!("cannot join ROS 2 domain {}: {e:?}", options.domain_id))
}

/// State the dVRK latches (`operating_state`): reliable and transient-local, so a late
/// subscriber still gets the last one.
pub fn latched_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// Commands and measured state streams (`move_cp`, `measured_cp`, ...): reliable, the
/// latest few.
pub fn stream_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .history(History::KeepLast { depth: 10 })
}
