//! The own evaluation set: frames from the mock's renderer (`stitch_sim::StereoRenderer`),
//! the renderer the pipeline was tuned on.
//!
//! The set: needle poses spread over the workspace, held in the right jaw near the swage or
//! in the left jaw near the tip (as after a handover), most with the jaw from above (normal
//! within 40° of straight down), some presented towards the camera (as at the correction
//! point); the thread runs from the swage to the wound, and in a share of frames loops over
//! the needle. Everything from one seed.

use crate::FrameResult;
use nalgebra::{Translation3, Unit, UnitQuaternion};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use std::time::Instant;
use stitch_perception::pipeline::{JawHint, NeedleEnd, NeedlePipeline};
use stitch_robot::{Needle, Point, Pose, Vector};
use stitch_sim::{PhantomView, SceneView, StereoRenderer, ToolView, grasp_in_needle_frame};

/// One evaluation frame's scene.
#[derive(Clone, Debug, PartialEq)]
pub struct Sample {
    /// What the camera sees.
    pub scene: SceneView,
    /// The true needle pose.
    pub truth: Pose,
    /// Which jaw holds it: "right" or "left".
    pub jaw: &'static str,
    /// Whether the thread was laid across the needle.
    pub thread_over: bool,
}

/// The workspace the set spreads over, robot frame, m (the mock's default workspace around
/// the wound and both homes).
pub const WORKSPACE: [[f64; 2]; 3] = [[-0.045, 0.045], [-0.03, 0.05], [-0.105, -0.075]];

/// `n` samples from `seed`, for the default phantom `phantom`.
pub fn dataset(n: usize, seed: u64, needle: Needle, phantom: &PhantomView) -> Vec<Sample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let to_camera = Vector::new(0.0, 0.125, 0.12).normalize();
    (0..n)
        .map(|_| {
            let center = Point::new(
                rng.random_range(WORKSPACE[0][0]..WORKSPACE[0][1]),
                rng.random_range(WORKSPACE[1][0]..WORKSPACE[1][1]),
                rng.random_range(WORKSPACE[2][0]..WORKSPACE[2][1]),
            );
            let presented = rng.random_bool(0.3);
            // Presented: the plane faces the camera, the jaw holding it from behind (a
            // circle looks the same from both sides; the tool's shaft runs along the normal).
            let (axis, cone) = if presented {
                (-to_camera, 30f64.to_radians())
            } else {
                (-Vector::z(), 40f64.to_radians())
            };
            let normal = random_in_cone(&mut rng, &axis, cone);
            let spin = rng.random_range(0.0..std::f64::consts::TAU);
            let align =
                UnitQuaternion::rotation_between(&Vector::z(), &normal).unwrap_or_else(|| {
                    UnitQuaternion::from_axis_angle(&Vector::x_axis(), std::f64::consts::PI)
                });
            let rotation = align * UnitQuaternion::from_axis_angle(&Vector::z_axis(), spin);
            let truth = Pose::from_parts(Translation3::from(center.coords), rotation);
            let right = rng.random_bool(0.5);
            let angle = if right {
                rng.random_range(140f64..160.0).to_radians()
            } else {
                rng.random_range(15f64..35.0).to_radians()
            };
            let tool = truth * grasp_in_needle_frame(&needle, angle);
            let swage = truth * needle.swage();
            let anchor = phantom.wound_start;
            let thread_over = rng.random_bool(0.3);
            let mid = if thread_over {
                // Loop over the needle: through a point over its arc, nearer the camera.
                let a = rng.random_range(0.3..2.8);
                truth * needle.point_at(a) + to_camera * 0.004
            } else {
                let m = Point::from((swage.coords + anchor.coords) / 2.0);
                Point::new(m.x, m.y, phantom.surface_z.max(m.z - 0.02))
            };
            Sample {
                scene: SceneView {
                    needle: Some((needle, truth)),
                    thread: vec![vec![anchor, mid, swage]],
                    tools: vec![ToolView {
                        pose: tool,
                        jaw_rad: 0.0,
                    }],
                },
                truth,
                jaw: if right { "right" } else { "left" },
                thread_over,
            }
        })
        .collect()
}

fn random_in_cone(rng: &mut ChaCha8Rng, axis: &Vector, cone: f64) -> Vector {
    let cos_max = cone.cos();
    let c = rng.random_range(cos_max..1.0);
    let s = (1.0 - c * c).sqrt();
    let phi = rng.random_range(0.0..std::f64::consts::TAU);
    let local = Vector::new(s * phi.cos(), s * phi.sin(), c);
    let q = UnitQuaternion::rotation_between(&Vector::z(), axis).unwrap_or_else(|| {
        UnitQuaternion::from_axis_angle(&Unit::new_normalize(Vector::x()), std::f64::consts::PI)
    });
    q * local
}

/// The jaw hint a sample's robot would give: where its holding jaw is and which end it holds
/// nearer (the right jaw grasps near the swage, the left near the tip).
pub fn jaw_hint(s: &Sample) -> JawHint {
    let tool = s.scene.tools[0].pose;
    JawHint {
        jaw: Point::from(tool.translation.vector),
        end: if s.jaw == "right" {
            NeedleEnd::Swage
        } else {
            NeedleEnd::Tip
        },
    }
}

/// Render and estimate every sample, blind (full frames) or with each sample's jaw hint;
/// noise from `seed`.
pub fn run(
    pipeline: &NeedlePipeline,
    renderer: &StereoRenderer,
    samples: &[Sample],
    seed: u64,
    hinted: bool,
) -> Vec<FrameResult> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    samples
        .iter()
        .enumerate()
        .map(|(i, s)| {
            let t0 = Instant::now();
            let pair = renderer.render(&s.scene, &Pose::identity(), &mut rng);
            let t1 = Instant::now();
            let hint = hinted.then(|| jaw_hint(s));
            let out = pipeline.estimate(&pair.left, &pair.right, hint.as_ref(), seed ^ i as u64);
            let total = t1.elapsed();
            FrameResult::new(
                out.map(|o| (o, pipeline.needle)),
                &s.truth,
                total,
                t1 - t0,
                s.jaw,
                s.thread_over,
            )
        })
        .collect()
}
