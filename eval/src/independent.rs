//! The independent evaluation set: stereo pairs that the pipeline was not tuned on, made by a
//! renderer that shares no code and no modelling choice with the mock's
//! (`stitch_sim::render`, a z-buffered rasteriser of tubes over a fixed phantom, one camera).
//!
//! How it differs, on purpose:
//! - **A ray tracer.** Every pixel casts rays (2×2 jittered samples near objects): the tissue
//!   is a plane, the thread and the instrument are chains of capsules intersected
//!   analytically, the needle is sphere-traced against a distance function of a tapered arc.
//!   Hard shadows from the main light; reflections of an environment on the needle.
//! - **Another rig every pair.** Image sizes 1024×768 to 1920×1080, focal lengths 800–2,400
//!   px, principal points off centre, baselines 4 mm (an endoscope) to 7 cm (two cameras on a
//!   bar) — disparities from tens to several hundred pixels — looking from 7 to 22 cm at
//!   35–85° elevation, rolled up to ±25°, the needle anywhere in the frame. A rig whose pixel
//!   of disparity spans more than 2.5 mm of depth at the needle is not drawn (a dVRK
//!   endoscope's spans about 1.8 mm at 10 cm): no stereo method places a 0.7 mm wire's arc
//!   from such a pair.
//! - **Other tissue**: five palettes (muscle, red, liver, a pale phantom, fat), gradient-noise
//!   texture with cellular vessels, bump-mapped and wet (specular highlights), none of the
//!   mock's drape, slit or marks.
//! - **Other light**: a light beside the lens (inverse-square fall-off) and sometimes a
//!   second one above, tinted warm to cool, with vignetting, a white balance, exposure.
//! - **Another needle**: the same 12 mm radius and 0.7 mm wire (the pipeline's model), but
//!   the tip tapers over 1.5–3.5 mm with a profile drawn per pair, the swage is 10–35 %
//!   thicker over 1–2.5 mm, and the steel reflects the room and the tissue.
//! - **Thread and jaws**: the thread leaves the swage along the needle and runs to the tissue,
//!   beside the needle or looped over it; about half of the needles are held by a jaw (two
//!   fingers, a clevis, a shaft), near the tip or the swage, the rest lie free in view.
//! - **The camera**: Gaussian defocus (σ 0.3–1.4 px) and shot plus read noise, applied to
//!   the gamma-encoded image, per view.
//!
//! What it keeps from the pipeline's assumptions: a rectified pair with its calibration, a
//! steel needle of the pipeline's radius and wire, a violet thread. Every pair is drawn from
//! one seed; the same seed gives the same set and the same pixels.

use crate::FrameResult;
use nalgebra::{Isometry3, Matrix3, Rotation3, Translation3, UnitQuaternion};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use std::f64::consts::{PI, TAU};
use std::time::Instant;
use stitch_perception::PerceptionError;
use stitch_perception::pipeline::{JawHint, NeedleEnd, NeedlePipeline};
use stitch_robot::{Needle, Point, Pose, RgbImage, StereoCalibration, Vector};
use stitch_sim::Label;

/// One independent pair's scene and truth.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// The rig: intrinsics, baseline, the left camera's pose (robot frame = this scene's
    /// world; the tissue is the plane z = 0).
    pub calibration: StereoCalibration,
    /// The needle frame in the robot frame (tip at +x·r, swage at −x·r, normal +z).
    pub truth: Pose,
    /// The jaw holding the needle, if there is one in view: its tool tip and the end it holds
    /// the needle nearer to.
    pub jaw: Option<JawHint>,
    /// Whether the thread loops over the needle (between it and the camera).
    pub thread_over: bool,
    scene: Scene,
}

impl Sample {
    /// The thread: its centreline from where it enters the tissue to the swage, that end,
    /// and the swage, m.
    pub fn thread_truth(&self) -> (Vec<Point>, Point, Point) {
        let caps = &self.scene.capsules[..self.scene.thread_capsules];
        let mut line: Vec<Point> = caps.iter().map(|c| c.a).collect();
        if let Some(c) = caps.last() {
            line.push(c.b);
        }
        line.reverse();
        let (start, swage) = (line[0], line[line.len() - 1]);
        (line, start, swage)
    }

    /// "tip", "swage" (the end the jaw holds nearer) or "none", for tables.
    pub fn jaw_label(&self) -> &'static str {
        match self.jaw {
            Some(JawHint {
                end: NeedleEnd::Tip,
                ..
            }) => "tip",
            Some(_) => "swage",
            None => "none",
        }
    }
}

