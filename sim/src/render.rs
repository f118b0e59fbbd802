//! The mock's stereo camera: a calibrated, rectified pair rendered from the scene's truth.
//!
//! What it draws, all from the robot-frame truth: the textured tissue phantom and the drape
//! around it (a plane, with the wound's slit and its entry and exit marks), the needle as a
//! shiny metal tube (diffuse and specular shading, so highlights move between the two views),
//! the violet thread, each PSM's jaws, wrist and shaft, then lighting variation (a gain per
//! frame), sensor noise and defocus (soft edges a configurable width). Every frame comes with
//! its ground truth: the needle pose and a label image per view.
//!
//! Written by hand because no crate rasterises anti-aliased 3D tubes into a z-tested stereo
//! pair with per-pixel labels; the drawing is a few hundred lines of projection and coverage.
//!
//! Speed: the static background (tissue, drape, their depth) is drawn once per renderer;
//! each frame copies it, draws the tubes over the few pixels they cover and adds noise from a
//! precomputed table at a random offset. `stitch bench perception` reports the time per pair.

use crate::SimError;
use nalgebra::Translation3;
use nalgebra::{Matrix3, Rotation3, UnitQuaternion, Vector2, Vector3};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use serde::{Deserialize, Serialize};
use std::sync::Arc;
use stitch_robot::{Needle, Point, Pose, RgbImage, StereoCalibration, Vector};

type Translation = Translation3<f64>;

/// The stereo camera's set-up: intrinsics, baseline, where it looks from, and the image
/// effects. Defaults: a 1280×960 industrial pair 4 cm apart (the left camera at +x, so the
/// pair's midpoint is above the wound), looking down at 45° at the wound from about 18 cm,
/// with a field of view (56° across) whose two views overlap over the whole workspace
/// (plausible for the paper's set-up; modelling choices).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraConfig {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Focal length, pixels (both axes).
    pub focal_px: f64,
    /// Distance between the two cameras' centres, m.
    pub baseline_m: f64,
    /// The left camera's optical centre, robot frame, m.
    pub eye: [f64; 3],
    /// The point the left camera's optical axis passes through, robot frame, m.
    pub target: [f64; 3],
    /// Standard deviation of the sensor noise, 8-bit levels.
    pub noise_sigma: f64,
    /// Width of the soft edge every object's outline is drawn with (defocus), pixels.
    pub blur_px: f64,
    /// Frame-to-frame lighting variation: the gain is drawn in 1 ± this.
    pub lighting_variation: f64,
}

impl Default for CameraConfig {
    fn default() -> Self {
        Self {
            width: 1280,
            height: 960,
            focal_px: 1200.0,
            baseline_m: 0.04,
            eye: [0.02, 0.135, 0.005],
            target: [0.02, 0.01, -0.115],
            noise_sigma: 3.0,
            blur_px: 1.2,
            lighting_variation: 0.15,
        }
    }
}

impl CameraConfig {
    /// Refuse set-ups no camera has.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |what: &str, why: String| {
            Err(SimError::Config {
                what: format!("camera.{what}"),
                why,
            })
        };
        if !(16..=8192).contains(&self.width) || !(16..=8192).contains(&self.height) {
            return bad(
                "width/height",
                format!("{}×{}; expected 16 to 8192 pixels", self.width, self.height),
            );
        }
        if !(self.focal_px.is_finite() && (50.0..=50_000.0).contains(&self.focal_px)) {
            return bad(
                "focal_px",
                format!("{}; expected 50 to 50,000 pixels", self.focal_px),
            );
        }
        if !(self.baseline_m.is_finite() && (0.001..=0.5).contains(&self.baseline_m)) {
            return bad(
                "baseline_m",
                format!("{}; expected 0.001 to 0.5 m", self.baseline_m),
            );
        }
        let eye = Vector::from(self.eye);
        let target = Vector::from(self.target);
        if !(eye.iter().chain(target.iter()).all(|v| v.is_finite())) {
            return bad("eye/target", "not finite".into());
        }
        let view = target - eye;
        if view.norm() < 0.01 || view.normalize().cross(&Vector::z()).norm() < 0.05 {
            return bad(
                "eye/target",
                format!(
                    "looking from {:?} at {:?}; expected at least 1 cm apart and not straight up or down",
                    self.eye, self.target
                ),
            );
        }
        for (name, v, hi) in [
            ("noise_sigma", self.noise_sigma, 50.0),
            ("blur_px", self.blur_px, 10.0),
            ("lighting_variation", self.lighting_variation, 0.5),
        ] {
            if !(v.is_finite() && (0.0..=hi).contains(&v)) {
                return bad(name, format!("{v}; expected 0 to {hi}"));
            }
        }
        Ok(())
    }

    /// The left camera's frame in the robot frame: z along the optical axis, x to the image's
    /// right, y down.
    pub fn camera_to_robot(&self) -> Pose {
        let eye = Vector::from(self.eye);
        let z = (Vector::from(self.target) - eye).normalize();
        let x = z.cross(&Vector::z()).normalize();
        let y = z.cross(&x);
        let r = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        Pose::from_parts(
            Translation::from(eye),
            UnitQuaternion::from_rotation_matrix(&r),
        )
    }

    /// The calibration of this camera (exact: the renderer's own intrinsics and pose).
    pub fn calibration(&self) -> StereoCalibration {
        StereoCalibration {
            fx: self.focal_px,
            fy: self.focal_px,
            cx: f64::from(self.width) / 2.0,
            cy: f64::from(self.height) / 2.0,
            baseline_m: self.baseline_m,
            width: self.width,
            height: self.height,
            camera_to_robot: self.camera_to_robot(),
        }
    }
}

