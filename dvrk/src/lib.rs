#![doc = include_str!("../README.md")]

#[cfg(feature = "ros2")]
pub mod arm;
#[cfg(feature = "ros2")]
pub mod camera;
pub mod msg;
#[cfg(feature = "sim-node")]
pub mod oracle;
#[cfg(feature = "ros2")]
pub mod ros2;
#[cfg(feature = "sim-node")]
pub mod sim_node;

use serde::Serialize;
use serde::de::DeserializeOwned;

/// The RTPS encapsulation header of little-endian plain CDR (`CDR_LE`): what ROS 2 puts
/// before every serialised message.
pub const CDR_LE: [u8; 4] = [0x00, 0x01, 0x00, 0x00];
/// The same for big-endian CDR (`CDR_BE`), which peers may send.
pub const CDR_BE: [u8; 4] = [0x00, 0x00, 0x00, 0x00];

/// Why a message cannot be encoded or decoded.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum WireError {
    /// Fewer bytes than the encapsulation header.
    #[error("message of {len} bytes is shorter than its 4-byte encapsulation header")]
    Truncated {
        /// Bytes received.
        len: usize,
    },
    /// An encapsulation this backend does not read (e.g. XCDR2, parameter lists).
    #[error("unsupported CDR encapsulation {0:02x?}; expected plain CDR (00 00 or 00 01)")]
    Encapsulation([u8; 2]),
    /// The payload does not decode as the message type.
    #[error("cannot decode {type_name}: {reason}")]
    Decode {
        /// The ROS type.
        type_name: &'static str,
        /// What the decoder said.
        reason: String,
    },
    /// The message does not encode (a length over CDR's limits).
    #[error("cannot encode {type_name}: {reason}")]
    Encode {
        /// The ROS type.
        type_name: &'static str,
        /// What the encoder said.
        reason: String,
    },
}

/// Encode `msg` as ROS 2 does: the `CDR_LE` header, then the little-endian CDR payload.
pub fn encode<T: Serialize>(msg: &T, type_name: &'static str) -> Result<Vec<u8>, WireError> {
    let payload =
        cdr_encoding::to_vec::<T, byteorder::LittleEndian>(msg).map_err(|e| WireError::Encode {
            type_name,
            reason: e.to_string(),
        })?;
    let mut out = Vec::with_capacity(4 + payload.len());
    out.extend_from_slice(&CDR_LE);
    out.extend_from_slice(&payload);
    Ok(out)
}

/// Decode a serialised ROS 2 message of either byte order; never panics on bad input.
pub fn decode<T: DeserializeOwned>(bytes: &[u8], type_name: &'static str) -> Result<T, WireError> {
    if bytes.len() < 4 {
        return Err(WireError::Truncated { len: bytes.len() });
    }
    let payload = &bytes[4..];
    let err = |e: cdr_encoding::Error| WireError::Decode {
        type_name,
        reason: e.to_string(),
    };
    match [bytes[0], bytes[1]] {
        [0x00, 0x01] => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(payload)
            .map(|(v, _)| v)
            .map_err(err),
        [0x00, 0x00] => cdr_encoding::from_bytes::<T, byteorder::BigEndian>(payload)
            .map(|(v, _)| v)
            .map_err(err),
        other => Err(WireError::Encapsulation(other)),
    }
}

/// A measured pose in the robot frame, checked: a zero stamp (CRTK's "invalid") or a
/// non-finite or non-unit quaternion is refused.
pub fn pose_from_msg(m: &msg::PoseStamped) -> Result<stitch_robot::Pose, String> {
    if m.header.stamp.is_zero() {
        return Err("zero stamp (the dVRK marks invalid data so)".into());
    }
    let p = m.pose.position;
    let q = m.pose.orientation;
    let values = [p.x, p.y, p.z, q.x, q.y, q.z, q.w];
    if !values.iter().all(|v| v.is_finite()) {
        return Err(format!("non-finite pose {values:?}"));
    }
    let norm = (q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w).sqrt();
    if (norm - 1.0).abs() > 1e-3 {
        return Err(format!("quaternion of norm {norm:.4}, not a rotation"));
    }
    use stitch_robot::nalgebra::{Quaternion, Translation3, UnitQuaternion};
    let q = Quaternion::new(q.w, q.x, q.y, q.z);
    // A quaternion that was unit where it was sent is taken as it is, so a pose crosses the
    // wire bit for bit; one a little off is normalised.
    let rotation = if (norm - 1.0).abs() <= 1e-12 {
        UnitQuaternion::new_unchecked(q)
    } else {
        UnitQuaternion::from_quaternion(q)
    };
    Ok(stitch_robot::Pose::from_parts(
        Translation3::new(p.x, p.y, p.z),
        rotation,
    ))
}

/// A pose command's message, stamped `stamp`.
pub fn pose_to_msg(
    pose: &stitch_robot::Pose,
    stamp: msg::Time,
    frame_id: &str,
) -> msg::PoseStamped {
    let t = pose.translation.vector;
    let q = pose.rotation.quaternion();
    msg::PoseStamped {
        header: msg::Header {
            stamp,
            frame_id: frame_id.to_string(),
        },
        pose: msg::Pose {
            position: msg::Point {
                x: t.x,
                y: t.y,
                z: t.z,
            },
            orientation: msg::Quaternion {
                x: q.i,
                y: q.j,
                z: q.k,
                w: q.w,
            },
        },
    }
}