/// Everything the ray tracer needs, world frame, m; linear colours.
#[derive(Clone, Debug, PartialEq)]
struct Scene {
    needle: NeedleShape,
    /// Thread segments, then the instrument's.
    capsules: Vec<Capsule>,
    /// How many of `capsules` are the thread's (the rest are the instrument's).
    thread_capsules: usize,
    /// Bounding spheres (centre, radius) of runs of `GROUP` consecutive capsules: shadow
    /// rays test a run's sphere before its capsules (testing every capsule was 40 % of the
    /// render time).
    groups: Vec<(Point, f64)>,
    tissue: Tissue,
    lights: Vec<Light>,
    ambient: f64,
    camera: CameraEffects,
    seed: u64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct NeedleShape {
    /// World → needle frame.
    to_local: Isometry3<f64>,
    radius: f64,
    wire_r: f64,
    tip_r: f64,
    taper_len: f64,
    taper_power: f64,
    swage_scale: f64,
    swage_len: f64,
    albedo: [f64; 3],
    specular: f64,
    shininess: f64,
    reflect: f64,
    /// The environment it reflects: above the horizon and below (the tissue).
    sky: [f64; 3],
    ground: [f64; 3],
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Material {
    albedo: [f64; 3],
    specular: f64,
    shininess: f64,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Capsule {
    a: Point,
    b: Point,
    r: f64,
    material: Material,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Tissue {
    base: [f64; 3],
    second: [f64; 3],
    vessel: [f64; 3],
    scale_m: f64,
    vessel_scale_m: f64,
    bump: f64,
    specular: f64,
    shininess: f64,
    offset: [f64; 2],
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct Light {
    position: Point,
    /// Radiant intensity per channel, scaled so 1 is the exposure's white at 1 m.
    intensity: [f64; 3],
    shadows: bool,
}

#[derive(Clone, Copy, Debug, PartialEq)]
struct CameraEffects {
    vignetting: f64,
    white_balance: [f64; 3],
    blur_sigma_px: f64,
    read_noise: f64,
    shot_noise: f64,
}

/// The image sizes the rigs are drawn from, pixels.
const SIZES: [(u32, u32); 4] = [(1280, 960), (1920, 1080), (1024, 768), (1440, 1080)];

/// Tissue palettes, sRGB: muscle, red tissue, liver, a pale silicone phantom, fat.
const PALETTES: [[[u8; 3]; 2]; 5] = [
    [[205, 105, 100], [180, 80, 85]],
    [[170, 55, 50], [140, 40, 45]],
    [[120, 40, 35], [95, 30, 35]],
    [[232, 145, 140], [220, 125, 130]],
    [[225, 175, 100], [210, 150, 90]],
];

/// Dyed braided sutures, sRGB (violet polyglactin and its shades).
const THREADS: [[u8; 3]; 4] = [[95, 50, 150], [110, 60, 170], [80, 42, 128], [120, 72, 165]];

fn linear(c: [u8; 3]) -> [f64; 3] {
    c.map(|v| (f64::from(v) / 255.0).powf(2.2))
}

/// `n` samples from `seed`, for a needle of `needle`'s radius and wire.
pub fn dataset(n: usize, seed: u64, needle: Needle) -> Vec<Sample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1D_E9E4_DE47);
    (0..n).map(|_| sample(&mut rng, &needle)).collect()
}

fn unit_in_cone(rng: &mut ChaCha8Rng, axis: &Vector, cone: f64) -> Vector {
    let c = rng.random_range(cone.cos()..1.0);
    let s = (1.0 - c * c).sqrt();
    let phi = rng.random_range(0.0..TAU);
    let (a, b) = perpendiculars(axis);
    (a * (s * phi.cos()) + b * (s * phi.sin()) + axis * c).normalize()
}

/// Two unit vectors perpendicular to `v` and to each other.
fn perpendiculars(v: &Vector) -> (Vector, Vector) {
    let n = v.normalize();
    let helper = if n.x.abs() < 0.8 {
        Vector::x()
    } else {
        Vector::y()
    };
    let a = n.cross(&helper).normalize();
    (a, n.cross(&a))
}

fn sample(rng: &mut ChaCha8Rng, needle: &Needle) -> Sample {
    let r = needle.radius_m;
    let wire_r = needle.wire_diameter_m / 2.0;
    // Rejection sampling of the geometry; each draw is cheap and most pass.
    let mut attempt = 0;
    loop {
        attempt += 1;
        let center0 = Point::new(
            rng.random_range(-0.02..0.02),
            rng.random_range(-0.02..0.02),
            rng.random_range(0.006..0.03),
        );
        // The camera, relative to the needle.
        let distance = (rng.random_range(0.07f64.ln()..0.22f64.ln())).exp();
        let elevation = rng.random_range(35f64..85.0).to_radians();
        let azimuth = rng.random_range(0.0..TAU);
        let eye = center0
            + Vector::new(
                elevation.cos() * azimuth.cos(),
                elevation.cos() * azimuth.sin(),
                elevation.sin(),
            ) * distance;
        let (width, height) = SIZES[rng.random_range(0..SIZES.len())];
        // The needle's normal: presented to the camera, or lying roughly flat.
        let to_eye = (eye - center0).normalize();
        let presented = rng.random_bool(0.4);
        let normal = if presented {
            unit_in_cone(rng, &to_eye, 35f64.to_radians())
        } else {
            unit_in_cone(rng, &Vector::z(), 45f64.to_radians())
        };
        let normal = if rng.random_bool(0.5) {
            normal
        } else {
            -normal
        };
        // A needle seen within 18° of edge-on shows no arc: no image can place it.
        if normal.dot(&to_eye).abs() < 0.31 {
            continue;
        }
        let (e1, e2) = perpendiculars(&normal);
        let spin = rng.random_range(0.0..TAU);
        let x = e1 * spin.cos() + e2 * spin.sin();
        let y = normal.cross(&x);
        let rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
            Matrix3::from_columns(&[x, y, normal]),
        ));
        // Lift it clear of the tissue.
        let lowest = (0..=32)
            .map(|k| (center0 + rot * needle.point_at(PI * f64::from(k) / 32.0).coords).z)
            .fold(f64::INFINITY, f64::min);
        let center = center0 + Vector::z() * (0.0015 - lowest).max(0.0);
        let truth = Pose::from_parts(Translation3::from(center.coords), rot);
        // Look near the needle, not at it: the needle lands anywhere in the middle of the
        // frame.
        let aim = center
            + Vector::new(
                rng.random_range(-0.3..0.3),
                rng.random_range(-0.3..0.3),
                0.0,
            ) * (distance * 0.35);
        let forward = (aim - eye).normalize();
        let right0 = forward.cross(&Vector::z()).normalize();
        let down0 = forward.cross(&right0);
        let roll = rng.random_range(-25f64..25.0).to_radians();
        let right = right0 * roll.cos() + down0 * roll.sin();
        let down = forward.cross(&right);
        let cam_rot = UnitQuaternion::from_rotation_matrix(&Rotation3::from_matrix_unchecked(
            Matrix3::from_columns(&[right, down, forward]),
        ));
        let camera_to_robot = Pose::from_parts(Translation3::from(eye.coords), cam_rot);
        // Intrinsics: the wire at least 2 pixels wide, the needle at most 40 % of the height.
        let arc: Vec<Point> = (0..=48)
            .map(|k| truth * needle.point_at(PI * f64::from(k) / 48.0))
            .collect();
        let to_cam = camera_to_robot.inverse();
        let depths: Vec<f64> = arc.iter().map(|p| (to_cam * p).z).collect();
        let (zmin, zmax) = depths
            .iter()
            .fold((f64::INFINITY, 0.0f64), |(a, b), &z| (a.min(z), b.max(z)));
        if zmin < 0.04 {
            continue;
        }
        let f_lo = 800f64.max(2.0 * zmax / needle.wire_diameter_m);
        let f_hi = 2400f64.min(0.4 * f64::from(height) * zmin / (2.0 * r));
        if f_lo >= f_hi {
            continue;
        }
        let fx = rng.random_range(f_lo..f_hi);
        let cx = f64::from(width) / 2.0 + rng.random_range(-15.0..15.0);
        let cy = f64::from(height) / 2.0 + rng.random_range(-15.0..15.0);
        // The baseline: 4 mm to 7 cm, but not so short for the distance that a pixel of
        // disparity spans more than 2.5 mm of depth at the needle (a dVRK endoscope's 5.5 mm
        // at 10 cm is about 1.8 mm a pixel; a 4 mm baseline at 21 cm, 10 mm, where no stereo
        // method can place a 0.7 mm wire's arc).
        let z_mid = depths.iter().sum::<f64>() / depths.len() as f64;
        let b_lo = 0.004f64.max(z_mid * z_mid / (fx * MAX_DEPTH_STEP_M));
        if b_lo >= 0.07 {
            continue;
        }
        let baseline_m = rng.random_range(b_lo.ln()..0.07f64.ln()).exp();
        let calibration = StereoCalibration {
            fx,
            fy: fx,
            cx,
            cy,
            baseline_m,
            width,
            height,
            camera_to_robot,
        };
        let in_view = |b: f64| {
            arc.iter().all(|p| {
                let q = to_cam * p;
                let u = fx * (q.x - b) / q.z + cx;
                let v = fx * q.y / q.z + cy;
                u > 16.0 && v > 16.0 && u < f64::from(width) - 16.0 && v < f64::from(height) - 16.0
            })
        };
        // Both views must see the whole needle; after 5,000 draws (statistically
        // unreachable) the last one is kept rather than loop forever.
        if !(in_view(0.0) && in_view(baseline_m)) && attempt < 5000 {
            continue;
        }
        return build(rng, needle, calibration, truth, wire_r, presented);
    }
}

/// Everything but the rig: the needle's shape, jaw, thread, tissue, light and camera effects.
fn build(
    rng: &mut ChaCha8Rng,
    needle: &Needle,
    calibration: StereoCalibration,
    truth: Pose,
    wire_r: f64,
    _presented: bool,
) -> Sample {
    let r = needle.radius_m;
    let eye = Point::from(calibration.camera_to_robot.translation.vector);
    let forward = calibration.camera_to_robot.rotation * Vector::z();
    let grey = rng.random_range(0.32..0.55);
    let tint = rng.random_range(-0.03..0.03);
    let shape = NeedleShape {
        to_local: truth.inverse(),
        radius: r,
        wire_r,
        tip_r: rng.random_range(0.00002..0.00006),
        taper_len: rng.random_range(0.0015..0.0035),
        taper_power: rng.random_range(0.6..1.2),
        swage_scale: rng.random_range(1.1..1.35),
        swage_len: rng.random_range(0.001..0.0025),
        albedo: [grey + tint, grey, grey - tint],
        specular: rng.random_range(0.5..1.0),
        shininess: rng.random_range(15.0..80.0),
        reflect: rng.random_range(0.2..0.45),
        sky: [rng.random_range(0.5..0.9); 3],
        ground: [0.0; 3],
    };
    let point = |a: f64| truth * needle.point_at(a);
    let tangent = |a: f64| truth.rotation * Vector::new(-a.sin(), a.cos(), 0.0);
    let mut capsules = Vec::new();
    // The thread: from the swage, on along the needle's curve for a few millimetres, then
    // beside the needle or looped over it, down to where it enters the tissue.
    let thread_over = rng.random_bool(0.35);
    let swage = point(PI);
    let out = swage + tangent(PI) * rng.random_range(0.002..0.004);
    let to_eye = |p: &Point| (eye - p).normalize();
    let mid = if thread_over {
        let p = point(rng.random_range(0.4..2.4));
        p + to_eye(&p) * rng.random_range(0.002..0.005)
    } else {
        let a = rng.random_range(0.0..TAU);
        let c = Point::from(truth.translation.vector);
        let d = rng.random_range(0.015..0.03);
        Point::new(
            c.x + d * a.cos(),
            c.y + d * a.sin(),
            rng.random_range(0.003..0.015),
        )
    };
    let anchor = {
        let a = rng.random_range(0.0..TAU);
        let d = rng.random_range(0.025..0.05);
        Point::new(swage.x + d * a.cos(), swage.y + d * a.sin(), -0.0005)
    };
    let thread_r = rng.random_range(0.00011..0.00019);
    let thread_material = Material {
        albedo: linear(THREADS[rng.random_range(0..THREADS.len())]),
        specular: rng.random_range(0.02..0.12),
        shininess: 12.0,
    };
    let path = catmull_rom(&[swage, out, mid, anchor], 24);
    for w in path.windows(2) {
        capsules.push(Capsule {
            a: w[0],
            b: w[1],
            r: thread_r,
            material: thread_material,
        });
    }
    let thread_capsules = capsules.len();
    // The jaw, in about half of the pairs.
    let jaw = if rng.random_bool(0.55) {
        let near_tip = rng.random_bool(0.5);
        let angle = if near_tip {
            rng.random_range(20f64..65.0).to_radians()
        } else {
            rng.random_range(115f64..160.0).to_radians()
        };
        let g = point(angle);
        let t = tangent(angle);
        let n = truth.rotation * Vector::z();
        // The shaft leaves upwards, tilted off the needle's normal.
        let up = if n.z >= 0.0 { n } else { -n };
        let mut u = unit_in_cone(rng, &up, 35f64.to_radians());
        if u.z < 0.2 {
            u = (u + Vector::z()).normalize();
        }
        // The fingers straddle the wire; they close across it.
        let w = t.cross(&u).normalize();
        let finger_r = rng.random_range(0.0006..0.0009);
        let dark = rng.random_range(0.02..0.08);
        let steel = Material {
            albedo: [dark; 3],
            specular: rng.random_range(0.15..0.4),
            shininess: 40.0,
        };
        let black = Material {
            albedo: [0.015; 3],
            specular: 0.15,
            shininess: 25.0,
        };
        for s in [-1.0, 1.0] {
            let o = w * (s * (wire_r + finger_r));
            capsules.push(Capsule {
                a: g + o - u * 0.0015,
                b: g + o + u * 0.007,
                r: finger_r,
                material: steel,
            });
        }
        capsules.push(Capsule {
            a: g + u * 0.007,
            b: g + u * 0.012,
            r: 0.0022,
            material: steel,
        });
        capsules.push(Capsule {
            a: g + u * 0.012,
            b: g + u * 0.15,
            r: 0.004,
            material: black,
        });
        Some(JawHint {
            jaw: g,
            end: if near_tip {
                NeedleEnd::Tip
            } else {
                NeedleEnd::Swage
            },
        })
    } else {
        None
    };
    let palette = PALETTES[rng.random_range(0..PALETTES.len())];
    let tissue = Tissue {
        base: linear(palette[0]),
        second: linear(palette[1]),
        vessel: linear([110, 25, 30]),
        scale_m: rng.random_range(0.003..0.012),
        vessel_scale_m: rng.random_range(0.004..0.01),
        bump: rng.random_range(0.1..0.6),
        // Wet tissue: small, sharp, clipped highlights.
        specular: rng.random_range(0.03..0.25),
        shininess: rng.random_range(150.0..600.0),
        offset: [rng.random_range(0.0..100.0), rng.random_range(0.0..100.0)],
    };
    let mut shape = shape;
    shape.ground = tissue.base.map(|c| c * 0.6);
    // The light beside the lens; sometimes a second one above. The exposure puts the
    // needle's surroundings at a mid grey to near white.
    let cam = calibration.camera_to_robot.rotation;
    let main = eye
        + cam
            * Vector::new(
                rng.random_range(-0.03..0.03),
                rng.random_range(-0.03..0.03),
                0.0,
            );
    let needle_c = Point::from(truth.translation.vector);
    let temperature = rng.random_range(-1.0..1.0);
    let colour = [1.0 + 0.06 * temperature, 1.0, 1.0 - 0.08 * temperature];
    let exposure = rng.random_range(0.7..1.2);
    let d2 = (main - needle_c).norm_squared();
    let mut lights = vec![Light {
        position: main,
        intensity: colour.map(|c| c * exposure * d2),
        shadows: true,
    }];
    if rng.random_bool(0.4) {
        let above = needle_c
            + Vector::new(
                rng.random_range(-0.2..0.2),
                rng.random_range(-0.2..0.2),
                rng.random_range(0.2..0.4),
            );
        let s = rng.random_range(0.2..0.5) * (above - needle_c).norm_squared();
        lights.push(Light {
            position: above,
            intensity: [s; 3],
            shadows: false,
        });
    }
    let _ = forward;
    let camera = CameraEffects {
        vignetting: rng.random_range(0.0..0.35),
        white_balance: [
            rng.random_range(0.94..1.06),
            1.0,
            rng.random_range(0.94..1.06),
        ],
        blur_sigma_px: rng.random_range(0.3..1.4),
        read_noise: rng.random_range(1.0..4.0),
        shot_noise: rng.random_range(0.0..0.25),
    };
    let groups = capsules
        .chunks(GROUP)
        .map(|run| {
            let n = (2 * run.len()) as f64;
            let centre =
                Point::from(run.iter().map(|c| c.a.coords + c.b.coords).sum::<Vector>() / n);
            let r = run
                .iter()
                .map(|c| (c.a - centre).norm().max((c.b - centre).norm()) + c.r)
                .fold(0.0, f64::max);
            (centre, r)
        })
        .collect();
    let scene = Scene {
        needle: shape,
        capsules,
        thread_capsules,
        groups,
        tissue,
        lights,
        ambient: rng.random_range(0.05..0.2),
        camera,
        seed: rng.random(),
    };
    Sample {
        calibration,
        truth,
        jaw,
        thread_over,
        scene,
    }
}

/// A centripetal Catmull–Rom curve through `p`, `per` segments between each pair.
fn catmull_rom(p: &[Point], per: usize) -> Vec<Point> {
    let n = p.len();
    let at = |i: isize| -> Point {
        if i < 0 {
            p[0] + (p[0] - p[1])
        } else if i as usize >= n {
            p[n - 1] + (p[n - 1] - p[n - 2])
        } else {
            p[i as usize]
        }
    };
    let mut out = vec![p[0]];
    for i in 0..n as isize - 1 {
        let (p0, p1, p2, p3) = (at(i - 1), at(i), at(i + 1), at(i + 2));
        let knot = |a: &Point, b: &Point| (b - a).norm().sqrt().max(1e-9);
        let t0 = 0.0;
        let t1 = t0 + knot(&p0, &p1);
        let t2 = t1 + knot(&p1, &p2);
        let t3 = t2 + knot(&p2, &p3);
        for k in 1..=per {
            let t = t1 + (t2 - t1) * k as f64 / per as f64;
            let l = |a: &Point, b: &Point, ta: f64, tb: f64| -> Vector {
                a.coords * ((tb - t) / (tb - ta)) + b.coords * ((t - ta) / (tb - ta))
            };
            let a1 = l(&p0, &p1, t0, t1);
            let a2 = l(&p1, &p2, t1, t2);
            let a3 = l(&p2, &p3, t2, t3);
            let b1 = a1 * ((t2 - t) / (t2 - t0)) + a2 * ((t - t0) / (t2 - t0));
            let b2 = a2 * ((t3 - t) / (t3 - t1)) + a3 * ((t - t1) / (t3 - t1));
            out.push(Point::from(
                b1 * ((t2 - t) / (t2 - t1)) + b2 * ((t - t1) / (t2 - t1)),
            ));
        }
    }
    out
}

// ---------------------------------------------------------------------------------------
// The ray tracer. Written by hand: it is the point of this set to draw the pairs another
// way than the mock does, and it is a few hundred lines of intersection and shading.

const TILE: u32 = 16;
/// Where in a pixel near an object its four rays pass.
const JITTER: [(f64, f64); 4] = [(0.25, 0.25), (0.75, 0.25), (0.25, 0.75), (0.75, 0.75)];

/// Which of a view's `TILE`-pixel tiles each object may cover.
struct Tiles {
    /// Tiles per row.
    tw: u32,
    /// The capsules that may cover each tile.
    objects: Vec<Vec<u32>>,
    /// Whether the needle may cover each tile.
    needle: Vec<bool>,
    /// Whether a shadow may fall on each tile (within two tiles of an object).
    near: Vec<bool>,
}
/// The most depth one pixel of disparity may span at the needle, m (see `sample`).
const MAX_DEPTH_STEP_M: f64 = 0.0025;
/// Capsules per bounding sphere for shadow rays.
const GROUP: usize = 8;

#[derive(Clone, Copy)]
enum Hit {
    Tissue,
    Needle,
    Capsule(usize),
}

impl NeedleShape {
    /// The wire's radius at `angle` from the tip, m.
    fn wire_at(&self, angle: f64) -> f64 {
        let s = self.radius * angle;
        if s < self.taper_len {
            return self.tip_r
                + (self.wire_r - self.tip_r)
                    * (s / self.taper_len).max(0.0).powf(self.taper_power);
        }
        let from_swage = self.radius * (PI - angle);
        let ramp = 0.0004;
        if from_swage < self.swage_len {
            self.wire_r * self.swage_scale
        } else if from_swage < self.swage_len + ramp {
            let k = (from_swage - self.swage_len) / ramp;
            self.wire_r * (self.swage_scale + (1.0 - self.swage_scale) * k)
        } else {
            self.wire_r
        }
    }