/// A PSM's tool as the camera sees it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ToolView {
    /// The tool-tip frame (jaws close at its origin, the blades run back along −z), m.
    pub pose: Pose,
    /// The jaw opening, rad.
    pub jaw_rad: f64,
}

/// Everything the camera draws besides the static phantom.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneView {
    /// The needle's shape and pose; `None` if it is out of view.
    pub needle: Option<(Needle, Pose)>,
    /// The thread in view, in pieces (the free thread, the open stitch's loop), each a
    /// polyline, m.
    pub thread: Vec<Vec<Point>>,
    /// The tools.
    pub tools: Vec<ToolView>,
}

/// The static phantom the renderer draws as background.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PhantomView {
    /// Height of the raised wound's top (the tissue between the entry and exit holes), m.
    pub surface_z: f64,
    /// Height of the holes' centres, m.
    pub hole_z: f64,
    /// Height of the pad around the raised wound, m.
    pub floor_z: f64,
    /// The wound's first entry point and its direction along the wound (unit), m.
    pub wound_start: Point,
    /// Unit vector along the wound.
    pub wound_dir: Vector,
    /// Length of the wound, m.
    pub wound_length_m: f64,
    /// Half the distance between the entry and exit marks, m.
    pub half_bite_m: f64,
    /// Spacing of the marks along the wound, m.
    pub spacing_m: f64,
}

/// What a pixel shows, in the truth's label images.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[repr(u8)]
pub enum Label {
    /// Tissue, drape.
    Background = 0,
    /// The needle.
    Needle = 1,
    /// The thread.
    Thread = 2,
    /// A tool's jaws, wrist or shaft.
    Tool = 3,
}

/// A rendered pair's ground truth.
#[derive(Clone, Debug, PartialEq)]
pub struct FrameTruth {
    /// The needle's true pose, robot frame (`None` if out of view).
    pub needle: Option<Pose>,
    /// Per pixel of the left image, what covers most of it ([`Label`] as `u8`).
    pub left_labels: Vec<u8>,
    /// The same for the right image.
    pub right_labels: Vec<u8>,
}

impl FrameTruth {
    /// Pixels of `label` in the left image.
    pub fn count_left(&self, label: Label) -> usize {
        self.left_labels
            .iter()
            .filter(|&&l| l == label as u8)
            .count()
    }
}

/// A rendered stereo pair and its truth.
#[derive(Clone, Debug, PartialEq)]
pub struct RenderedPair {
    /// Left image.
    pub left: RgbImage,
    /// Right image.
    pub right: RgbImage,
    /// What is where.
    pub truth: FrameTruth,
}

/// One view's static background.
#[derive(Debug)]
struct Background {
    rgb: Vec<u8>,
    depth: Vec<f32>,
}

/// Noise table entries beyond an image's byte count: each frame reads a stretch starting at
/// a random offset below this.
const NOISE_OFFSETS: usize = 1 << 20;

/// The stereo renderer. Cheap to clone (the background is shared).
#[derive(Clone, Debug)]
pub struct StereoRenderer {
    config: CameraConfig,
    calibration: StereoCalibration,
    /// Robot frame → left camera frame.
    robot_to_camera: Pose,
    backgrounds: Arc<[Background; 2]>,
    noise: Arc<Vec<i8>>,
}

