//! A mock dVRK configuration file, any text: parsed as `--mock-config` parses it, then every
//! part checked where a run checks it (the scene by building the mock, the noise model, the
//! camera). A clear error or a usable mock, never a panic.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stitch_robot::SimClock;
use stitch_sim::{MockDvrk, Streams};

fuzz_target!(|data: &[u8]| {
    let Ok(text) = std::str::from_utf8(data) else {
        return;
    };
    let Ok(config) = stitch_cli::inputs::mock_config(text) else {
        return;
    };
    if config.sensing.validate().is_err() || config.camera.validate().is_err() {
        return;
    }
    let _ = MockDvrk::new(&config.scene, Streams::new(1), SimClock::new());
});
