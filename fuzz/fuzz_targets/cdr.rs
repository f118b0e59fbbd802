//! A serialised ROS 2 message, any bytes, as every type stitch receives or reads back:
//! decoded (either byte order) and then checked as the receiver checks it, or refused with a
//! clear error, never a panic nor an allocation the bytes alone ask for.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stitch_dvrk::msg::{
    CameraInfo, Empty, Float64, Image, JointState, OperatingState, PoseStamped, StringMsg,
    StringStamped,
};
use stitch_dvrk::{camera, decode, pose_from_msg};
use stitch_robot::Pose;

fuzz_target!(|data: &[u8]| {
    let Some((&which, bytes)) = data.split_first() else {
        return;
    };
    match which % 12 {
        0 => {
            if let Ok(m) = decode::<PoseStamped>(bytes, "geometry_msgs/msg/PoseStamped") {
                let _ = pose_from_msg(&m);
            }
        }
        1 => {
            let _ = decode::<JointState>(bytes, "sensor_msgs/msg/JointState");
        }
        2 => {
            let _ = decode::<OperatingState>(bytes, "crtk_msgs/msg/OperatingState");
        }
        3 => {
            let _ = decode::<StringMsg>(bytes, "std_msgs/msg/String");
        }
        4 => {
            let _ = decode::<StringStamped>(bytes, "crtk_msgs/msg/StringStamped");
        }
        5 => {
            let _ = decode::<Empty>(bytes, "std_msgs/msg/Empty");
        }
        6 => {
            let _ = decode::<Float64>(bytes, "std_msgs/msg/Float64");
        }
        7 => {
            if let Ok(m) = decode::<Image>(bytes, "sensor_msgs/msg/Image") {
                let _ = camera::rgb_from_image(&m, "/fuzz/image");
            }
        }
        8 => {
            // Two infos back to back: the left's length first (u16, little-endian).
            let Some((len, rest)) = bytes.split_first_chunk::<2>() else {
                return;
            };
            let n = usize::from(u16::from_le_bytes(*len)).min(rest.len());
            let (l, r) = rest.split_at(n);
            let info = |b| decode::<CameraInfo>(b, "sensor_msgs/msg/CameraInfo");
            if let (Ok(l), Ok(r)) = (info(l), info(r)) {
                if let Ok(c) = camera::calibration_from_info(&l, &r, Pose::identity()) {
                    assert!(c.validate().is_ok(), "{c:?}");
                }
            }
        }
        9 => {
            let _ = decode::<stitch_recorder::Event>(bytes, "stitch_msgs/msg/Event");
        }
        10 => {
            let _ =
                decode::<stitch_recorder::NeedleEstimate>(bytes, "stitch_msgs/msg/NeedleEstimate");
        }
        _ => {
            let _ = decode::<stitch_recorder::StepEnd>(bytes, "stitch_msgs/msg/StepEnd");
        }
    }
});