/// Tissue and drape colours, linear 0–255 (modelling choices: a pink silicone pad on a
/// green drape).
const TISSUE: [f32; 3] = [206.0, 122.0, 118.0];
const DRAPE: [f32; 3] = [52.0, 112.0, 78.0];
const MARK: [f32; 3] = [96.0, 34.0, 38.0];
const THREAD: [f32; 3] = [118.0, 58.0, 172.0];
const TOOL: [f32; 3] = [38.0, 38.0, 44.0];
/// Half extents of the phantom pad around the wound, m (modelling choice).
const PAD_HALF_WIDTH_M: f64 = 0.05;
const PAD_MARGIN_M: f64 = 0.04;
/// The raised wound's extent beyond its first and last points, m (modelling choice).
pub(crate) const WOUND_MARGIN_M: f64 = 0.004;
/// Thread radius (a 3-0 suture is about 0.3 mm thick), m.
const THREAD_RADIUS_M: f64 = 0.00015;

impl StereoRenderer {
    /// A renderer for this camera and phantom. Draws the static background (tens of ms).
    pub fn new(config: CameraConfig, phantom: PhantomView) -> Result<Self, SimError> {
        config.validate()?;
        let calibration = config.calibration();
        let robot_to_camera = calibration.camera_to_robot.inverse();
        let backgrounds = Arc::new([
            background(&config, &robot_to_camera, &phantom, 0.0),
            background(&config, &robot_to_camera, &phantom, config.baseline_m),
        ]);
        // The sensor noise: a fixed table of Gaussian draws (σ = noise_sigma), read from a
        // random offset each frame.
        let mut rng = ChaCha8Rng::seed_from_u64(0x0057_17c4);
        let sigma = config.noise_sigma;
        let bytes = config.width as usize * config.height as usize * 3;
        let noise = (0..bytes + NOISE_OFFSETS)
            .map(|_| {
                let g: f64 = (0..4).map(|_| rng.random::<f64>()).sum::<f64>() - 2.0;
                // Sum of 4 uniforms: variance 1/3.
                (g * sigma * 3f64.sqrt()).round().clamp(-127.0, 127.0) as i8
            })
            .collect();
        Ok(Self {
            config,
            calibration,
            robot_to_camera,
            backgrounds,
            noise: Arc::new(noise),
        })
    }

    /// The camera's calibration (exact).
    pub fn calibration(&self) -> &StereoCalibration {
        &self.calibration
    }

    /// Its configuration.
    pub fn config(&self) -> &CameraConfig {
        &self.config
    }

    /// Render `scene` as seen by a camera whose true pose differs from the calibrated one by
    /// `hand_eye` (identity for an exact calibration; a pose estimated through the
    /// calibration then comes out as `hand_eye · truth`). Noise and lighting come from `rng`.
    pub fn render(&self, scene: &SceneView, hand_eye: &Pose, rng: &mut ChaCha8Rng) -> RenderedPair {
        let robot_to_camera = self.robot_to_camera * hand_eye;
        let gain = 1.0 + self.config.lighting_variation * (2.0 * rng.random::<f64>() - 1.0);
        let tubes = tubes(scene, &robot_to_camera);
        let offsets = [
            rng.random_range(0..NOISE_OFFSETS),
            rng.random_range(0..NOISE_OFFSETS),
        ];
        let [(left, left_labels), (right, right_labels)] = [0usize, 1].map(|i| {
            let shift = if i == 0 { 0.0 } else { self.config.baseline_m };
            self.render_view(&tubes, i, shift, gain as f32, offsets[i])
        });
        RenderedPair {
            left,
            right,
            truth: FrameTruth {
                needle: scene.needle.map(|(_, p)| p),
                left_labels,
                right_labels,
            },
        }
    }

