//! Camera frames: dropped and counted on a robot when the writer is behind, waited for on a
//! simulated run.

use std::path::PathBuf;
use stitch_recorder::{Recorder, RecorderOptions, RunInfo};

fn tmp(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("stitch-recorder-frames-{}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d.join(name)
}

/// On a robot (wall-time run) a writer that cannot keep up with the camera drops frames, never
/// events or telemetry, counts them and says so; on a simulated run the camera waits and none
/// is dropped.
#[test]
fn frames_the_writer_has_no_room_for_are_dropped_and_counted_on_a_robot_only() {
    use std::sync::Arc;
    use stitch_robot::{RgbImage, SimClock, StereoCalibration, StereoFrame};
    let calibration = StereoCalibration {
        fx: 800.0,
        fy: 800.0,
        cx: 320.0,
        cy: 240.0,
        baseline_m: 0.005,
        width: 640,
        height: 480,
        camera_to_robot: stitch_robot::Pose::identity(),
    };
    let frame = StereoFrame {
        stamp: std::time::Duration::ZERO,
        left: RgbImage::new(640, 480),
        right: RgbImage::new(640, 480),
    };
    for robot in [true, false] {
        let path = tmp(&format!("frames-{robot}.mcap"));
        let options = RecorderOptions {
            wall_flush: robot,
            // Room for one pair: every pair sent while one waits has none.
            max_frame_queue_bytes: 640 * 480 * 3 * 2,
            frame_period: Some(std::time::Duration::ZERO),
        };
        let recorder = Recorder::create(&path, &RunInfo::default(), options).expect("created");
        let tap = recorder.tap(Arc::new(SimClock::new()));
        let observe = tap.frames().expect("frames are recorded");
        for _ in 0..40 {
            observe(&frame, &calibration);
            tap.log(
                stitch_recorder::Log::INFO,
                "test",
                "telemetry between frames",
            );
        }
        let stats = recorder.finish().expect("finished");
        assert_eq!(
            stats.frames + stats.frames_dropped,
            40,
            "{robot}: {stats:?}"
        );
        let got = stitch_recorder::read(&path).expect("reads");
        let meta = &got
            .metadata
            .iter()
            .find(|(n, _)| n == "stitch_recording")
            .expect("the summary metadata")
            .1;
        assert_eq!(meta["frames_dropped"], stats.frames_dropped.to_string());
        let logs = got
            .channels
            .values()
            .find(|c| c.topic == "/rosout")
            .map(|c| got.messages.iter().filter(|m| m.0 == c.id).count())
            .unwrap_or(0);
        if robot {
            assert!(
                stats.frames_dropped > 0,
                "JPEG encoding is slower than 40 sends: {stats:?}"
            );
            assert!(
                logs > 40,
                "every telemetry line kept, and the drops said: {logs}"
            );
        } else {
            assert_eq!(stats.frames_dropped, 0, "a simulated camera waits");
            assert_eq!(logs, 40);
        }
    }
}
