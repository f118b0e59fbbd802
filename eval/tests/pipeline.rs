//! The whole pipeline on rendered frames against their truth, typed failures, and RANSAC's
//! robustness to outliers.

use proptest::prelude::*;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use stitch_eval::accuracy;
use stitch_eval::own as evaluate;
use stitch_perception::fit::{RansacParams, plane_basis, ransac_circle, ransac_plane};
use stitch_perception::{NeedlePipeline, PerceptionError};
use stitch_robot::{Needle, Point, Pose, SimClock, Vector};
use stitch_sim::{CameraConfig, MockDvrk, SceneConfig, SceneView, StereoRenderer, Streams};

fn renderer() -> StereoRenderer {
    let world =
        MockDvrk::new(&SceneConfig::default(), Streams::new(1), SimClock::new()).expect("world");
    StereoRenderer::new(CameraConfig::default(), world.phantom_view()).expect("renderer")
}

#[test]
fn rendered_needles_are_found_within_a_millimetre_or_refused() {
    let r = renderer();
    let world =
        MockDvrk::new(&SceneConfig::default(), Streams::new(1), SimClock::new()).expect("world");
    let samples = evaluate::dataset(60, 7, Needle::default(), &world.phantom_view());
    let p = NeedlePipeline::classical(r.calibration().clone(), Needle::default()).expect("p");
    // With the holding jaw known, on 500 frames (`stitch bench perception`): 96 % within
    // 1 mm and 5°, none more than 3 mm off. Sixty frames must show the same picture.
    let held = evaluate::run(&p, &r, &samples, 7, true);
    let a = accuracy(&held);
    assert!(a.within_1mm_5deg >= 0.9, "{a:?}");
    assert_eq!(a.wrong, 0, "{a:?}");
    assert!(a.endpoint_mm[0] < 0.4 && a.normal_deg[0] < 1.0, "{a:?}");
    // From full frames alone, tip and swage are sometimes ambiguous (a typed failure).
    let blind = accuracy(&evaluate::run(&p, &r, &samples, 7, false));
    assert!(blind.within_1mm_5deg >= 0.75, "{blind:?}");
    assert!(blind.wrong <= 2, "{blind:?}");
    // The mock's noise model fitted to the pipeline (`--perception fitted`) still describes
    // it: per-axis σ from the medians (3D: median = 1.54 σ; normal tilt: 1.18 σ), within a
    // factor of two, and the share of failures within 5 points.
    let fitted = stitch_sim::SensingConfig::fitted_to_pipeline();
    let sigma_p = a.center_mm[0] * 1e-3 / 1.54;
    let sigma_r = a.normal_deg[0].to_radians() / 1.18;
    let ratio_p = sigma_p / fitted.elsewhere.sigma_position_m;
    let ratio_r = sigma_r / fitted.elsewhere.sigma_rotation_rad;
    assert!(
        (0.5..2.0).contains(&ratio_p),
        "position σ {sigma_p} vs {fitted:?}"
    );
    assert!(
        (0.5..2.0).contains(&ratio_r),
        "rotation σ {sigma_r} vs {fitted:?}"
    );
    assert!(
        (a.failures - fitted.elsewhere.p_dropout).abs() < 0.05,
        "{a:?}"
    );
    // The same seed, the same results.
    let again = evaluate::run(&p, &r, &samples, 7, true);
    let errs = |v: &[stitch_eval::FrameResult]| -> Vec<_> {
        v.iter().map(|f| (f.error, f.failure.clone())).collect()
    };
    assert_eq!(errs(&held), errs(&again));
}