    fn render_view(
        &self,
        tubes: &[Tube],
        view: usize,
        shift_m: f64,
        gain: f32,
        noise_offset: usize,
    ) -> (RgbImage, Vec<u8>) {
        let (w, h) = (self.config.width as usize, self.config.height as usize);
        let bg = &self.backgrounds[view];
        let mut rgb: Vec<f32> = Vec::new();
        // Depth of what is drawn, per touched pixel (the background's elsewhere).
        let mut drawn_depth: Vec<f32> = Vec::new();
        let mut labels = vec![Label::Background as u8; w * h];
        // Objects are drawn into a sparse float layer over the background: only the pixels
        // they touch are converted.
        let mut touched: Vec<u32> = Vec::new();
        let f = self.config.focal_px as f32;
        let (cx, cy) = (w as f32 / 2.0, h as f32 / 2.0);
        let soft = self.config.blur_px.max(0.5) as f32;
        let light = Vector3::new(-0.3f32, -0.6, -1.0).normalize();
        let toward_eye = Vector3::new(0.0f32, 0.0, -1.0);
        let half = (light + toward_eye).normalize();
        // Project every tube first: the union of their boxes bounds the scratch index.
        let projected: Vec<_> = tubes
            .iter()
            .filter_map(|tube| {
                let a = tube.a - Vector3::new(shift_m as f32, 0.0, 0.0);
                let b = tube.b - Vector3::new(shift_m as f32, 0.0, 0.0);
                if a.z < 0.01 || b.z < 0.01 {
                    return None;
                }
                let pa = Vector2::new(f * a.x / a.z + cx, f * a.y / a.z + cy);
                let pb = Vector2::new(f * b.x / b.z + cx, f * b.y / b.z + cy);
                let (ra, rb) = (f * tube.radius[0] / a.z, f * tube.radius[1] / b.z);
                let reach = ra.max(rb) + soft;
                if pa.x.max(pb.x) + reach < 0.0 || pa.y.max(pb.y) + reach < 0.0 {
                    return None;
                }
                let x0 = (pa.x.min(pb.x) - reach).floor().max(0.0) as usize;
                let x1 = ((pa.x.max(pb.x) + reach).ceil() as usize).min(w);
                let y0 = (pa.y.min(pb.y) - reach).floor().max(0.0) as usize;
                let y1 = ((pa.y.max(pb.y) + reach).ceil() as usize).min(h);
                (x0 < x1 && y0 < y1).then_some((tube, a, b, pa, pb, ra, rb, [x0, y0, x1, y1]))
            })
            .collect();
        let bx0 = projected.iter().map(|t| t.7[0]).min().unwrap_or(0);
        let by0 = projected.iter().map(|t| t.7[1]).min().unwrap_or(0);
        let bx1 = projected.iter().map(|t| t.7[2]).max().unwrap_or(0);
        let by1 = projected.iter().map(|t| t.7[3]).max().unwrap_or(0);
        let bw = bx1.saturating_sub(bx0);
        let mut layer_index = vec![u32::MAX; bw * by1.saturating_sub(by0)];
        for &(tube, a, b, pa, pb, ra, rb, [x0, y0, x1, y1]) in &projected {
            let ab = pb - pa;
            let len2 = ab.norm_squared().max(1e-6);
            let along = ab / len2.sqrt();
            let across = Vector2::new(-along.y, along.x);
            for y in y0..y1 {
                for x in x0..x1 {
                    let p = Vector2::new(x as f32 + 0.5, y as f32 + 0.5);
                    let t = ((p - pa).dot(&ab) / len2).clamp(0.0, 1.0);
                    let q = pa + ab * t;
                    let d = p - q;
                    let r = ra + (rb - ra) * t;
                    let d2 = d.norm_squared();
                    if d2 >= (r + 0.5 * soft) * (r + 0.5 * soft) {
                        continue;
                    }
                    let dist = d2.sqrt();
                    let coverage = (0.5 + (r - dist) / soft).clamp(0.0, 1.0);
                    if coverage <= 0.0 {
                        continue;
                    }
                    let z = a.z + (b.z - a.z) * t;
                    let i = y * w + x;
                    let li = (y - by0) * bw + (x - bx0);
                    let slot = layer_index[li];
                    let nearest = if slot == u32::MAX {
                        bg.depth[i]
                    } else {
                        drawn_depth[slot as usize]
                    };
                    if z >= nearest {
                        continue;
                    }
                    // Shade a tube: the surface normal from the offset across it (unit: `across`
                    // and the view direction are orthogonal unit vectors).
                    let s = (d.dot(&across) / r.max(0.5)).clamp(-1.0, 1.0);
                    let normal = Vector3::new(across.x * s, across.y * s, 0.0)
                        + toward_eye * (1.0 - s * s).max(0.0).sqrt();
                    let diffuse = normal.dot(&-light).max(0.0);
                    let color = match tube.material {
                        Material::Metal => {
                            let spec = normal.dot(&half).max(0.0).powi(24);
                            let v = 112.0 + 80.0 * diffuse + 300.0 * spec;
                            [v, v, v * 1.03]
                        }
                        Material::Thread => THREAD.map(|c| c * (0.75 + 0.35 * diffuse)),
                        Material::Tool => TOOL.map(|c| c * (0.8 + 0.4 * diffuse)),
                    };
                    let k = if slot == u32::MAX {
                        let k = touched.len() as u32;
                        layer_index[li] = k;
                        touched.push(i as u32);
                        drawn_depth.push(bg.depth[i]);
                        let o = i * 3;
                        rgb.extend(bg.rgb[o..o + 3].iter().map(|&c| f32::from(c)));
                        k
                    } else {
                        slot
                    } as usize;
                    for c in 0..3 {
                        let old = rgb[k * 3 + c];
                        rgb[k * 3 + c] = old + (color[c] - old) * coverage;
                    }
                    if coverage >= 0.5 {
                        drawn_depth[k] = z;
                        labels[i] = tube.material.label() as u8;
                    }
                }
            }
        }
        // Compose: background everywhere, the object layer where drawn; gain and noise.
        // Gain in 1/128ths (at most 1.5 × 128 × 255 fits in u16), then noise from one
        // contiguous stretch of the table, in one pass that builds the image (a loop the
        // compiler vectorises); then the drawn pixels, likewise.
        let g = (gain * 128.0).round().clamp(0.0, 192.0) as u16;
        let noise = &self.noise[noise_offset..noise_offset + bg.rgb.len()];
        let expose = |v: u8, n: i8| {
            let x = ((u16::from(v) * g) >> 7) as i16 + i16::from(n);
            x.clamp(0, 255) as u8
        };
        let mut out: Vec<u8> = bg
            .rgb
            .iter()
            .zip(noise)
            .map(|(&v, &n)| expose(v, n))
            .collect();
        for (k, &i) in touched.iter().enumerate() {
            let o = i as usize * 3;
            for c in 0..3 {
                let v = rgb[k * 3 + c].round().clamp(0.0, 255.0) as u8;
                out[o + c] = expose(v, noise[o + c]);
            }
        }
        (
            RgbImage {
                width: self.config.width,
                height: self.config.height,
                data: out,
            },
            labels,
        )
    }
}

