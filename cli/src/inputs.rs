//! What the `stitch` command reads from files a user or a lab hands it, parsed from their
//! bytes or text with a clear error and never a panic: the mock dVRK's configuration, a
//! stereo calibration, an image. The fuzz targets (`fuzz/`) call these.

use anyhow::Context;
use serde::{Deserialize, Serialize};
use stitch_robot::nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion};
use stitch_robot::{Pose, RgbImage, StereoCalibration};
use stitch_sim::{CameraConfig, SceneConfig, SensingConfig};

/// The mock dVRK's configuration file.
#[derive(Debug, Default, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MockConfig {
    /// The scene: wound, phantom, arms, thread, faults.
    pub scene: SceneConfig,
    /// The needle estimator's noise model.
    pub sensing: SensingConfig,
    /// The rendered stereo camera.
    pub camera: CameraConfig,
}

/// The mock configuration in `text` (TOML), as parsed: each part is checked where it is
/// used (the scene when the mock is built, the camera when it renders).
pub fn mock_config(text: &str) -> anyhow::Result<MockConfig> {
    Ok(toml::from_str::<MockConfig>(text)?)
}

/// The stereo calibration in `text` (TOML, [`CalibrationFile`]), checked.
pub fn calibration(text: &str) -> anyhow::Result<StereoCalibration> {
    let file: CalibrationFile = toml::from_str(text)?;
    file.to_calibration()
}

/// The largest image side read, pixels (the ROS 2 camera's bound too).
pub const MAX_IMAGE_SIDE: u32 = 16_384;

/// An image file's bytes (PNG, or any format the `image` crate reads here) as 8-bit RGB; one
/// larger than [`MAX_IMAGE_SIDE`] a side, or needing more than 1 GiB to decode, is refused.
pub fn image(bytes: &[u8]) -> anyhow::Result<RgbImage> {
    let mut reader = image::ImageReader::new(std::io::Cursor::new(bytes))
        .with_guessed_format()
        .context("cannot tell the image's format")?;
    let mut limits = image::Limits::default();
    limits.max_image_width = Some(MAX_IMAGE_SIDE);
    limits.max_image_height = Some(MAX_IMAGE_SIDE);
    limits.max_alloc = Some(1 << 30);
    reader.limits(limits);
    let img = reader.decode()?.into_rgb8();
    Ok(RgbImage {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    })
}

/// The calibration file: a rectified pair's shared intrinsics, its baseline, image size, and
/// the left camera's pose in the robot frame (hand-eye).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CalibrationFile {
    /// Focal length along x, pixels.
    pub fx: f64,
    /// Focal length along y, pixels.
    pub fy: f64,
    /// Principal point, pixels.
    pub cx: f64,
    /// Principal point, pixels.
    pub cy: f64,
    /// Distance between the cameras' centres, m.
    pub baseline_m: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// The left camera frame in the robot frame.
    pub camera_to_robot: TransformFile,
}

/// A rigid transform: translation (m) and rotation matrix (rows).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TransformFile {
    /// Translation, m.
    pub translation_m: [f64; 3],
    /// Rotation matrix, row by row.
    pub rotation: [[f64; 3]; 3],
}

impl CalibrationFile {
    /// The file that says `c`.
    pub fn from_calibration(c: &StereoCalibration) -> Self {
        let m = c.camera_to_robot.rotation.to_rotation_matrix();
        let m = m.matrix();
        let t = c.camera_to_robot.translation.vector;
        Self {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            baseline_m: c.baseline_m,
            width: c.width,
            height: c.height,
            camera_to_robot: TransformFile {
                translation_m: [t.x, t.y, t.z],
                rotation: [0, 1, 2].map(|r| [m[(r, 0)], m[(r, 1)], m[(r, 2)]]),
            },
        }
    }

    /// The calibration this file says, checked.
    pub fn to_calibration(&self) -> anyhow::Result<StereoCalibration> {
        let r = &self.camera_to_robot.rotation;
        let m = Matrix3::from_fn(|i, j| r[i][j]);
        let err = (m.transpose() * m - Matrix3::identity()).norm();
        if !err.is_finite() || err > 1e-3 || (m.determinant() - 1.0).abs() > 1e-3 {
            anyhow::bail!(
                "camera_to_robot.rotation is not a rotation matrix (‖RᵀR − I‖ = {err:.2e}, det = {:.4})",
                m.determinant()
            );
        }
        let t = self.camera_to_robot.translation_m;
        let c = StereoCalibration {
            fx: self.fx,
            fy: self.fy,
            cx: self.cx,
            cy: self.cy,
            baseline_m: self.baseline_m,
            width: self.width,
            height: self.height,
            camera_to_robot: Pose::from_parts(
                Translation3::new(t[0], t[1], t[2]),
                UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(m)),
            ),
        };
        c.validate()?;
        Ok(c)
    }
}
