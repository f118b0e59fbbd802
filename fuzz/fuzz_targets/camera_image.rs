//! `sensor_msgs/Image` as a ROS 2 camera sends it, any fields: converted to RGB or refused
//! with a clear error, never a panic or an allocation the fields alone ask for.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stitch_dvrk::camera::rgb_from_image;
use stitch_dvrk::msg::Image;

const ENCODINGS: [&str; 6] = ["rgb8", "bgr8", "rgba8", "bgra8", "mono8", "16UC1"];

fuzz_target!(|data: &[u8]| {
    if data.len() < 13 {
        return;
    }
    let u32_at = |i: usize| u32::from_le_bytes([data[i], data[i + 1], data[i + 2], data[i + 3]]);
    let m = Image {
        encoding: ENCODINGS[usize::from(data[0]) % ENCODINGS.len()].to_string(),
        // Small sizes mostly (so the data can match them), any size sometimes.
        width: if data[1] & 1 == 0 {
            u32_at(1) % 64
        } else {
            u32_at(1)
        },
        height: if data[5] & 1 == 0 {
            u32_at(5) % 64
        } else {
            u32_at(5)
        },
        step: if data[9] & 1 == 0 {
            u32_at(9) % 512
        } else {
            u32_at(9)
        },
        data: data[13..].to_vec(),
        ..Image::default()
    };
    if let Ok(img) = rgb_from_image(&m, "/fuzz/image") {
        assert_eq!(img.data.len(), img.width as usize * img.height as usize * 3);
    }
});