#[test]
fn frames_without_a_needle_are_typed_failures() {
    let r = renderer();
    let p = NeedlePipeline::classical(r.calibration().clone(), Needle::default()).expect("p");
    let empty = SceneView {
        needle: None,
        thread: vec![],
        tools: vec![],
    };
    let pair = r.render(&empty, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(1));
    let e = p
        .estimate(&pair.left, &pair.right, None, 1)
        .expect_err("nothing");
    assert!(matches!(e, PerceptionError::NoMask { .. }), "{e}");
    // A white (overexposed) pair: everything is unsaturated and bright, which is no needle
    // shape either.
    let mut white = pair.clone();
    white.left.data.fill(255);
    white.right.data.fill(255);
    let e = p
        .estimate(&white.left, &white.right, None, 1)
        .expect_err("white");
    assert!(!matches!(e, PerceptionError::Camera { .. }), "{e}");
    // The wrong size.
    let small = stitch_robot::RgbImage::new(64, 48);
    let e = p.estimate(&small, &small, None, 1).expect_err("size");
    assert!(e.to_string().contains("64×48"), "{e}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// A noisy half circle of the known radius in a cloud where half the points are outliers:
    /// RANSAC still finds its centre and normal.
    #[test]
    fn ransac_survives_half_outliers(
        seed in any::<u64>(),
        cx in -0.05f64..0.05, cy in -0.05f64..0.05, cz in -0.15f64..-0.05,
        nx in -1.0f64..1.0, ny in -1.0f64..1.0, nz in -1.0f64..1.0,
    ) {
        let n = Vector::new(nx, ny, nz);
        prop_assume!(n.norm() > 0.1);
        let n = n.normalize();
        let c = Point::new(cx, cy, cz);
        let r = 0.012;
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let (e1, e2) = plane_basis(&n);
        let mut pts = Vec::new();
        for i in 0..300 {
            let a = std::f64::consts::PI * f64::from(i) / 299.0;
            let noise = Vector::new(rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0), rng.random_range(-1.0..1.0)) * 0.00015;
            pts.push(c + (e1 * a.cos() + e2 * a.sin()) * r + noise);
        }
        for _ in 0..300 {
            pts.push(c + Vector::new(rng.random_range(-0.02..0.02), rng.random_range(-0.02..0.02), rng.random_range(-0.02..0.02)));
        }
        let p = RansacParams::default();
        let (plane, _) = ransac_plane(&pts, &[], &p, &mut rng).expect("plane");
        let (circle, inliers) = ransac_circle(&pts, &[], &plane, r, &p, &mut rng).expect("circle");
        prop_assert!((circle.center - c).norm() < 0.0003, "centre off by {} m", (circle.center - c).norm());
        prop_assert!(circle.normal.cross(&n).norm() < 2f64.to_radians().sin());
        prop_assert!(inliers.len() >= 280, "{} inliers", inliers.len());
    }
}

#[test]
fn a_needle_lodged_in_tissue_is_found_through_its_holes() {
    use stitch_perception::TissueHint;
    use stitch_robot::nalgebra::{Matrix3, Rotation3, Translation3, UnitQuaternion};
    let r = renderer();
    let p = NeedlePipeline::classical(r.calibration().clone(), Needle::default()).expect("p");
    // Through the first wound point's holes (−5, 0, −120) mm and (5, 0, −120) mm, dipping
    // under the tissue, the tip 50° past the exit.
    let (entry, exit) = (
        Point::new(-0.005, 0.0, -0.12),
        Point::new(0.005, 0.0, -0.12),
    );
    let center = Point::new(
        0.0,
        0.0,
        -0.12 + (0.012f64.powi(2) - 0.005f64.powi(2)).sqrt(),
    );
    let tip_angle = (-65.38f64 + 50.0).to_radians();
    let x = Vector::new(tip_angle.cos(), 0.0, tip_angle.sin());
    let z = Vector::y();
    let rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, z.cross(&x), z]));
    let truth = Pose::from_parts(
        Translation3::from(center.coords),
        UnitQuaternion::from_rotation_matrix(&rot),
    );
    let needle = Needle::default();
    let swage = truth * needle.swage();
    let scene = SceneView {
        needle: Some((needle, truth)),
        thread: vec![vec![Point::new(-0.02, 0.0, -0.116), swage]],
        tools: vec![],
    };
    let pair = r.render(&scene, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(3));
    // The holes as the plan knows them, a few tenths of a millimetre off.
    let holes = TissueHint {
        entry: entry + Vector::new(0.0002, 0.0, 0.0),
        exit: exit + Vector::new(0.0, 0.0003, 0.0),
    };
    let out = p
        .estimate_in_tissue(&pair.left, &pair.right, &holes, 1)
        .expect("found");
    let e = stitch_perception::PoseError::between(&needle, &out.pose, &truth);
    assert!(e.tip_m < 0.001 && e.center_m < 0.001, "{e:?}");
    // A needle seen clearly, but 1 cm from the holes it is said to be in, is not the needle
    // in them: refused, not placed there.
    let beside = TissueHint {
        entry: entry + Vector::new(0.0, 0.01, 0.0),
        exit: exit + Vector::new(0.0, 0.01, 0.0),
    };
    let err = p
        .estimate_in_tissue(&pair.left, &pair.right, &beside, 1)
        .expect_err("not in those holes");
    assert!(matches!(err, PerceptionError::BadFit { .. }), "{err}");
    // Holes a needle cannot pass through both of are refused.
    let far = TissueHint {
        entry: Point::new(-0.02, 0.0, -0.12),
        exit: Point::new(0.02, 0.0, -0.12),
    };
    let err = p
        .estimate_in_tissue(&pair.left, &pair.right, &far, 1)
        .expect_err("too far apart");
    assert!(err.to_string().contains("cannot pass"), "{err}");
}

