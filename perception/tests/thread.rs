//! The thread tracer on analytic curves: a known 3D curve drawn into a rectified pair (a
//! violet line about 2.4 px wide, anti-aliased, on pink, with noise), traced and compared.

use stitch_perception::thread::{ThreadHint, ThreadParams, trace};
use stitch_perception::{ColorSegmenter, PerceptionError};
use stitch_robot::{Point, Pose, RgbImage, StereoCalibration, distance_to_polyline};

const W: u32 = 640;
const H: u32 = 480;

fn calib() -> StereoCalibration {
    StereoCalibration {
        fx: 1000.0,
        fy: 1000.0,
        cx: 320.0,
        cy: 240.0,
        baseline_m: 0.04,
        width: W,
        height: H,
        camera_to_robot: Pose::identity(),
    }
}

/// A curve from `a` to `b` in the camera frame, bowed sideways and in depth, `n` points.
fn curve(a: Point, b: Point, bow_x: f64, bow_z: f64, n: usize) -> Vec<Point> {
    (0..=n)
        .map(|k| {
            let s = k as f64 / n as f64;
            let p = a + (b - a) * s;
            Point::new(
                p.x + bow_x * (2.0 * std::f64::consts::PI * s).sin(),
                p.y,
                p.z + bow_z * (std::f64::consts::PI * s).sin(),
            )
        })
        .collect()
}

/// Draw the curve into one view (`shift` metres of baseline to the right), with `cover`, a
/// grey box over part of the image, if any.
fn draw(
    c: &StereoCalibration,
    line: &[Point],
    shift: f64,
    cover: Option<[f64; 4]>,
    seed: u32,
) -> RgbImage {
    let mut img = RgbImage::new(c.width, c.height);
    let px: Vec<[f64; 2]> = line
        .iter()
        .map(|p| [c.fx * (p.x - shift) / p.z + c.cx, c.fy * p.y / p.z + c.cy])
        .collect();
    let mut state = seed.wrapping_mul(2_654_435_761).max(1);
    let mut noise = || {
        state ^= state << 13;
        state ^= state >> 17;
        state ^= state << 5;
        f64::from(state % 7) - 3.0
    };
    for y in 0..c.height {
        for x in 0..c.width {
            let q = [f64::from(x) + 0.5, f64::from(y) + 0.5];
            let mut d = f64::INFINITY;
            for w in px.windows(2) {
                let (a, b) = (w[0], w[1]);
                let ab = [b[0] - a[0], b[1] - a[1]];
                let l2 = ab[0] * ab[0] + ab[1] * ab[1];
                let t = if l2 > 0.0 {
                    (((q[0] - a[0]) * ab[0] + (q[1] - a[1]) * ab[1]) / l2).clamp(0.0, 1.0)
                } else {
                    0.0
                };
                d = d.min((q[0] - a[0] - t * ab[0]).hypot(q[1] - a[1] - t * ab[1]));
            }
            let alpha = (1.2 + 0.5 - d).clamp(0.0, 1.0);
            let mut rgb = [
                200.0 * (1.0 - alpha) + 110.0 * alpha,
                130.0 * (1.0 - alpha) + 60.0 * alpha,
                140.0 * (1.0 - alpha) + 170.0 * alpha,
            ];
            if let Some([x0, y0, x1, y1]) = cover
                && (x0..x1).contains(&q[0])
                && (y0..y1).contains(&q[1])
            {
                rgb = [60.0, 60.0, 66.0];
            }
            let i = ((y * c.width + x) * 3) as usize;
            for (k, c) in rgb.iter().enumerate() {
                img.data[i + k] = (c + noise()).clamp(0.0, 255.0) as u8;
            }
        }
    }
    img
}

/// The tracer with its defaults and the colour segmenter.
fn traced(
    c: &StereoCalibration,
    left: &RgbImage,
    right: &RgbImage,
    hint: &ThreadHint,
) -> Result<stitch_perception::ThreadTrace, PerceptionError> {
    trace(
        &ThreadParams::default(),
        &ColorSegmenter::default(),
        c,
        left,
        right,
        hint,
    )
}

fn length(line: &[Point]) -> f64 {
    line.windows(2).map(|w| (w[1] - w[0]).norm()).sum()
}

