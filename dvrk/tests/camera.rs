//! The stereo camera over real DDS, as a real camera driver streams it (no trigger): a fake
//! driver publishes left/right images and camera info at 30 Hz on this test's own domain, and
//! `Ros2Camera` reads the calibration, captures pairs, and refuses what it must.
#![cfg(feature = "ros2")]

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU8, Ordering};
use std::time::{Duration, Instant};
use stitch_dvrk::camera::{self, CameraSettings, Ros2Camera};
use stitch_dvrk::msg::{CameraInfo, Image, Time};
use stitch_dvrk::ros2::{Bus, Ros2Options, now_stamp, types};
use stitch_robot::{
    Pose, RgbImage, RobotError, SimClock, StereoCalibration, StereoCamera, nalgebra,
};

/// What the fake driver does.
const STREAM: u8 = 0;
const INFO_ONLY: u8 = 1;
const ZERO_STAMPS: u8 = 2;
const STALE_STAMPS: u8 = 3;
const NEW_CALIBRATION: u8 = 4;

fn calibration() -> StereoCalibration {
    StereoCalibration {
        fx: 410.5,
        fy: 409.25,
        cx: 31.5,
        cy: 23.75,
        baseline_m: 0.0052,
        width: 64,
        height: 48,
        camera_to_robot: Pose::identity(),
    }
}

/// A bgr8 image with 8 bytes of padding a row: pixel (x, y) is (b, g, r) = (x, y, side).
fn bgr_image(c: &StereoCalibration, side: u8, stamp: Time) -> Image {
    let step = c.width * 3 + 8;
    let mut data = vec![0xEE; (step * c.height) as usize];
    for y in 0..c.height {
        for x in 0..c.width {
            let at = (y * step + x * 3) as usize;
            data[at..at + 3].copy_from_slice(&[x as u8, y as u8, side]);
        }
    }
    Image {
        header: stitch_dvrk::msg::Header {
            stamp,
            frame_id: "cam".into(),
        },
        height: c.height,
        width: c.width,
        encoding: "bgr8".into(),
        is_bigendian: 0,
        step,
        data,
    }
}