    /// A distance bound to the needle's surface, needle frame (1-Lipschitz up to the taper's
    /// slope; the tracer steps 0.8 of it).
    fn distance(&self, p: &Point) -> f64 {
        let rho = (p.x * p.x + p.y * p.y).sqrt();
        let theta = p.y.atan2(p.x);
        if (0.0..=PI).contains(&theta) {
            ((rho - self.radius).powi(2) + p.z * p.z).sqrt() - self.wire_at(theta)
        } else {
            let tip = Point::new(self.radius, 0.0, 0.0);
            let swage = Point::new(-self.radius, 0.0, 0.0);
            let dt = (p - tip).norm() - self.tip_r;
            let ds = (p - swage).norm() - self.wire_r * self.swage_scale;
            dt.min(ds)
        }
    }

    fn max_r(&self) -> f64 {
        self.wire_r * self.swage_scale
    }

    /// The first hit of a world ray within `t_max`, if any.
    fn trace(&self, o: &Point, d: &Vector, t_max: f64) -> Option<f64> {
        let lo = self.to_local * o;
        let ld = self.to_local.rotation * d;
        // The bounding sphere.
        let bound = self.radius + self.max_r() + 1e-4;
        let b = lo.coords.dot(&ld);
        let c = lo.coords.norm_squared() - bound * bound;
        let h = b * b - c;
        if h < 0.0 {
            return None;
        }
        let (mut t, t_out) = ((-b - h.sqrt()).max(0.0), (-b + h.sqrt()).min(t_max));
        for _ in 0..240 {
            if t > t_out {
                return None;
            }
            let dist = self.distance(&(lo + ld * t));
            if dist < 1e-6 {
                return Some(t);
            }
            t += (0.8 * dist).max(2e-7);
        }
        None
    }