#[test]
fn a_bowed_curve_is_traced_to_a_fraction_of_a_millimetre_and_its_length_to_a_few_percent() {
    let c = calib();
    let cases = [
        (
            Point::new(-0.03, -0.02, 0.16),
            Point::new(0.025, 0.03, 0.13),
            0.01,
            0.015,
        ),
        (
            Point::new(0.03, -0.03, 0.14),
            Point::new(-0.02, 0.025, 0.17),
            -0.006,
            -0.01,
        ),
        (
            Point::new(-0.01, 0.035, 0.15),
            Point::new(0.01, -0.03, 0.15),
            0.012,
            0.02,
        ),
    ];
    for (i, (a, b, bx, bz)) in cases.into_iter().enumerate() {
        let truth = curve(a, b, bx, bz, 300);
        let left = draw(&c, &truth, 0.0, None, 1 + i as u32);
        let right = draw(&c, &truth, c.baseline_m, None, 100 + i as u32);
        let hint = ThreadHint {
            start: Some(a),
            swage: b,
            length_m: None,
        };
        let t = traced(&c, &left, &right, &hint).unwrap_or_else(|e| panic!("case {i}: {e}"));
        let mut errors: Vec<f64> = t
            .points
            .iter()
            .map(|p| distance_to_polyline(p, &truth))
            .collect();
        errors.sort_by(f64::total_cmp);
        let median = errors[errors.len() / 2];
        let worst = errors[errors.len() - 1];
        let len_err = (t.length_m - length(&truth)).abs() / length(&truth);
        assert!(median < 0.0005, "case {i}: median error {median} m");
        assert!(worst < 0.003, "case {i}: worst error {worst} m");
        assert!(
            len_err < 0.05,
            "case {i}: length {} against {}",
            t.length_m,
            length(&truth)
        );
        assert!(t.seen_share > 0.95, "case {i}: seen {}", t.seen_share);
        assert!(t.hidden.is_empty(), "case {i}: hidden {:?}", t.hidden);
        // Ends where the hint put them, in order.
        assert!(
            (t.points[0] - a).norm() < 0.002,
            "case {i}: first end {:?}",
            t.points[0]
        );
        assert!(
            (t.points[t.points.len() - 1] - b).norm() < 0.002,
            "case {i}"
        );
        // The stated uncertainty covers most of the truth.
        let inside = truth
            .iter()
            .filter(|p| t.nearest(p).is_some_and(|(_, d, s)| d <= 2.0 * s))
            .count();
        assert!(
            inside as f64 > 0.8 * truth.len() as f64,
            "case {i}: {inside} of {}",
            truth.len()
        );
    }
}

#[test]
fn a_stretch_behind_a_box_is_reported_hidden_and_bridged() {
    let c = calib();
    let (a, b) = (
        Point::new(-0.03, -0.02, 0.16),
        Point::new(0.025, 0.03, 0.13),
    );
    let truth = curve(a, b, 0.0, 0.01, 300);
    // A box over the middle of the curve in both views.
    let mid = truth[150];
    let u = c.fx * mid.x / mid.z + c.cx;
    let v = c.fy * mid.y / mid.z + c.cy;
    let cover = |shift: f64| {
        Some([
            u - 30.0 - c.fx * shift / mid.z,
            v - 30.0,
            u + 30.0 - c.fx * shift / mid.z,
            v + 30.0,
        ])
    };
    let left = draw(&c, &truth, 0.0, cover(0.0), 3);
    let right = draw(&c, &truth, c.baseline_m, cover(c.baseline_m), 4);
    let hint = ThreadHint {
        start: Some(a),
        swage: b,
        length_m: None,
    };
    let t = traced(&c, &left, &right, &hint).expect("traced past the box");
    assert_eq!(t.hidden.len(), 1, "{:?}", t.hidden);
    let [from, to] = t.hidden[0];
    let middle = t.length_m / 2.0;
    assert!(
        from < middle && middle < to,
        "hidden {from}..{to} of {}",
        t.length_m
    );
    // Less sure behind the box than where it is seen.
    let at = |s: f64| {
        let mut acc = 0.0;
        for (i, w) in t.points.windows(2).enumerate() {
            acc += (w[1] - w[0]).norm();
            if acc >= s {
                return t.sigma_m[i];
            }
        }
        t.sigma_m[t.sigma_m.len() - 1]
    };
    // Against the seen stretch beyond the box. (Before the box the thread falls outside the
    // right image, 250 px of disparity from x = 132 px: its depth rests on the start hint
    // and the spline, and its band is wide for that reason.)
    let beyond = to + 0.5 * (t.length_m - to);
    assert!(
        at(middle) > 2.0 * at(beyond),
        "{} vs {}",
        at(middle),
        at(beyond)
    );
}

