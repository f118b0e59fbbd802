//! A stereo calibration file (`stitch perceive --calib`) or a dVRK settings file
//! (`--dvrk-config`), any text: a checked value or a clear error, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stitch_dvrk::arm::DvrkConfig;

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    if let Ok(c) = stitch_cli::inputs::calibration(text) {
        // What it accepted is usable: finite, and valid by the pipeline's own check.
        assert!(c.validate().is_ok());
    }
    if let Ok(c) = toml::from_str::<DvrkConfig>(text) {
        let _ = c.validate();
    }
});