/// A camera driver on its own participant, streaming at 30 Hz until dropped.
struct FakeDriver {
    mode: Arc<AtomicU8>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl FakeDriver {
    fn start(options: Ros2Options, mode: u8) -> Self {
        let mode = Arc::new(AtomicU8::new(mode));
        let stop = Arc::new(AtomicBool::new(false));
        let (m, s) = (Arc::clone(&mode), Arc::clone(&stop));
        let thread = std::thread::spawn(move || {
            let settings = CameraSettings::default();
            let mut bus = Bus::new(&options, "fake_camera").expect("bus");
            let q = camera::publisher_qos();
            let images: [stitch_dvrk::ros2::Topic<Image>; 2] = [
                bus.publisher(&settings.left_image, types::IMAGE, &q)
                    .expect("left"),
                bus.publisher(&settings.right_image, types::IMAGE, &q)
                    .expect("right"),
            ];
            let infos: [stitch_dvrk::ros2::Topic<CameraInfo>; 2] = [
                bus.publisher(&settings.left_info, types::CAMERA_INFO, &q)
                    .expect("left info"),
                bus.publisher(&settings.right_info, types::CAMERA_INFO, &q)
                    .expect("right info"),
            ];
            while !s.load(Ordering::SeqCst) {
                let mode = m.load(Ordering::SeqCst);
                let mut c = calibration();
                if mode == NEW_CALIBRATION {
                    c.fx += 20.0;
                }
                let stamp = match mode {
                    ZERO_STAMPS => Time::default(),
                    STALE_STAMPS => {
                        let mut t = now_stamp();
                        t.sec -= 10;
                        t
                    }
                    _ => now_stamp(),
                };
                if mode != INFO_ONLY {
                    for (i, topic) in images.iter().enumerate() {
                        topic.publish(bgr_image(&c, i as u8, stamp)).expect("image");
                    }
                }
                for (i, topic) in infos.iter().enumerate() {
                    topic
                        .publish(camera::camera_info_msg(&c, i == 1, now_stamp(), "cam"))
                        .expect("info");
                }
                std::thread::sleep(Duration::from_millis(33));
            }
        });
        Self {
            mode,
            stop,
            thread: Some(thread),
        }
    }
}

impl Drop for FakeDriver {
    fn drop(&mut self) {
        self.stop.store(true, Ordering::SeqCst);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Each test its own domain, away from the other test binaries' and runs'.
fn domain(k: u16) -> Ros2Options {
    Ros2Options {
        domain_id: 200 + (std::process::id() % 6) as u16 * 5 + k,
    }
}

fn hand_eye() -> Pose {
    Pose::from_parts(
        nalgebra::Translation3::new(0.02, 0.13, 0.0),
        nalgebra::UnitQuaternion::from_euler_angles(2.3, 0.0, 0.1),
    )
}

fn connect(options: &Ros2Options) -> Result<Ros2Camera, RobotError> {
    Ros2Camera::connect(
        options,
        &CameraSettings {
            capture_timeout_s: 0.5,
            ..CameraSettings::default()
        },
        hand_eye(),
        None,
        Arc::new(SimClock::new()),
        Duration::from_secs(15),
    )
}

fn pixel(image: &RgbImage, x: u32, y: u32) -> [u8; 3] {
    let at = ((y * image.width + x) * 3) as usize;
    [image.data[at], image.data[at + 1], image.data[at + 2]]
}

#[test]
fn a_streaming_camera_gives_its_calibration_and_fresh_rgb_pairs() {
    let options = domain(0);
    let _driver = FakeDriver::start(options, STREAM);
    let camera = connect(&options).expect("connects");
    let want = StereoCalibration {
        camera_to_robot: hand_eye(),
        ..calibration()
    };
    assert_eq!(
        camera.calibration(),
        &want,
        "the baseline crosses exactly too"
    );
    for _ in 0..3 {
        let asked = Instant::now();
        let frame = camera.capture().expect("a pair");
        assert!(asked.elapsed() < Duration::from_millis(500));
        for (image, side) in [(&frame.left, 0u8), (&frame.right, 1)] {
            assert_eq!((image.width, image.height), (64, 48));
            assert_eq!(image.data.len(), 64 * 48 * 3, "the row padding is gone");
            // bgr8 (x, y, side) arrives as rgb8 (side, y, x).
            assert_eq!(pixel(image, 5, 7), [side, 7, 5]);
            assert_eq!(pixel(image, 63, 47), [side, 47, 63]);
        }
    }
}

#[test]
fn a_camera_that_sends_no_images_times_out_naming_its_topics() {
    let options = domain(1);
    let _driver = FakeDriver::start(options, INFO_ONLY);
    let camera = connect(&options).expect("camera_info is enough to connect");
    let asked = Instant::now();
    let e = camera.capture().expect_err("no images");
    let waited = asked.elapsed();
    let text = e.to_string();
    assert!(
        text.contains("no fresh, matching pair within 0.5 s"),
        "{text}"
    );
    assert!(
        text.contains("nothing on /stereo/left/image_rect_color"),
        "{text}"
    );
    assert!(waited >= Duration::from_millis(500), "{waited:?}");
}

#[test]
fn zero_and_stale_stamps_and_a_changed_calibration_are_refused() {
    let options = domain(2);
    let driver = FakeDriver::start(options, STREAM);
    let camera = connect(&options).expect("connects");
    // The driver changes what it sends; a few frames go by.
    let switch = |mode: u8| {
        driver.mode.store(mode, Ordering::SeqCst);
        std::thread::sleep(Duration::from_millis(100));
    };
    camera.capture().expect("a good pair first");
    switch(ZERO_STAMPS);
    let e = camera.capture().expect_err("zero stamps").to_string();
    assert!(e.contains("zero stamp"), "{e}");
    switch(STALE_STAMPS);
    match camera.capture() {
        Err(RobotError::Stale { age_s, .. }) => assert!(age_s > 9.0, "{age_s}"),
        other => panic!("expected stale, got {other:?}"),
    }
    switch(NEW_CALIBRATION);
    let e = camera.capture().expect_err("recalibrated").to_string();
    assert!(e.contains("calibration changed"), "{e}");
    switch(STREAM);
    camera.capture().expect("good again");
}

#[test]
fn no_camera_info_fails_the_connection_naming_topics_and_domain() {
    let options = domain(3);
    let started = Instant::now();
    let e = Ros2Camera::connect(
        &options,
        &CameraSettings::default(),
        hand_eye(),
        None,
        Arc::new(SimClock::new()),
        Duration::from_millis(700),
    )
    .expect_err("nothing there")
    .to_string();
    assert!(
        e.contains("/stereo/left/camera_info and /stereo/right/camera_info"),
        "{e}"
    );
    assert!(
        e.contains(&format!("ROS_DOMAIN_ID {}", options.domain_id)),
        "{e}"
    );
    assert!(started.elapsed() < Duration::from_secs(5));
}