#[test]
fn a_thread_mostly_hidden_or_missing_fails_typed() {
    let c = calib();
    let (a, b) = (
        Point::new(-0.03, -0.02, 0.16),
        Point::new(0.025, 0.03, 0.13),
    );
    let truth = curve(a, b, 0.0, 0.01, 300);
    let hint = ThreadHint {
        start: Some(a),
        swage: b,
        length_m: None,
    };
    // Most of it behind a wide box.
    let cover = |shift: f64| {
        Some([
            100.0 - 1000.0 * shift / 0.145,
            80.0,
            560.0 - 1000.0 * shift / 0.145,
            380.0,
        ])
    };
    let left = draw(&c, &truth, 0.0, cover(0.0), 5);
    let right = draw(&c, &truth, c.baseline_m, cover(c.baseline_m), 6);
    match traced(&c, &left, &right, &hint) {
        Err(PerceptionError::ThreadHidden { seen_share }) => assert!(seen_share < 0.6),
        Err(PerceptionError::NoThread { .. }) => {}
        other => panic!("expected a hidden thread, got {other:?}"),
    }
    // No thread at all.
    let empty = draw(
        &c,
        &[Point::new(5.0, 5.0, 1.0), Point::new(5.1, 5.0, 1.0)],
        0.0,
        None,
        7,
    );
    match traced(&c, &empty, &empty, &hint) {
        Err(PerceptionError::NoThread { view }) => assert_eq!(view, "left"),
        other => panic!("expected no thread, got {other:?}"),
    }
    // Images of the wrong size are a configuration error, not a missing thread.
    let small = RgbImage::new(32, 32);
    assert!(matches!(
        traced(&c, &small, &small, &hint),
        Err(PerceptionError::Config { .. })
    ));
}

/// The pair traced from the truth's first point to its last; its length within `tolerance`
/// (a share) of the truth's, its points' median distance from it under 0.5 mm.
fn traced_near(
    c: &StereoCalibration,
    left: &RgbImage,
    right: &RgbImage,
    truth: &[Point],
    tolerance: f64,
) -> stitch_perception::ThreadTrace {
    let hint = ThreadHint {
        start: Some(truth[0]),
        swage: truth[truth.len() - 1],
        length_m: None,
    };
    let t = traced(c, left, right, &hint).expect("traced");
    let mut errors: Vec<f64> = t
        .points
        .iter()
        .map(|p| distance_to_polyline(p, truth))
        .collect();
    errors.sort_by(f64::total_cmp);
    let median = errors[errors.len() / 2];
    let len_err = (t.length_m - length(truth)) / length(truth);
    assert!(
        len_err.abs() < tolerance,
        "length {} against {} ({:+.0} %)",
        t.length_m,
        length(truth),
        100.0 * len_err
    );
    assert!(median < 0.0005, "median error {median} m");
    t
}

/// Straight stretches through `corners`, `n` points each.
fn polyline(corners: &[Point], n: usize) -> Vec<Point> {
    let mut out = vec![corners[0]];
    for w in corners.windows(2) {
        out.extend((1..=n).map(|k| w[0] + (w[1] - w[0]) * (k as f64 / n as f64)));
    }
    out
}

#[test]
fn a_hairpin_of_170_degrees_is_walked_round_not_cut_short() {
    let c = calib();
    // Down 30 mm and back up at 10° to itself (the strands touch for the first 20 px from
    // the bend and are 3 px apart 18 px from it), across, and down to a swage 6 mm from the
    // bend: a cheapest path from the bend would bridge those 6 mm and leave out 60 mm.
    // (Steep strands: rows cross them, so the views match.)
    let a = Point::new(-0.005, -0.015, 0.15);
    let apex = Point::new(-0.005, 0.015, 0.15);
    let back = Point::new(0.0003, -0.015, 0.15);
    let across = Point::new(0.012, -0.015, 0.15);
    let b = Point::new(0.0, 0.019, 0.15);
    let truth = polyline(&[a, apex, back, across, b], 200);
    let left = draw(&c, &truth, 0.0, None, 11);
    let right = draw(&c, &truth, c.baseline_m, None, 12);
    traced_near(&c, &left, &right, &truth, 0.05);
}