#[derive(Clone, Copy, Debug, PartialEq)]
enum Material {
    Metal,
    Thread,
    Tool,
}

impl Material {
    fn label(self) -> Label {
        match self {
            Material::Metal => Label::Needle,
            Material::Thread => Label::Thread,
            Material::Tool => Label::Tool,
        }
    }
}

/// A straight tube (capsule) in the left camera's frame, m.
#[derive(Clone, Copy, Debug)]
struct Tube {
    a: Vector3<f32>,
    b: Vector3<f32>,
    /// Radius at `a` and at `b`, m.
    radius: [f32; 2],
    material: Material,
}

/// Segments of the needle arc drawn per half circle.
const NEEDLE_SEGMENTS: usize = 120;
/// Length of the tip's taper, m (modelling choice for a GS-21-like taper point).
pub const TIP_TAPER_M: f64 = 0.002;
/// Length of the swage, m, and its radius as a multiple of the wire's (modelling choices).
pub const SWAGE_LENGTH_M: f64 = 0.0012;
const SWAGE_SCALE: f64 = 1.25;

/// The scene's tubes in the camera frame, far ones first (painter's order for blending).
fn tubes(scene: &SceneView, robot_to_camera: &Pose) -> Vec<Tube> {
    let mut out = Vec::new();
    let cam = |p: &Point| {
        let q = robot_to_camera * p;
        Vector3::new(q.x as f32, q.y as f32, q.z as f32)
    };
    let mut tube = |a: &Point, b: &Point, radius: [f64; 2], material| {
        out.push(Tube {
            a: cam(a),
            b: cam(b),
            radius: radius.map(|r| r as f32),
            material,
        })
    };
    if let Some((needle, pose)) = &scene.needle {
        // The wire tapers to the point over its last TIP_TAPER_M and is crimped thicker over
        // the swage's last SWAGE_LENGTH_M, as on a real suture needle.
        let r = needle.radius_m;
        let wire = needle.wire_diameter_m / 2.0;
        let radius_at = |angle: f64| {
            let from_tip = angle * r;
            let from_swage = (std::f64::consts::PI - angle) * r;
            if from_tip < TIP_TAPER_M {
                wire * (0.15 + 0.85 * from_tip / TIP_TAPER_M)
            } else if from_swage < SWAGE_LENGTH_M {
                wire * SWAGE_SCALE
            } else {
                wire
            }
        };
        let angles: Vec<f64> = (0..=NEEDLE_SEGMENTS)
            .map(|k| std::f64::consts::PI * k as f64 / NEEDLE_SEGMENTS as f64)
            .collect();
        for w in angles.windows(2) {
            tube(
                &(pose * needle.point_at(w[0])),
                &(pose * needle.point_at(w[1])),
                [radius_at(w[0]), radius_at(w[1])],
                Material::Metal,
            );
        }
    }
    for w in scene.thread.iter().flat_map(|piece| piece.windows(2)) {
        // Subdivide so the depth test follows the thread.
        let n = (((w[1] - w[0]).norm() / 0.002).ceil() as usize).clamp(1, 200);
        for k in 0..n {
            let a = w[0] + (w[1] - w[0]) * (k as f64 / n as f64);
            let b = w[0] + (w[1] - w[0]) * ((k + 1) as f64 / n as f64);
            tube(&a, &b, [THREAD_RADIUS_M; 2], Material::Thread);
        }
    }
    for tool in &scene.tools {
        let p = &tool.pose;
        let wrist = p * Point::new(0.0, 0.0, -crate::JAW_LENGTH_M);
        let half = (tool.jaw_rad / 2.0).clamp(0.0, 1.2);
        for side in [-1.0, 1.0] {
            let tip = p * Point::new(
                0.0,
                side * crate::JAW_LENGTH_M * half.sin(),
                -crate::JAW_LENGTH_M * (1.0 - half.cos()),
            );
            tube(&wrist, &tip, [0.0009; 2], Material::Tool);
        }
        // The wrist and the shaft continue the tool's axis away from the tip.
        let back = p * Point::new(0.0, 0.0, -crate::JAW_LENGTH_M - 0.006);
        tube(&wrist, &back, [0.0025; 2], Material::Tool);
        // In pieces, so each piece's bounding box hugs it.
        for k in 0..8 {
            let z = |k: f64| -crate::JAW_LENGTH_M - 0.006 - 0.044 * k / 8.0;
            let a = p * Point::new(0.0, 0.0, z(f64::from(k)));
            let b = p * Point::new(0.0, 0.0, z(f64::from(k + 1)));
            tube(&a, &b, [0.0042; 2], Material::Tool);
        }
    }
    out.sort_by(|a, b| {
        let za = a.a.z + a.b.z;
        let zb = b.a.z + b.b.z;
        zb.total_cmp(&za)
    });
    out
}

