//! The crate's one error type.

use serde::Serialize;

/// What can go wrong at the hardware seam. Messages say which arm, what, and in which units.
#[derive(Clone, Debug, PartialEq, Serialize, thiserror::Error)]
#[non_exhaustive]
pub enum RobotError {
    /// A goal outside the workspace box (under the error policy).
    #[error(
        "{arm}: goal ({:.4}, {:.4}, {:.4}) m is outside the workspace box min ({:.4}, {:.4}, {:.4}) max ({:.4}, {:.4}, {:.4}) m",
        position[0], position[1], position[2], min[0], min[1], min[2], max[0], max[1], max[2]
    )]
    OutOfWorkspace {
        /// The arm.
        arm: String,
        /// The goal position, m.
        position: [f64; 3],
        /// The box's lower corner, m.
        min: [f64; 3],
        /// The box's upper corner, m.
        max: [f64; 3],
    },
    /// A command faster than the speed limit (under the error policy).
    #[error("{arm}: commanded {what} speed {speed:.4} exceeds the limit {limit:.4} ({unit})")]
    TooFast {
        /// The arm.
        arm: String,
        /// "linear" or "angular".
        what: &'static str,
        /// The commanded speed.
        speed: f64,
        /// The limit.
        limit: f64,
        /// "m/s" or "rad/s".
        unit: &'static str,
    },
    /// A pose or value that is NaN or infinite.
    #[error("{arm}: {what} is not finite")]
    NonFinite {
        /// The arm or device.
        arm: String,
        /// What was not finite.
        what: String,
    },
    /// A motion that did not finish in time.
    #[error("{arm}: motion did not finish within {after_s:.3} s")]
    Timeout {
        /// The arm.
        arm: String,
        /// The time waited, s.
        after_s: f64,
    },
    /// A measurement too old to act on.
    #[error("{arm}: measurement is {age_s:.3} s old")]
    Stale {
        /// The arm.
        arm: String,
        /// Its age, s.
        age_s: f64,
    },
    /// The robot reported a fault.
    #[error("{arm}: fault: {message}")]
    Fault {
        /// The arm.
        arm: String,
        /// The robot's message.
        message: String,
    },
    /// The backend cannot do this.
    #[error("unsupported: {what}")]
    Unsupported {
        /// What was asked.
        what: String,
    },
    /// A configuration value that cannot be used.
    #[error("invalid {what}: {why}")]
    InvalidConfig {
        /// Which setting.
        what: String,
        /// Why.
        why: String,
    },
}