/// A mission's first throw (seed 1, `stitch_thread.rhai`, the pipeline in the loop), right
/// after the insertion: the right jaw, just opened off the needle, hides its swage half in the
/// right view, where the left view still sees it. Those pixels get disparities matched to
/// anything (about 300 points off the circle, against 110 on it past the exit); they once made
/// the fit refuse ("110 of 413 points on the best circle near the holes") in every trial, and
/// are now left out: a point of the needle is needle in both views.
#[test]
fn a_needle_in_tissue_that_a_jaw_hides_from_one_view_is_found_through_its_holes() {
    use stitch_perception::TissueHint;
    use stitch_robot::nalgebra::{Quaternion, Translation3, UnitQuaternion};
    use stitch_sim::ToolView;
    let r = renderer();
    let p = NeedlePipeline::classical(r.calibration().clone(), Needle::default()).expect("p");
    let pose = |t: [f64; 3], q: [f64; 4]| {
        Pose::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_quaternion(Quaternion::new(q[3], q[0], q[1], q[2])),
        )
    };
    // The journal's truth and the right PSM's measured pose (quaternions x, y, z, w).
    let truth = pose(
        [0.001_994_3, -0.000_015_6, -0.107_992_9],
        [0.653_906_9, -0.269_045_5, -0.270_180_9, -0.653_469_6],
    );
    let jaw = pose(
        [-0.009_606_1, -0.000_035_7, -0.084_922_0],
        [0.560_718_3, -0.430_830_9, 0.431_777_2, 0.559_953_7],
    );
    let needle = Needle::default();
    let swage = truth * needle.swage();
    let scene = SceneView {
        needle: Some((needle, truth)),
        thread: vec![vec![
            Point::new(0.06, 0.03, -0.125),
            Point::new(0.01, 0.01, -0.12),
            swage,
        ]],
        tools: vec![ToolView {
            pose: jaw,
            jaw_rad: 0.5,
        }],
    };
    let pair = r.render(&scene, &Pose::identity(), &mut ChaCha8Rng::seed_from_u64(3));
    let holes = TissueHint {
        entry: Point::new(-0.005, 0.0, -0.12),
        exit: Point::new(0.005, 0.0, -0.12),
    };
    let out = p
        .estimate_in_tissue(&pair.left, &pair.right, &holes, 1)
        .expect("found");
    // The tip, which the extraction grasps, within 1.5 mm; the pose within 4 mm and 5° (the
    // arc seen past the exit is short, about 75°).
    let e = stitch_perception::PoseError::between(&needle, &out.pose, &truth);
    assert!(e.tip_m < 0.0015, "{e:?}");
    assert!(
        e.center_m < 0.004 && e.normal_rad < 5f64.to_radians(),
        "{e:?}"
    );
    // The points fitted are the wire both views see: most of them on the circle.
    let d = &out.diagnostics;
    assert!(d.circle_inliers * 2 >= d.cloud_points, "{d:?}");
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Whatever the images hold — noise, grey blobs that look like needle, thread colours —
    /// the pipeline answers with a pose or a typed failure, never a panic.
    #[test]
    fn arbitrary_images_never_panic(
        seed in any::<u64>(),
        blobs in 0usize..40,
        grey in any::<bool>(),
    ) {
        let calib = stitch_robot::StereoCalibration {
            fx: 200.0,
            fy: 200.0,
            cx: 80.0,
            cy: 60.0,
            baseline_m: 0.04,
            width: 160,
            height: 120,
            camera_to_robot: Pose::identity(),
        };
        let p = NeedlePipeline::classical(calib, Needle::default()).expect("p");
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let mut image = || {
            let mut img = stitch_robot::RgbImage::new(160, 120);
            for v in img.data.iter_mut() {
                *v = rng.random();
            }
            for _ in 0..blobs {
                let (x, y) = (rng.random_range(0..160usize), rng.random_range(0..120usize));
                let (w, h) = (rng.random_range(1..40usize), rng.random_range(1..6usize));
                let c: [u8; 3] = if grey { [200, 200, 200] } else { [120, 60, 170] };
                for yy in y..(y + h).min(120) {
                    for xx in x..(x + w).min(160) {
                        let i = (yy * 160 + xx) * 3;
                        img.data[i..i + 3].copy_from_slice(&c);
                    }
                }
            }
            img
        };
        let (l, r) = (image(), image());
        let _ = p.estimate(&l, &r, None, seed);
        let hint = stitch_perception::JawHint {
            jaw: Point::new(0.0, 0.0, 0.2),
            end: stitch_perception::NeedleEnd::Swage,
        };
        let _ = p.estimate(&l, &r, Some(&hint), seed);
        let holes = stitch_perception::TissueHint {
            entry: Point::new(-0.005, 0.0, 0.2),
            exit: Point::new(0.005, 0.0, 0.2),
        };
        let _ = p.estimate_in_tissue(&l, &r, &holes, seed);
        let _ = p.disparity(&l, &r, None);
    }
}