/// Smooth value noise in [0, 1) at `(x, y)` (lattice units), from a fixed hash.
fn value_noise(x: f64, y: f64) -> f64 {
    let hash = |i: i64, j: i64| {
        let mut h = (i as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (j as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F);
        h ^= h >> 29;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 32;
        (h >> 11) as f64 / (1u64 << 53) as f64
    };
    let (xf, yf) = (x.floor(), y.floor());
    let (i, j) = (xf as i64, yf as i64);
    let (u, v) = (x - xf, y - yf);
    let (u, v) = (u * u * (3.0 - 2.0 * u), v * v * (3.0 - 2.0 * v));
    let a = hash(i, j) + (hash(i + 1, j) - hash(i, j)) * u;
    let b = hash(i, j + 1) + (hash(i + 1, j + 1) - hash(i, j + 1)) * u;
    a + (b - a) * v
}

/// The tissue pad and drape as seen by the camera shifted `shift_m` along its x axis.
fn background(
    config: &CameraConfig,
    robot_to_camera: &Pose,
    phantom: &PhantomView,
    shift_m: f64,
) -> Background {
    let (w, h) = (config.width as usize, config.height as usize);
    let camera_to_robot = robot_to_camera.inverse();
    let origin = camera_to_robot * Point::new(shift_m, 0.0, 0.0);
    let f = config.focal_px;
    let (cx, cy) = (
        f64::from(config.width) / 2.0,
        f64::from(config.height) / 2.0,
    );
    let mut rgb = vec![0u8; w * h * 3];
    let mut depth = vec![f32::INFINITY; w * h];
    let across = Vector::z().cross(&phantom.wound_dir).normalize();
    for y in 0..h {
        for x in 0..w {
            let ray_cam = Vector::new((x as f64 + 0.5 - cx) / f, (y as f64 + 0.5 - cy) / f, 1.0);
            let ray = camera_to_robot.rotation * ray_cam;
            let i = y * w + x;
            if ray.z >= -1e-6 {
                rgb[i * 3..i * 3 + 3].copy_from_slice(&[20, 20, 24]);
                continue;
            }
            // The raised wound: a block between the entry and exit holes' planes, from the
            // pad up to its top (where the mock's tissue holds the needle); then the pad.
            let o = origin - phantom.wound_start;
            let (ou, ov, oz) = (o.dot(&across), o.dot(&phantom.wound_dir), origin.z);
            let (ru, rv, rz) = (ray.dot(&across), ray.dot(&phantom.wound_dir), ray.z);
            let hb = phantom.half_bite_m;
            let slabs = [
                (ou, ru, -hb, hb),
                (
                    ov,
                    rv,
                    -WOUND_MARGIN_M,
                    phantom.wound_length_m + WOUND_MARGIN_M,
                ),
                (oz, rz, phantom.floor_z, phantom.surface_z),
            ];
            let (mut t_in, mut t_out, mut face) = (0.0f64, f64::INFINITY, 3usize);
            for (k, &(o, r, lo, hi)) in slabs.iter().enumerate() {
                if r.abs() < 1e-12 {
                    if o < lo || o > hi {
                        t_in = f64::INFINITY;
                    }
                    continue;
                }
                let (a, b) = ((lo - o) / r, (hi - o) / r);
                let (a, b) = (a.min(b), a.max(b));
                if a > t_in {
                    t_in = a;
                    face = k;
                }
                t_out = t_out.min(b);
            }
            let on_block = t_in <= t_out && t_in.is_finite() && t_in > 0.0;
            let t = if on_block {
                t_in
            } else {
                (phantom.floor_z - origin.z) / ray.z
            };
            let p = origin + ray * t;
            depth[i] = t as f32; // ray_cam has unit z: t is the depth
            let rel = p - phantom.wound_start;
            let u = rel.dot(&across); // across the wound, m
            let v = rel.dot(&phantom.wound_dir); // along it, m
            let on_pad = u.abs() <= PAD_HALF_WIDTH_M
                && v >= -PAD_MARGIN_M
                && v <= phantom.wound_length_m + PAD_MARGIN_M;
            let mut c = if on_pad {
                let n = 0.6 * value_noise(p.x / 0.002, p.y / 0.002)
                    + 0.4 * value_noise(p.x / 0.0006 + 17.0, p.y / 0.0006 - 5.0);
                // The block's sides are lit less than its top and the pad.
                let side = if on_block && face != 2 { 0.85 } else { 1.0 };
                let shade = (0.82 + 0.3 * n) * side;
                TISSUE.map(|c| c * shade as f32)
            } else {
                let n = value_noise(p.x / 0.004, p.y / 0.004);
                DRAPE.map(|c| c * (0.85 + 0.25 * n) as f32)
            };
            if on_block {
                // The wound's slit on top, and the entry and exit holes on the sides.
                if face == 2 && u.abs() < 0.0004 {
                    c = MARK;
                }
                if phantom.spacing_m > 0.0 && face == 0 {
                    let k = (v / phantom.spacing_m).round();
                    let along = v - k * phantom.spacing_m;
                    let count = (phantom.wound_length_m / phantom.spacing_m).round();
                    let dz = p.z - phantom.hole_z;
                    if (0.0..=count).contains(&k) && (dz * dz + along * along).sqrt() < 0.0008 {
                        c = MARK;
                    }
                }
            }
            for (k, v) in c.iter().enumerate() {
                rgb[i * 3 + k] = v.round().clamp(0.0, 255.0) as u8;
            }
        }
    }
    Background { rgb, depth }
}

/// The mock dVRK's stereo camera: renders the world's truth each capture, seen through the
/// hand-eye fault if one is injected; an injected perception dropout gives an overexposed
/// (white) pair. Each capture costs `frame_time` of simulated time.
#[derive(Debug)]
pub struct MockCamera {
    world: crate::MockDvrk,
    renderer: StereoRenderer,
    rng: std::sync::Mutex<ChaCha8Rng>,
    frame_time: std::time::Duration,
}

impl MockCamera {
    /// A camera on `world` with this renderer; noise from the seed's perception stream.
    pub fn new(
        world: crate::MockDvrk,
        renderer: StereoRenderer,
        streams: crate::Streams,
        frame_time: std::time::Duration,
    ) -> Self {
        Self {
            world,
            renderer,
            rng: std::sync::Mutex::new(streams.rng(crate::Subsystem::Perception)),
            frame_time,
        }
    }

    /// Capture a pair with its truth (for tests and benches).
    pub fn capture_with_truth(&self) -> RenderedPair {
        self.world.clock().advance(self.frame_time);
        let scene = self.world.scene_view();
        let hand_eye = self.world.hand_eye_fault();
        let mut rng = self
            .rng
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner);
        let mut pair = self.renderer.render(&scene, &hand_eye, &mut rng);
        if self.world.perception_dropout_fires() {
            pair.left.data.fill(255);
            pair.right.data.fill(255);
        }
        pair
    }
}

