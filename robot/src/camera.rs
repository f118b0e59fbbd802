//! The stereo camera: calibrated, rectified frame pairs with a timestamp.

use crate::{Point, Pose, RobotError};
use serde::{Deserialize, Serialize};
use std::time::Duration;

/// An 8-bit RGB image, row-major, 3 bytes a pixel. A plain owned buffer so the seam pulls in
/// no imaging library; perception converts as it needs.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RgbImage {
    /// Width, pixels.
    pub width: u32,
    /// Height, pixels.
    pub height: u32,
    /// `width · height · 3` bytes.
    pub data: Vec<u8>,
}

impl RgbImage {
    /// A black image.
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            data: vec![0; width as usize * height as usize * 3],
        }
    }
}

/// Calibration of a rectified stereo pair (both images share the intrinsics).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct StereoCalibration {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point x, pixels.
    pub cx: f64,
    /// Principal point y, pixels.
    pub cy: f64,
    /// Distance between the two cameras' centres, m.
    pub baseline_m: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// The left camera's frame in the robot frame (hand-eye calibration).
    pub camera_to_robot: Pose,
}

impl StereoCalibration {
    /// Where the robot-frame point `p` falls in the left image, pixels `[column, row]`; `None`
    /// for a point not in front of the camera.
    pub fn left_pixel(&self, p: &Point) -> Option<[f64; 2]> {
        let q = self.camera_to_robot.inverse() * p;
        (q.z > 1e-6).then(|| [self.fx * q.x / q.z + self.cx, self.fy * q.y / q.z + self.cy])
    }

    /// Refuse values no camera has.
    pub fn validate(&self) -> Result<(), RobotError> {
        let bad = |why: String| {
            Err(RobotError::InvalidConfig {
                what: "stereo calibration".into(),
                why,
            })
        };
        for (name, v) in [("fx", self.fx), ("fy", self.fy)] {
            if !(v.is_finite() && v > 0.0) {
                return bad(format!(
                    "{name} = {v}; expected a positive focal length in pixels"
                ));
            }
        }
        for (name, v) in [("cx", self.cx), ("cy", self.cy)] {
            if !v.is_finite() {
                return bad(format!("{name} = {v}; expected a finite principal point"));
            }
        }
        if !(self.baseline_m.is_finite() && (0.001..=0.5).contains(&self.baseline_m)) {
            return bad(format!(
                "baseline {} m; expected 0.001 to 0.5 m",
                self.baseline_m
            ));
        }
        if self.width == 0 || self.height == 0 {
            return bad(format!(
                "image size {}×{}; expected non-zero",
                self.width, self.height
            ));
        }
        let t = self.camera_to_robot.translation.vector;
        let q = self.camera_to_robot.rotation.quaternion();
        if !(t.iter().all(|v| v.is_finite()) && q.coords.iter().all(|v| v.is_finite())) {
            return bad("camera_to_robot is not finite".into());
        }
        Ok(())
    }
}

/// A rectified stereo pair.
#[derive(Clone, Debug, PartialEq)]
pub struct StereoFrame {
    /// When it was captured, on the run's clock.
    pub stamp: Duration,
    /// Left image.
    pub left: RgbImage,
    /// Right image.
    pub right: RgbImage,
}

/// A calibrated stereo camera.
pub trait StereoCamera: Send + Sync {
    /// Its calibration.
    fn calibration(&self) -> &StereoCalibration;
    /// Capture a rectified pair.
    fn capture(&self) -> Result<StereoFrame, RobotError>;
}

/// Forwards every call, so `Arc<dyn StereoCamera>` (and `Box`, `&`) is a camera too.
macro_rules! forward_camera {
    ($($ptr:ty),*) => {$(
        impl<T: StereoCamera + ?Sized> StereoCamera for $ptr {
            fn calibration(&self) -> &StereoCalibration {
                (**self).calibration()
            }
            fn capture(&self) -> Result<StereoFrame, RobotError> {
                (**self).capture()
            }
        }
    )*};
}
forward_camera!(std::sync::Arc<T>, Box<T>, &T);

/// Something shown every frame a camera captures, with the camera's calibration (a
/// recorder's tap).
pub type FrameObserver = std::sync::Arc<dyn Fn(&StereoFrame, &StereoCalibration) + Send + Sync>;

/// `C`, showing every frame it captures to an observer, if it has one.
pub struct ObservedCamera<C> {
    camera: C,
    observer: Option<FrameObserver>,
}

impl<C> ObservedCamera<C> {
    /// `camera`, observed by `observer` (none: the camera as it is).
    pub fn new(camera: C, observer: Option<FrameObserver>) -> Self {
        Self { camera, observer }
    }
}

impl<C: std::fmt::Debug> std::fmt::Debug for ObservedCamera<C> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ObservedCamera")
            .field("camera", &self.camera)
            .field("observed", &self.observer.is_some())
            .finish()
    }
}

impl<C: StereoCamera> StereoCamera for ObservedCamera<C> {
    fn calibration(&self) -> &StereoCalibration {
        self.camera.calibration()
    }
    fn capture(&self) -> Result<StereoFrame, RobotError> {
        let frame = self.camera.capture()?;
        if let Some(observe) = &self.observer {
            observe(&frame, self.camera.calibration());
        }
        Ok(frame)
    }
}

/// A camera that returns black frames of its calibration's size, counting captures.
#[derive(Debug)]
pub struct DummyCamera {
    /// The calibration it reports.
    pub calibration: StereoCalibration,
    /// Captures so far.
    pub captures: std::sync::atomic::AtomicUsize,
}

impl DummyCamera {
    /// A dummy camera with this calibration.
    pub fn new(calibration: StereoCalibration) -> Self {
        Self {
            calibration,
            captures: std::sync::atomic::AtomicUsize::new(0),
        }
    }
}

impl StereoCamera for DummyCamera {
    fn calibration(&self) -> &StereoCalibration {
        &self.calibration
    }
    fn capture(&self) -> Result<StereoFrame, RobotError> {
        self.captures
            .fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        let (w, h) = (self.calibration.width, self.calibration.height);
        Ok(StereoFrame {
            stamp: Duration::ZERO,
            left: RgbImage::new(w, h),
            right: RgbImage::new(w, h),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calib() -> StereoCalibration {
        StereoCalibration {
            fx: 1400.0,
            fy: 1400.0,
            cx: 640.0,
            cy: 480.0,
            baseline_m: 0.05,
            width: 1280,
            height: 960,
            camera_to_robot: Pose::identity(),
        }
    }

    #[test]
    fn calibrations_are_checked() {
        calib().validate().expect("plausible");
        let e = StereoCalibration {
            baseline_m: 2.0,
            ..calib()
        }
        .validate()
        .expect_err("too wide");
        assert!(e.to_string().contains("baseline 2 m"), "{e}");
        assert!(
            StereoCalibration {
                fx: -1.0,
                ..calib()
            }
            .validate()
            .is_err()
        );
        assert!(
            StereoCalibration {
                width: 0,
                ..calib()
            }
            .validate()
            .is_err()
        );
    }

    #[test]
    fn the_dummy_captures_frames_of_its_size() {
        let cam = DummyCamera::new(calib());
        let f = cam.capture().expect("frame");
        assert_eq!(
            (f.left.width, f.right.height, f.left.data.len()),
            (1280, 960, 1280 * 960 * 3)
        );
        assert_eq!(cam.captures.load(std::sync::atomic::Ordering::SeqCst), 1);
    }
}
