//! Where the needle's ends go, on analytic point clouds (no images): the half-circle rule
//! places both ends π apart on the fitted circle whatever is missing of the thin tip, and
//! the tip is told from the swage by the thread alone.

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use std::f64::consts::PI;
use stitch_perception::fit::{self, RansacParams, arc_extent, plane_basis};
use stitch_perception::pipeline::{Anchor, PipelineParams, half_circle_ends, tip_is_low_end};
use stitch_robot::{Point, Vector};

const R: f64 = 0.012;

/// A needle's true frame: centre, in-plane axes `x` (towards the tip) and `y` (the tip runs
/// to the swage through +y), so the tip is at angle 0 and the swage at π.
struct Truth {
    center: Point,
    x: Vector,
    y: Vector,
}

impl Truth {
    fn at(&self, a: f64) -> Point {
        self.center + (self.x * a.cos() + self.y * a.sin()) * R
    }
}

fn random_truth(rng: &mut ChaCha8Rng) -> Truth {
    let normal = Vector::new(
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
        rng.random_range(-1.0..1.0),
    )
    .try_normalize(1e-6)
    .unwrap_or_else(Vector::z);
    let (e1, e2) = plane_basis(&normal);
    let spin = rng.random_range(0.0..2.0 * PI);
    let x = e1 * spin.cos() + e2 * spin.sin();
    Truth {
        center: Point::new(
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.03..0.03),
            rng.random_range(-0.1..-0.05),
        ),
        x,
        y: normal.cross(&x),
    }
}

/// Points along the wire from the swage (π) to `lost_m` short of the tip (0), with
/// `noise_m` of jitter (Gaussian-ish) in every direction.
fn cloud(t: &Truth, lost_m: f64, noise_m: f64, rng: &mut ChaCha8Rng) -> Vec<Point> {
    let first = lost_m / R;
    (0..600)
        .map(|i| {
            let a = first + (PI - first) * f64::from(i) / 599.0;
            let jitter = Vector::new(
                rng.random_range(-1.0..1.0) + rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0) + rng.random_range(-1.0..1.0),
                rng.random_range(-1.0..1.0) + rng.random_range(-1.0..1.0),
            ) * (noise_m / 2.0);
            t.at(a) + jitter
        })
        .collect()
}

/// Fit the cloud as the pipeline does and place the ends with `anchor` (the tip's side
/// given: which observed end is nearer the true tip — the cue's answer, tested apart).
/// Returns (tip, swage, the observed tip end).
fn place(points: &[Point], t: &Truth, anchor: Anchor, seed: u64) -> (Point, Point, Point) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    let params = RansacParams::default();
    let (plane, on) = fit::ransac_plane(points, &[], &params, &mut rng).expect("plane");
    let on: Vec<Point> = on.iter().map(|&i| points[i]).collect();
    let (circle, inl) = fit::ransac_circle(&on, &[], &plane, R, &params, &mut rng).expect("circle");
    let pts: Vec<Point> = inl.iter().map(|&i| on[i]).collect();
    let arc = arc_extent(&pts, &circle).expect("arc");
    let (e1, e2) = plane_basis(&circle.normal);
    let at = |a: f64| circle.center + (e1 * a.cos() + e2 * a.sin()) * R;
    let (lo, hi) = (at(arc.start), at(arc.start + arc.extent));
    let tip_is_lo = (lo - t.at(0.0)).norm() < (hi - t.at(0.0)).norm();
    let swage_cap = 0.0; // the analytic wire's points end at the swage's centre line
    let (tip_a, swage_a) = half_circle_ends(arc.start, arc.extent, tip_is_lo, anchor, swage_cap);
    (at(tip_a), at(swage_a), if tip_is_lo { lo } else { hi })
}

#[test]
fn the_ends_lie_a_half_circle_apart_whatever_is_missing_of_the_tip() {
    let mut rng = ChaCha8Rng::seed_from_u64(7);
    for case in 0..40u32 {
        let t = random_truth(&mut rng);
        // 0.5 to 4 mm of the tip missing (a taper too thin for the mask), 0.1 mm noise.
        let lost = 0.0005 + 0.0035 * f64::from(case) / 39.0;
        let points = cloud(&t, lost, 0.0001, &mut rng);
        let (tip, swage, seen_tip) = place(&points, &t, Anchor::Swage, u64::from(case));
        let (tip_err, swage_err) = ((tip - t.at(0.0)).norm(), (swage - t.at(PI)).norm());
        assert!(
            tip_err < 0.0003 && swage_err < 0.0003,
            "case {case}, {:.1} mm missing: tip {:.2} mm off, swage {:.2} mm off",
            lost * 1e3,
            tip_err * 1e3,
            swage_err * 1e3
        );
        // What the image shows of the tip is where the rule did not put it.
        assert!(
            (seen_tip - t.at(0.0)).norm() > 0.7 * lost,
            "case {case}: the observed end is the tip itself"
        );
    }
}

#[test]
fn a_tip_anchor_goes_past_the_observed_end_by_what_was_lost() {
    let mut rng = ChaCha8Rng::seed_from_u64(11);
    for case in 0..20u32 {
        let t = random_truth(&mut rng);
        let lost = 0.001 + 0.002 * f64::from(case) / 19.0;
        // The swage's side is hidden (a jaw holds it): its last 5 mm are gone too.
        let points: Vec<Point> = cloud(&t, lost, 0.0001, &mut rng)
            .into_iter()
            .filter(|p| (p - t.at(PI)).norm() > 0.005)
            .collect();
        let (tip, swage, _) = place(
            &points,
            &t,
            Anchor::Tip { lost_rad: lost / R },
            u64::from(case),
        );
        let (tip_err, swage_err) = ((tip - t.at(0.0)).norm(), (swage - t.at(PI)).norm());
        assert!(
            tip_err < 0.0003 && swage_err < 0.0003,
            "case {case}: tip {:.2} mm off, swage {:.2} mm off",
            tip_err * 1e3,
            swage_err * 1e3
        );
        // Anchored on the observed tip with nothing added, both ends are off by the loss.
        let (bare, _, _) = place(&points, &t, Anchor::Tip { lost_rad: 0.0 }, u64::from(case));
        assert!((bare - t.at(0.0)).norm() > 0.7 * lost);
    }
}

#[test]
fn the_thread_alone_tells_the_tip_from_the_swage() {
    let p = PipelineParams::default();
    // No taper measured at either end, no jaw: the end with the thread is the swage.
    assert_eq!(tip_is_low_end([0, 40], [None, None], 0, &p), Some(true));
    assert_eq!(tip_is_low_end([40, 0], [None, None], 0, &p), Some(false));
    // Both wire ends measured alike (no taper to see): the thread still decides.
    assert_eq!(
        tip_is_low_end([3, 60], [Some(1.0), Some(1.0)], 0, &p),
        Some(true)
    );
    // Thread at both ends alike, or none: nothing tells.
    assert_eq!(tip_is_low_end([30, 30], [None, None], 0, &p), None);
    assert_eq!(tip_is_low_end([0, 0], [Some(1.0), Some(1.0)], 0, &p), None);
    // The thread and the taper agreeing; and contradicting (a typed failure, not a guess).
    assert_eq!(
        tip_is_low_end([0, 40], [Some(0.5), None], 0, &p),
        Some(true)
    );
    assert_eq!(tip_is_low_end([0, 40], [None, Some(0.5)], 0, &p), None);
    // A known jaw overrides both.
    assert_eq!(tip_is_low_end([0, 40], [None, None], -8, &p), Some(false));
}