impl stitch_robot::StereoCamera for MockCamera {
    fn calibration(&self) -> &StereoCalibration {
        self.renderer.calibration()
    }
    fn capture(&self) -> Result<stitch_robot::StereoFrame, stitch_robot::RobotError> {
        let pair = self.capture_with_truth();
        Ok(stitch_robot::StereoFrame {
            stamp: stitch_robot::Clock::now(self.world.clock()),
            left: pair.left,
            right: pair.right,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn phantom() -> PhantomView {
        PhantomView {
            surface_z: -0.116,
            hole_z: -0.12,
            floor_z: -0.126,
            wound_start: Point::new(0.0, 0.0, -0.116),
            wound_dir: Vector::y(),
            wound_length_m: 0.04,
            half_bite_m: 0.005,
            spacing_m: 0.008,
        }
    }

    fn needle_pose() -> Pose {
        Pose::from_parts(
            Translation::new(-0.01, 0.01, -0.095),
            UnitQuaternion::from_euler_angles(1.2, 0.3, 0.4),
        )
    }

    #[test]
    fn the_needle_is_drawn_where_it_projects_and_its_disparity_matches_its_depth() {
        let r = StereoRenderer::new(CameraConfig::default(), phantom()).expect("renderer");
        let needle = Needle::default();
        let scene = SceneView {
            needle: Some((needle, needle_pose())),
            thread: vec![],
            tools: vec![],
        };
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let pair = r.render(&scene, &Pose::identity(), &mut rng);
        let c = r.calibration();
        let to_cam = c.camera_to_robot.inverse();
        // The arc's middle point projects onto needle pixels in both views, offset by the
        // disparity f·B/Z.
        let mid = to_cam * (needle_pose() * needle.point_at(std::f64::consts::FRAC_PI_2));
        let (u, v) = (c.fx * mid.x / mid.z + c.cx, c.fy * mid.y / mid.z + c.cy);
        let d = c.fx * c.baseline_m / mid.z;
        let at = |labels: &[u8], u: f64| labels[v as usize * c.width as usize + u as usize];
        assert_eq!(at(&pair.truth.left_labels, u), Label::Needle as u8);
        assert_eq!(at(&pair.truth.right_labels, u - d), Label::Needle as u8);
        assert_ne!(at(&pair.truth.right_labels, u), Label::Needle as u8);
        // About as many pixels as a 0.7 mm wire 12π mm long at this range.
        let px = pair.truth.count_left(Label::Needle) as f64;
        let expect = (0.0007 * c.fx / mid.z) * (std::f64::consts::PI * 0.012 * c.fx / mid.z);
        assert!(px > 0.3 * expect && px < 1.5 * expect, "{px} vs {expect}");
    }

    #[test]
    fn the_same_rng_gives_the_same_frame_and_another_differs() {
        let r = StereoRenderer::new(CameraConfig::default(), phantom()).expect("renderer");
        let scene = SceneView {
            needle: Some((Needle::default(), needle_pose())),
            thread: vec![vec![
                Point::new(0.0, 0.0, -0.116),
                Point::new(-0.02, 0.02, -0.1),
            ]],
            tools: vec![],
        };
        let a = r.render(&scene, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(3));
        let b = r.render(&scene, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(3));
        let c = r.render(&scene, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(4));
        assert!(a == b);
        assert!(a.left != c.left);
        assert!(a.truth.count_left(Label::Thread) > 50);
    }

    #[test]
    fn needle_below_the_tissue_is_hidden() {
        let r = StereoRenderer::new(CameraConfig::default(), phantom()).expect("renderer");
        let below = Pose::from_parts(
            Translation::new(0.0, 0.01, -0.14),
            UnitQuaternion::identity(),
        );
        let scene = SceneView {
            needle: Some((Needle::default(), below)),
            thread: vec![],
            tools: vec![],
        };
        let pair = r.render(&scene, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(1));
        assert_eq!(pair.truth.count_left(Label::Needle), 0);
    }

    #[test]
    fn bad_cameras_are_refused() {
        let c = CameraConfig {
            baseline_m: 3.0,
            ..CameraConfig::default()
        };
        assert!(StereoRenderer::new(c, phantom()).is_err());
        let c = CameraConfig {
            target: [0.02, 0.135, -0.2],
            ..CameraConfig::default()
        };
        assert!(c.validate().is_err(), "straight down");
    }
}