    fn normal(&self, world: &Point) -> Vector {
        let p = self.to_local * world;
        let e = 2e-6;
        let g = Vector::new(
            self.distance(&(p + Vector::x() * e)) - self.distance(&(p - Vector::x() * e)),
            self.distance(&(p + Vector::y() * e)) - self.distance(&(p - Vector::y() * e)),
            self.distance(&(p + Vector::z() * e)) - self.distance(&(p - Vector::z() * e)),
        );
        self.to_local.inverse().rotation * g.try_normalize(1e-12).unwrap_or_else(Vector::z)
    }
}

/// Ray–capsule intersection (`d` unit): the entry distance, if any.
fn hit_capsule(o: &Point, d: &Vector, c: &Capsule) -> Option<f64> {
    let ba = c.b - c.a;
    let oa = o - c.a;
    let baba = ba.dot(&ba);
    let bard = ba.dot(d);
    let baoa = ba.dot(&oa);
    let rdoa = d.dot(&oa);
    let oaoa = oa.dot(&oa);
    let a = baba - bard * bard;
    let b = baba * rdoa - baoa * bard;
    let cc = baba * oaoa - baoa * baoa - c.r * c.r * baba;
    let h = b * b - a * cc;
    if h >= 0.0 && a.abs() > 1e-18 {
        let t = (-b - h.sqrt()) / a;
        let y = baoa + t * bard;
        if y > 0.0 && y < baba {
            return (t > 0.0).then_some(t);
        }
        let oc = if y <= 0.0 { oa } else { o - c.b };
        let b = d.dot(&oc);
        let cc = oc.dot(&oc) - c.r * c.r;
        let h = b * b - cc;
        if h > 0.0 {
            let t = -b - h.sqrt();
            return (t > 0.0).then_some(t);
        }
    }
    None
}

fn capsule_normal(p: &Point, c: &Capsule) -> Vector {
    let ba = c.b - c.a;
    let k = ((p - c.a).dot(&ba) / ba.dot(&ba)).clamp(0.0, 1.0);
    (p - (c.a + ba * k))
        .try_normalize(1e-12)
        .unwrap_or_else(Vector::z)
}

/// `x.floor()` for the noise lattice (|x| well under 2⁶²), inlined: the target's baseline has
/// no rounding instruction, so `f64::floor` is a library call, 5 % of the render time.
#[inline]
fn floor(x: f64) -> f64 {
    let t = x as i64 as f64;
    if t > x { t - 1.0 } else { t }
}

/// 32 unit gradients evenly around the circle (a table: the per-lattice-point sine and
/// cosine were most of the renderer's time).
const GRADIENTS: [(f64, f64); 32] = {
    let mut g = [(0.0, 0.0); 32];
    let mut i = 0;
    while i < 32 {
        // cos and sin of 2πi/32 by their Taylor series (const context has no libm).
        let a = TAU * i as f64 / 32.0 - PI;
        let (mut c, mut s, mut term_c, mut term_s) = (0.0, 0.0, 1.0, a);
        let mut k = 0;
        while k < 20 {
            c += term_c;
            s += term_s;
            term_c *= -a * a / (((2 * k + 1) * (2 * k + 2)) as f64);
            term_s *= -a * a / (((2 * k + 2) * (2 * k + 3)) as f64);
            k += 1;
        }
        g[i] = (c, s);
        i += 1;
    }
    g
};

/// Gradient noise (a hashed-gradient lattice, quintic fade), about −1 to 1.
fn gradient_noise(x: f64, y: f64, salt: u64) -> f64 {
    let (xi, yi) = (floor(x), floor(y));
    let (fx, fy) = (x - xi, y - yi);
    let grad = |ix: f64, iy: f64, dx: f64, dy: f64| {
        let mut h = (ix as i64 as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
            ^ (iy as i64 as u64).wrapping_mul(0xC2B2_AE3D_27D4_EB4F)
            ^ salt;
        h ^= h >> 31;
        h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
        h ^= h >> 29;
        let (gx, gy) = GRADIENTS[(h & 31) as usize];
        gx * dx + gy * dy
    };
    let fade = |t: f64| t * t * t * (t * (t * 6.0 - 15.0) + 10.0);
    let (u, v) = (fade(fx), fade(fy));
    let n00 = grad(xi, yi, fx, fy);
    let n10 = grad(xi + 1.0, yi, fx - 1.0, fy);
    let n01 = grad(xi, yi + 1.0, fx, fy - 1.0);
    let n11 = grad(xi + 1.0, yi + 1.0, fx - 1.0, fy - 1.0);
    let a = n00 + (n10 - n00) * u;
    let b = n01 + (n11 - n01) * u;
    (a + (b - a) * v) * 1.4
}

fn fbm(x: f64, y: f64, octaves: u32, salt: u64) -> f64 {
    let (mut s, mut amp, mut freq, mut norm) = (0.0, 1.0, 1.0, 0.0);
    for o in 0..octaves {
        s += amp * gradient_noise(x * freq, y * freq, salt.wrapping_add(u64::from(o)));
        norm += amp;
        amp *= 0.5;
        freq *= 2.03;
    }
    s / norm
}

/// Cellular noise: the gap between the nearest and second-nearest feature points (small on
/// cell borders: the vessels).
fn cell_border(x: f64, y: f64) -> f64 {
    let (xi, yi) = (floor(x) as i64, floor(y) as i64);
    let (mut d1, mut d2) = (f64::INFINITY, f64::INFINITY);
    for dy in -1..=1 {
        for dx in -1..=1 {
            let (cx, cy) = (xi + dx, yi + dy);
            let mut h = (cx as u64).wrapping_mul(0x9E37_79B9_7F4A_7C15)
                ^ (cy as u64).wrapping_mul(0xD6E8_FEB8_6659_FD93);
            h ^= h >> 32;
            h = h.wrapping_mul(0xFF51_AFD7_ED55_8CCD);
            let px = cx as f64 + (h & 0xFFFF) as f64 / 65536.0;
            let py = cy as f64 + ((h >> 16) & 0xFFFF) as f64 / 65536.0;
            let d = ((px - x).powi(2) + (py - y).powi(2)).sqrt();
            if d < d1 {
                d2 = d1;
                d1 = d;
            } else if d < d2 {
                d2 = d;
            }
        }
    }
    d2 - d1
}

impl Tissue {
    fn height(&self, x: f64, y: f64) -> f64 {
        fbm(
            x / self.scale_m * 3.0 + self.offset[0],
            y / self.scale_m * 3.0 + self.offset[1],
            3,
            7,
        )
    }

    /// Albedo (linear) and the bumped normal at a point of the plane.
    fn surface(&self, p: &Point) -> ([f64; 3], Vector) {
        let (u, v) = (
            p.x / self.scale_m + self.offset[0],
            p.y / self.scale_m + self.offset[1],
        );
        let mix = (0.5 + 0.5 * fbm(u, v, 4, 3)).clamp(0.0, 1.0);
        let fine = 0.85 + 0.3 * (0.5 + 0.5 * gradient_noise(u * 9.0, v * 9.0, 11));
        let border = cell_border(
            p.x / self.vessel_scale_m + self.offset[1],
            p.y / self.vessel_scale_m + self.offset[0],
        );
        let vessel = (1.0 - border / 0.08).clamp(0.0, 1.0) * 0.6;
        let mut albedo = [0.0; 3];
        for (k, a) in albedo.iter_mut().enumerate() {
            let c = self.base[k] + (self.second[k] - self.base[k]) * mix;
            *a = (c * fine) * (1.0 - vessel) + self.vessel[k] * vessel;
        }
        let e = self.scale_m * 0.02;
        let h0 = self.height(p.x, p.y);
        let hx = self.height(p.x + e, p.y) - h0;
        let hy = self.height(p.x, p.y + e) - h0;
        // Height amplitude, m: a few tenths of a millimetre of relief.
        let a = self.bump * 0.0003;
        let n = Vector::new(-a * hx / e, -a * hy / e, 1.0).normalize();
        (albedo, n)
    }
}

impl Scene {
    /// The nearest hit along a ray: what, and how far.
    fn cast(&self, o: &Point, d: &Vector, capsules: &[u32], needle: bool) -> Option<(Hit, f64)> {
        let mut best = if d.z < -1e-9 {
            Some((Hit::Tissue, -o.z / d.z))
        } else {
            None
        };
        let limit = |b: &Option<(Hit, f64)>| b.map_or(f64::INFINITY, |(_, t)| t);
        for &i in capsules {
            let c = &self.capsules[i as usize];
            if let Some(t) = hit_capsule(o, d, c) {
                if t < limit(&best) {
                    best = Some((Hit::Capsule(i as usize), t));
                }
            }
        }
        if needle {
            if let Some(t) = self.needle.trace(o, d, limit(&best)) {
                best = Some((Hit::Needle, t));
            }
        }
        best
    }

    /// Whether the path from `p` to a light is blocked.
    fn shadowed(&self, p: &Point, light: &Point) -> bool {
        let v = light - p;
        let dist = v.norm();
        let d = v / dist;
        let o = p + d * 1e-5;
        self.groups
            .iter()
            .zip(self.capsules.chunks(GROUP))
            .any(|((centre, r), run)| {
                // Ray against the run's bounding sphere first.
                let oc = o - centre;
                let b = oc.dot(&d);
                let c = oc.norm_squared() - r * r;
                (c < 0.0 || (b < 0.0 && b * b > c))
                    && run
                        .iter()
                        .any(|c| hit_capsule(&o, &d, c).is_some_and(|t| t < dist))
            })
            || self.needle.trace(&o, &d, dist).is_some()
    }

    /// Linear radiance seen along a ray that hit `hit` at distance `t`.
    fn shade(&self, o: &Point, d: &Vector, hit: Hit, t: f64, shadows: bool) -> [f64; 3] {
        let p = o + d * t;
        let view = -d;
        let (albedo, n, specular, shininess, reflect) = match hit {
            Hit::Tissue => {
                let (a, n) = self.tissue.surface(&p);
                (a, n, self.tissue.specular, self.tissue.shininess, 0.0)
            }
            Hit::Needle => (
                self.needle.albedo,
                self.needle.normal(&p),
                self.needle.specular,
                self.needle.shininess,
                self.needle.reflect,
            ),
            Hit::Capsule(i) => {
                let c = &self.capsules[i];
                (
                    c.material.albedo,
                    capsule_normal(&p, c),
                    c.material.specular,
                    c.material.shininess,
                    0.0,
                )
            }
        };
        let n = if n.dot(&view) < 0.0 { -n } else { n };
        let mut out = albedo.map(|a| a * self.ambient);
        for light in &self.lights {
            let lv = light.position - p;
            let d2 = lv.norm_squared();
            let l = lv / d2.sqrt();
            let ndl = n.dot(&l);
            if ndl <= 0.0 {
                continue;
            }
            if light.shadows && shadows && self.shadowed(&p, &light.position) {
                continue;
            }
            let h = (l + view).normalize();
            let spec = specular * n.dot(&h).max(0.0).powf(shininess) * (shininess + 8.0) / 32.0;
            for k in 0..3 {
                let e = light.intensity[k] / d2;
                out[k] += e * (albedo[k] * ndl + spec);
            }
        }
        if reflect > 0.0 {
            let r = d - n * (2.0 * d.dot(&n));
            let env = if r.z > 0.0 {
                self.needle.sky
            } else {
                self.needle.ground
            };
            let fresnel = reflect + (1.0 - reflect) * (1.0 - n.dot(&view).max(0.0)).powi(5) * 0.5;
            for k in 0..3 {
                out[k] = out[k] * (1.0 - fresnel) + env[k] * fresnel;
            }
        }
        out
    }

    /// Which of a view's tiles each object may cover (`eye`: the view's origin).
    fn tiles(&self, calib: &StereoCalibration, eye: &Point) -> Tiles {
        let (w, h) = (calib.width, calib.height);
        let rot = calib.camera_to_robot.rotation;
        let to_cam = |p: &Point| rot.inverse() * (p - eye);
        // Which tiles each object may cover: capsules by their projected ends, the needle
        // by points along its arc, each grown by its projected radius.
        let (tw, th) = (w.div_ceil(TILE), h.div_ceil(TILE));
        let mut tiles: Vec<Vec<u32>> = vec![Vec::new(); (tw * th) as usize];
        let mut needle_tiles = vec![false; (tw * th) as usize];
        let mut near = vec![false; (tw * th) as usize];
        let mark = |a: &Point, b: &Point, r: f64, f: &mut dyn FnMut(usize)| {
            // Clip to the front of the camera.
            let (qa, qb) = (to_cam(a), to_cam(b));
            let zmin = 0.005;
            if qa.z < zmin && qb.z < zmin {
                return;
            }
            let clip = |p: &Vector, q: &Vector| -> Vector {
                if p.z >= zmin {
                    *p
                } else {
                    p + (q - p) * ((zmin - p.z) / (q.z - p.z))
                }
            };
            let (pa, pb) = (clip(&qa, &qb), clip(&qb, &qa));
            let pr = |v: &Vector| {
                (
                    calib.fx * v.x / v.z + calib.cx,
                    calib.fy * v.y / v.z + calib.cy,
                )
            };
            let ((ua, va), (ub, vb)) = (pr(&pa), pr(&pb));
            let pad = calib.fx * r / pa.z.min(pb.z) + 3.0;
            let x0 = ((ua.min(ub) - pad).max(0.0) as u32 / TILE).min(tw - 1);
            let x1 = ((ua.max(ub) + pad).clamp(0.0, f64::from(w - 1)) as u32 / TILE).min(tw - 1);
            let y0 = ((va.min(vb) - pad).max(0.0) as u32 / TILE).min(th - 1);
            let y1 = ((va.max(vb) + pad).clamp(0.0, f64::from(h - 1)) as u32 / TILE).min(th - 1);
            if ua.max(ub) + pad < 0.0 || va.max(vb) + pad < 0.0 {
                return;
            }
            for ty in y0..=y1 {
                for tx in x0..=x1 {
                    f((ty * tw + tx) as usize);
                }
            }
        };
        for (i, c) in self.capsules.iter().enumerate() {
            mark(&c.a, &c.b, c.r, &mut |k| tiles[k].push(i as u32));
        }
        let local_to_world = self.needle.to_local.inverse();
        let arc: Vec<Point> = (0..=96)
            .map(|k| {
                let a = -0.1 + (PI + 0.2) * f64::from(k) / 96.0;
                local_to_world
                    * Point::new(
                        self.needle.radius * a.cos(),
                        self.needle.radius * a.sin(),
                        0.0,
                    )
            })
            .collect();
        for s in arc.windows(2) {
            mark(&s[0], &s[1], self.needle.max_r() * 2.0, &mut |k| {
                needle_tiles[k] = true
            });
        }
        // Shadows fall near what casts them: tiles within two of an object.
        for ty in 0..th {
            for tx in 0..tw {
                let k = (ty * tw + tx) as usize;
                if needle_tiles[k] || !tiles[k].is_empty() {
                    for dy in -2i64..=2 {
                        for dx in -2i64..=2 {
                            let (x, y) = (i64::from(tx) + dx, i64::from(ty) + dy);
                            if x >= 0 && y >= 0 && x < i64::from(tw) && y < i64::from(th) {
                                near[(y as u32 * tw + x as u32) as usize] = true;
                            }
                        }
                    }
                }
            }
        }
        Tiles {
            tw,
            objects: tiles,
            needle: needle_tiles,
            near,
        }
    }

    /// The view's origin: the left camera, or moved along its x by `shift_m`.
    fn eye(calib: &StereoCalibration, shift_m: f64) -> Point {
        Point::from(calib.camera_to_robot.translation.vector)
            + calib.camera_to_robot.rotation * Vector::x() * shift_m
    }

    /// One view: origin the left camera, or moved along its x by `shift_m` (the baseline).
    fn view(&self, calib: &StereoCalibration, shift_m: f64, rng: &mut ChaCha8Rng) -> RgbImage {
        let (w, h) = (calib.width, calib.height);
        let rot = calib.camera_to_robot.rotation;
        let eye = Self::eye(calib, shift_m);
        let Tiles {
            tw,
            objects: tiles,
            needle: needle_tiles,
            near,
        } = self.tiles(calib, &eye);
        let mut linear = vec![[0.0f64; 3]; (w * h) as usize];
        let ray = |u: f64, v: f64| -> Vector {
            (rot * Vector::new((u - calib.cx) / calib.fx, (v - calib.cy) / calib.fy, 1.0))
                .normalize()
        };
        // Rows on all cores (each pixel is a pure function of the scene: the order cannot
        // change the image).
        use rayon::prelude::*;
        linear
            .par_chunks_mut(w as usize)
            .enumerate()
            .for_each(|(y, row)| {
                let y = y as u32;
                for x in 0..w {
                    let k = ((y / TILE) * tw + x / TILE) as usize;
                    let objects = needle_tiles[k] || !tiles[k].is_empty();
                    let samples: &[(f64, f64)] = if objects { &JITTER } else { &[(0.5, 0.5)] };
                    let mut acc = [0.0; 3];
                    for &(jx, jy) in samples {
                        let d = ray(f64::from(x) + jx, f64::from(y) + jy);
                        let c = match self.cast(&eye, &d, &tiles[k], needle_tiles[k]) {
                            Some((hit, t)) => self.shade(&eye, &d, hit, t, near[k]),
                            None => [0.0; 3],
                        };
                        for i in 0..3 {
                            acc[i] += c[i];
                        }
                    }
                    let n = samples.len() as f64;
                    row[x as usize] = acc.map(|a| a / n);
                }
            });
        self.develop(&linear, w, h, calib, rng)
    }

    /// What each pixel of a view shows ([`Label`] as `u8`, row-major): of the four rays the
    /// view's image traces through a pixel near an object, what most of them hit (a tie
    /// goes to the needle, then the thread, then the instrument).
    fn labels(&self, calib: &StereoCalibration, shift_m: f64) -> Vec<u8> {
        let (w, h) = (calib.width, calib.height);
        let rot = calib.camera_to_robot.rotation;
        let eye = Self::eye(calib, shift_m);
        let tiles = self.tiles(calib, &eye);
        let ray = |u: f64, v: f64| -> Vector {
            (rot * Vector::new((u - calib.cx) / calib.fx, (v - calib.cy) / calib.fy, 1.0))
                .normalize()
        };
        let mut out = vec![Label::Background as u8; (w * h) as usize];
        use rayon::prelude::*;
        out.par_chunks_mut(w as usize)
            .enumerate()
            .for_each(|(y, row)| {
                let y = y as u32;
                for x in 0..w {
                    let k = ((y / TILE) * tiles.tw + x / TILE) as usize;
                    if !tiles.needle[k] && tiles.objects[k].is_empty() {
                        continue;
                    }
                    // Counts of background, needle, thread, instrument.
                    let mut n = [0u8; 4];
                    for &(jx, jy) in &JITTER {
                        let d = ray(f64::from(x) + jx, f64::from(y) + jy);
                        let l = match self.cast(&eye, &d, &tiles.objects[k], tiles.needle[k]) {
                            Some((Hit::Needle, _)) => Label::Needle,
                            Some((Hit::Capsule(i), _)) if i < self.thread_capsules => Label::Thread,
                            Some((Hit::Capsule(_), _)) => Label::Tool,
                            _ => Label::Background,
                        };
                        n[l as usize] += 1;
                    }
                    // The last of the most hit wins.
                    let best = [Label::Background, Label::Tool, Label::Thread, Label::Needle]
                        .into_iter()
                        .max_by_key(|&l| n[l as usize])
                        .unwrap_or(Label::Background);
                    row[x as usize] = best as u8;
                }
            });
        out
    }

    /// Linear radiance to an 8-bit image: vignetting, white balance, gamma, defocus, noise.
    fn develop(
        &self,
        linear: &[[f64; 3]],
        w: u32,
        h: u32,
        calib: &StereoCalibration,
        rng: &mut ChaCha8Rng,
    ) -> RgbImage {
        let cam = &self.camera;
        let corner = (calib.cx.max(f64::from(w) - calib.cx).powi(2)
            + calib.cy.max(f64::from(h) - calib.cy).powi(2))
        .sqrt();
        let mut g: Vec<[f32; 3]> = Vec::with_capacity(linear.len());
        for y in 0..h {
            for x in 0..w {
                let r = ((f64::from(x) - calib.cx).powi(2) + (f64::from(y) - calib.cy).powi(2))
                    .sqrt()
                    / corner;
                let vig = 1.0 - cam.vignetting * r * r;
                let c = linear[(y * w + x) as usize];
                g.push([0, 1, 2].map(|k| {
                    let v = (c[k] * vig * cam.white_balance[k]).clamp(0.0, 1.0);
                    gamma(v)
                }));
            }
        }
        // Separable Gaussian defocus.
        let s = cam.blur_sigma_px;
        let rad = (3.0 * s).ceil() as i64;
        let kernel: Vec<f32> = (-rad..=rad)
            .map(|i| (-(i * i) as f64 / (2.0 * s * s)).exp() as f32)
            .collect();
        let ksum: f32 = kernel.iter().sum();
        let blur = |src: &[[f32; 3]], horizontal: bool| -> Vec<[f32; 3]> {
            let mut out = vec![[0.0f32; 3]; src.len()];
            for y in 0..i64::from(h) {
                for x in 0..i64::from(w) {
                    let mut acc = [0.0f32; 3];
                    for (j, kv) in kernel.iter().enumerate() {
                        let o = j as i64 - rad;
                        let (sx, sy) = if horizontal {
                            ((x + o).clamp(0, i64::from(w) - 1), y)
                        } else {
                            (x, (y + o).clamp(0, i64::from(h) - 1))
                        };
                        let p = src[(sy * i64::from(w) + sx) as usize];
                        for k in 0..3 {
                            acc[k] += kv * p[k];
                        }
                    }
                    out[(y * i64::from(w) + x) as usize] = acc.map(|a| a / ksum);
                }
            }
            out
        };
        let g = blur(&blur(&g, true), false);
        let mut data = Vec::with_capacity(g.len() * 3);
        for p in g {
            for v in p {
                // Shot noise's variance grows with the signal: σ² = read² + k·level.
                let sigma = (cam.read_noise.powi(2) + cam.shot_noise * f64::from(v)).sqrt();
                let n = gaussian(rng) * sigma;
                data.push((f64::from(v) + n).round().clamp(0.0, 255.0) as u8);
            }
        }
        RgbImage {
            width: w,
            height: h,
            data,
        }
    }
}

/// 255·v^(1/2.2) for v in [0, 1], from a table over √v (fine where the curve is steep),
/// linearly interpolated: 12 million `powf` calls were 10 % of the render time.
fn gamma(v: f64) -> f32 {
    const N: usize = 2048;
    static TABLE: std::sync::OnceLock<Vec<f32>> = std::sync::OnceLock::new();
    let table = TABLE.get_or_init(|| {
        (0..=N)
            .map(|i| ((i as f64 / N as f64).powf(2.0 / 2.2) * 255.0) as f32)
            .collect()
    });
    let x = v.clamp(0.0, 1.0).sqrt() * N as f64;
    let i = (x as usize).min(N - 1);
    let f = (x - i as f64) as f32;
    table[i] + (table[i + 1] - table[i]) * f
}

/// One standard normal draw (Box–Muller).
pub(crate) fn gaussian(rng: &mut ChaCha8Rng) -> f64 {
    let u1: f64 = rng.random_range(1e-12..1.0);
    let u2: f64 = rng.random();
    (-2.0 * u1.ln()).sqrt() * (TAU * u2).cos()
}

/// Ray-trace a sample's stereo pair (left, right).
pub fn render(sample: &Sample) -> (RgbImage, RgbImage) {
    let mut rng = ChaCha8Rng::seed_from_u64(sample.scene.seed);
    let left = sample.scene.view(&sample.calibration, 0.0, &mut rng);
    let right = sample
        .scene
        .view(&sample.calibration, sample.calibration.baseline_m, &mut rng);
    (left, right)
}

/// A sample's left image alone (the same pixels as [`render`]'s left).
pub fn render_left(sample: &Sample) -> RgbImage {
    let mut rng = ChaCha8Rng::seed_from_u64(sample.scene.seed);
    sample.scene.view(&sample.calibration, 0.0, &mut rng)
}

/// What each pixel of a sample's left and right images shows ([`Label`] as `u8`, row-major):
/// the truth segmentation is scored against. Cheap next to [`render`] (no shading).
pub fn render_labels(sample: &Sample) -> (Vec<u8>, Vec<u8>) {
    let c = &sample.calibration;
    (
        sample.scene.labels(c, 0.0),
        sample.scene.labels(c, c.baseline_m),
    )
}

/// The renderer's version: part of a cached pair's file name, raised whenever a change to
/// the renderer changes its images, so a cache never serves pairs an older renderer made.
pub const RENDER_VERSION: u32 = 3;

/// A sample's pair from `cache` if it holds it, else rendered (and written there when
/// `cache` is given; a pair that cannot be written is still returned). The files are raw
/// 8-bit RGB, named by the renderer's version, the scene's seed and the size.
pub fn render_cached(sample: &Sample, cache: Option<&std::path::Path>) -> (RgbImage, RgbImage) {
    let Some(dir) = cache else {
        return render(sample);
    };
    let (w, h) = (sample.calibration.width, sample.calibration.height);
    let name = |side: &str| {
        dir.join(format!(
            "v{RENDER_VERSION}-{:016x}-{w}x{h}-{side}.rgb",
            sample.scene.seed
        ))
    };
    let read = |side: &str| -> Option<RgbImage> {
        let data = std::fs::read(name(side)).ok()?;
        (data.len() == (w * h * 3) as usize).then_some(RgbImage {
            width: w,
            height: h,
            data,
        })
    };
    if let (Some(l), Some(r)) = (read("left"), read("right")) {
        return (l, r);
    }
    let (l, r) = render(sample);
    // A cache is an optimisation: a full disk only costs the next run the render.
    let _ = std::fs::create_dir_all(dir)
        .and_then(|()| std::fs::write(name("left"), &l.data))
        .and_then(|()| std::fs::write(name("right"), &r.data));
    (l, r)
}

/// Builds a pipeline for a rig (a mode of `run`).
pub type MakePipeline =
    dyn Fn(&StereoCalibration) -> Result<NeedlePipeline, PerceptionError> + Sync;

/// Estimate every sample with each pipeline `make` builds for its rig (one per mode), blind
/// or with the sample's jaw hint when there is a jaw; pairs come from `cache` where it holds
/// them (see [`render_cached`]). Pairs are rendered two at a time on
/// the machine's cores, then estimated one after the other (the latencies are one core's).
/// Returns one list of results per mode, in sample order.
pub fn run(
    samples: &[Sample],
    modes: &[(bool, &MakePipeline)],
    seed: u64,
    cache: Option<&std::path::Path>,
) -> Vec<Vec<FrameResult>> {
    let mut results: Vec<Vec<FrameResult>> = vec![Vec::with_capacity(samples.len()); modes.len()];
    for (c, chunk) in samples.chunks(2).enumerate() {
        let started = Instant::now();
        let pairs: Vec<(RgbImage, RgbImage)> = {
            use rayon::prelude::*;
            chunk.par_iter().map(|s| render_cached(s, cache)).collect()
        };
        let render_each = started.elapsed() / chunk.len().max(1) as u32;
        for (k, (s, (left, right))) in chunk.iter().zip(&pairs).enumerate() {
            let i = c * 2 + k;
            for (m, (hinted, make)) in modes.iter().enumerate() {
                let hint = if *hinted { s.jaw } else { None };
                let t0 = Instant::now();
                let out = make(&s.calibration).and_then(|p| {
                    p.estimate(left, right, hint.as_ref(), seed ^ i as u64)
                        .map(|o| (o, p.needle))
                });
                let total = t0.elapsed();
                let r = FrameResult::new(
                    out,
                    &s.truth,
                    total,
                    render_each,
                    s.jaw_label(),
                    s.thread_over,
                );
                results[m].push(r);
            }
        }
    }
    results
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_same_seed_gives_the_same_set_and_another_differs() {
        let a = dataset(6, 3, Needle::default());
        let b = dataset(6, 3, Needle::default());
        let c = dataset(6, 4, Needle::default());
        assert_eq!(a, b);
        assert_ne!(a, c);
    }

    #[test]
    fn rigs_vary_and_the_needle_is_in_both_views() {
        let set = dataset(60, 1, Needle::default());
        let needle = Needle::default();
        let (mut dmin, mut dmax) = (f64::INFINITY, 0.0f64);
        let mut sizes = std::collections::BTreeSet::new();
        for s in &set {
            let c = &s.calibration;
            sizes.insert((c.width, c.height));
            let to_cam = c.camera_to_robot.inverse();
            for k in 0..=16 {
                let q = to_cam * (s.truth * needle.point_at(PI * f64::from(k) / 16.0));
                let (u, v) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
                let d = c.fx * c.baseline_m / q.z;
                dmin = dmin.min(d);
                dmax = dmax.max(d);
                for uu in [u, u - d] {
                    assert!(uu > 0.0 && uu < f64::from(c.width), "{uu} in {}", c.width);
                }
                assert!(v > 0.0 && v < f64::from(c.height));
            }
        }
        assert!(sizes.len() >= 3, "{sizes:?}");
        assert!(dmin < 60.0 && dmax > 300.0, "disparities {dmin}..{dmax}");
        let jaws = set.iter().filter(|s| s.jaw.is_some()).count();
        assert!((15..=45).contains(&jaws), "{jaws} of 60 with a jaw");
    }

    #[test]
    fn labels_cover_the_needle_where_it_projects_and_the_thread_and_jaw_appear() {
        let needle = Needle::default();
        let set = dataset(12, 5, needle);
        let mut with_jaw = 0;
        for s in &set {
            let c = &s.calibration;
            let (left, right) = render_labels(s);
            assert_eq!(left.len(), (c.width * c.height) as usize);
            let count = |m: &[u8], l: Label| m.iter().filter(|&&v| v == l as u8).count();
            for m in [&left, &right] {
                assert!(
                    count(m, Label::Needle) > 50,
                    "{} needle pixels",
                    count(m, Label::Needle)
                );
                assert!(
                    count(m, Label::Thread) > 20,
                    "{} thread pixels",
                    count(m, Label::Thread)
                );
                assert!(count(m, Label::Background) > m.len() / 2);
            }
            if s.jaw.is_some() {
                with_jaw += 1;
                assert!(count(&left, Label::Tool) > 0);
            }
            // The middle of the arc's wire, where nothing lies over it, is labelled needle.
            let to_cam = c.camera_to_robot.inverse();
            let (mut on, mut under) = (0, 0);
            for k in 2..=30 {
                let q = to_cam * (s.truth * needle.point_at(PI * f64::from(k) / 32.0));
                let (u, v) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
                let l = left[(v as u32 * c.width + u as u32) as usize];
                on += usize::from(l == Label::Needle as u8);
                under += usize::from(l == Label::Thread as u8 || l == Label::Tool as u8);
            }
            assert!(
                on + under >= 27 && on >= 10,
                "of 29 arc points {on} needle, {under} under"
            );
        }
        assert!(with_jaw > 0);
    }

    #[test]
    fn the_needle_is_drawn_bright_where_it_projects_and_the_tip_tapers() {
        let set = dataset(4, 2, Needle::default());
        let s = &set[0];
        let (left, _) = render(s);
        let c = &s.calibration;
        let to_cam = c.camera_to_robot.inverse();
        let needle = Needle::default();
        // Along the middle of the arc, the pixel at the projection is brighter than the
        // tissue a few wire widths to the side, in most places.
        let mut brighter = 0;
        for k in 4..=28 {
            let a = PI * f64::from(k) / 32.0;
            let q = to_cam * (s.truth * needle.point_at(a));
            let (u, v) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
            let px = |x: f64, y: f64| {
                let i = (y as u32 * left.width + x as u32) as usize * 3;
                left.data[i..i + 3]
                    .iter()
                    .map(|&b| u32::from(b))
                    .sum::<u32>()
            };
            let off = c.fx * 0.003 / q.z;
            if px(u, v) > px(u + off, v + off).min(px(u - off, v - off)) {
                brighter += 1;
            }
        }
        assert!(brighter >= 15, "{brighter} of 25");
        let shape = &s.scene.needle;
        assert!(shape.wire_at(0.0) < 0.2 * shape.wire_r);
        assert!(shape.wire_at(PI) > 1.05 * shape.wire_r);
        assert!((shape.wire_at(PI / 2.0) - shape.wire_r).abs() < 1e-12);
    }

    #[test]
    fn capsules_are_hit_where_they_are_and_missed_elsewhere() {
        let c = Capsule {
            a: Point::new(0.0, 0.0, 0.0),
            b: Point::new(0.01, 0.0, 0.0),
            r: 0.001,
            material: Material {
                albedo: [0.5; 3],
                specular: 0.0,
                shininess: 1.0,
            },
        };
        let o = Point::new(0.005, 0.0, 0.1);
        let t = hit_capsule(&o, &-Vector::z(), &c).expect("hit");
        assert!((t - 0.099).abs() < 1e-9, "{t}");
        assert!(hit_capsule(&Point::new(0.005, 0.002, 0.1), &-Vector::z(), &c).is_none());
        // The rounded end.
        let t = hit_capsule(&Point::new(-0.0005, 0.0, 0.1), &-Vector::z(), &c).expect("cap");
        assert!((t - (0.1 - (1e-6f64 - 0.25e-6).sqrt())).abs() < 1e-9, "{t}");
    }
}