#[test]
fn a_loop_whose_start_is_hidden_is_walked_from_the_swage_not_cut_across() {
    let c = calib();
    // A trochoid with one loop: the thread crosses itself, and a cheapest path between the
    // ends would cut across the crossing. The first few millimetres from the tissue are
    // behind a box, so no walk can set out from the start.
    let (len, r) = (0.05, 0.012);
    let truth: Vec<Point> = (0..=600)
        .map(|k| {
            let s = f64::from(k) / 600.0;
            let phase = std::f64::consts::TAU * s;
            Point::new(
                -0.025 + len * s + r * phase.sin(),
                0.01 - r * (1.0 - phase.cos()),
                0.15 + 0.005 * (std::f64::consts::PI * s).sin(),
            )
        })
        .collect();
    let a = truth[0];
    let u = c.fx * a.x / a.z + c.cx;
    let v = c.fy * a.y / a.z + c.cy;
    let cover = |shift: f64| {
        let du = c.fx * shift / a.z;
        Some([u - 20.0 - du, v - 14.0, u + 14.0 - du, v + 14.0])
    };
    let left = draw(&c, &truth, 0.0, cover(0.0), 13);
    let right = draw(&c, &truth, c.baseline_m, cover(c.baseline_m), 14);
    let t = traced_near(&c, &left, &right, &truth, 0.08);
    // The hidden stretch is the first one, at the start.
    assert!(
        t.hidden.first().is_some_and(|h| h[0] < 0.001),
        "hidden {:?}",
        t.hidden
    );
}

#[test]
fn a_loop_cut_off_by_a_hidden_neck_is_spliced_in_when_a_length_prior_says_it_is_missing() {
    let c = calib();
    // From an exit under a box, down and round a U below it, back up under the box, and on
    // up to the swage: the view shows the U apart from the rest (its neck is under the
    // box), so the path between the ends leaves it out.
    let (z, u0, u1) = (0.15, -0.004, 0.004);
    let truth = polyline(
        &[
            Point::new(-0.003, 0.010, z),
            Point::new(u0, 0.035, z),
            Point::new(u1, 0.035, z),
            Point::new(0.003, 0.010, z),
            Point::new(0.010, -0.020, z),
        ],
        120,
    );
    let px = |x: f64, y: f64| [c.fx * x / z + c.cx, c.fy * y / z + c.cy];
    let cover = |shift: f64| {
        let du = c.fx * shift / z;
        let ([x0, y0], [x1, y1]) = (px(-0.008, 0.006), px(0.008, 0.014));
        Some([x0 - du, y0, x1 - du, y1])
    };
    let left = draw(&c, &truth, 0.0, cover(0.0), 21);
    let right = draw(&c, &truth, c.baseline_m, cover(c.baseline_m), 22);
    let true_len = length(&truth);
    let hint = |length_m| ThreadHint {
        start: Some(truth[0]),
        swage: truth[truth.len() - 1],
        length_m,
    };
    let bottom = Point::new(0.0, 0.035, z);
    let near_bottom = |t: &stitch_perception::ThreadTrace| {
        t.points
            .iter()
            .map(|p| (p - bottom).norm())
            .fold(f64::INFINITY, f64::min)
    };
    // Without a prior: the visible path, far short, nowhere near the U.
    let t = traced(&c, &left, &right, &hint(None)).expect("traced");
    assert!(t.length_m < 0.7 * true_len, "{} of {true_len}", t.length_m);
    assert!(near_bottom(&t) > 0.01, "{}", near_bottom(&t));
    // With a prior (the truth's length, or 10 % over it): the U spliced in, through the
    // hidden neck, and the length within 10 %.
    for prior in [true_len, 1.1 * true_len] {
        let t = traced(&c, &left, &right, &hint(Some(prior))).expect("traced");
        let err = (t.length_m - true_len) / true_len;
        assert!(
            err.abs() < 0.1,
            "prior {prior}: {} of {true_len}",
            t.length_m
        );
        assert!(near_bottom(&t) < 0.001, "{}", near_bottom(&t));
        assert!(
            t.hidden.iter().any(|h| h[1] - h[0] > 0.003),
            "hidden {:?}",
            t.hidden
        );
    }
    // A prior the visible path already meets leaves it as it was.
    let short = traced(&c, &left, &right, &hint(None))
        .expect("traced")
        .length_m;
    let t = traced(&c, &left, &right, &hint(Some(short))).expect("traced");
    assert!(near_bottom(&t) > 0.01, "{}", near_bottom(&t));
}
