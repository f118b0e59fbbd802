//! The thread tracer's two evaluation sets and its accuracy against their truth.
//!
//! - **Own**: the mock's renderer drawing the mock's own thread (the chain of links, settled
//!   by its physics from a stitch's exit to a held needle's swage, round the holding tool and
//!   in a share of frames the other tool's open jaw above it), the set the tracer was tuned
//!   on.
//! - **Independent**: the independent ray tracer's pairs (`independent.rs`), whose thread is
//!   a smooth curve from the swage to where it enters the tissue, drawn in other colours and
//!   widths under other cameras and light; never used to tune.
//!
//! The tracer is given what a plan would give it: the exit point and the swage (here the
//! true ones; in a mission the swage comes from the needle estimate).

use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use serde::Serialize;
use std::time::Instant;
use stitch_perception::PerceptionError;
use stitch_perception::segment::Segmenter;
use stitch_perception::thread::{ThreadHint, ThreadParams, ThreadTrace, arc_lengths, trace};
use stitch_robot::{
    Needle, Point, Pose, RgbImage, StereoCalibration, Vector, distance_to_polyline,
};
use stitch_sim::{
    Ground, Phantom, SceneView, StereoRenderer, Thread, ThreadConfig, ToolView,
    grasp_in_needle_frame, tool_capsules,
};

/// One pair's thread truth and what the tracer is told.
#[derive(Clone, Debug, PartialEq)]
pub struct ThreadSample {
    /// The true thread from its first end to the swage, robot frame, m.
    pub truth: Vec<Point>,
    /// What a plan would tell the tracer.
    pub hint: ThreadHint,
    /// Whether another tool is in view over the thread.
    pub occluded: bool,
}

/// An own-set pair's scene and its thread.
#[derive(Clone, Debug, PartialEq)]
pub struct OwnThreadSample {
    /// What the camera sees.
    pub scene: SceneView,
    /// The thread's truth and hint.
    pub sample: ThreadSample,
}

/// `n` own-set scenes from `seed`: a needle held by the right jaw over the workspace, the
/// thread from the exit of one of `phantom`'s wound points to its swage (5 to 20 cm of it),
/// and in 40 % of them the left tool's open jaw above the thread.
pub fn own_set(n: usize, seed: u64, needle: Needle, phantom: &Phantom) -> Vec<OwnThreadSample> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x7A_2EAD);
    let ground: Ground = stitch_sim::ground_of(phantom);
    let ws = crate::own::WORKSPACE;
    (0..n)
        .map(|_| {
            let wp = &phantom.wound.points[rng.random_range(0..phantom.wound.points.len())];
            let from = wp.exit;
            // The needle above the wound, beyond the exit side, its jaw from above.
            let out = (wp.exit - wp.entry)
                .try_normalize(1e-12)
                .unwrap_or_else(Vector::x);
            let center = Point::new(
                (from.x + out.x * rng.random_range(0.005..0.03)).clamp(ws[0][0], ws[0][1]),
                (from.y + rng.random_range(-0.02..0.02)).clamp(ws[1][0], ws[1][1]),
                rng.random_range(ws[2][0]..ws[2][1]),
            );
            let spin = rng.random_range(0.0..std::f64::consts::TAU);
            let tilt = rng.random_range(-0.5..0.5);
            let rotation =
                nalgebra::UnitQuaternion::from_euler_angles(std::f64::consts::PI + tilt, 0.0, spin);
            let pose = Pose::from_parts(nalgebra::Translation3::from(center.coords), rotation);
            let tool =
                pose * grasp_in_needle_frame(&needle, rng.random_range(140f64..160.0).to_radians());
            let swage = pose * needle.swage();
            let mut tools = vec![ToolView {
                pose: tool,
                jaw_rad: 0.0,
            }];
            let occluded = rng.random_bool(0.4);
            if occluded {
                // The other tool, jaw open, 5–15 mm above a point between the two ends.
                let mid = from + (swage - from) * rng.random_range(0.3..0.7);
                let above = Point::new(mid.x, mid.y, ground.top_z + rng.random_range(0.005..0.015));
                let r = nalgebra::UnitQuaternion::from_euler_angles(
                    std::f64::consts::PI + rng.random_range(-0.4..0.4),
                    rng.random_range(-0.3..0.3),
                    rng.random_range(0.0..std::f64::consts::TAU),
                );
                tools.push(ToolView {
                    pose: Pose::from_parts(nalgebra::Translation3::from(above.coords), r),
                    jaw_rad: 0.6,
                });
            }
            // The other tool pushes the thread; the holding one holds its end (the mock's
            // world leaves the links at the swage to the grasp too).
            let capsules: Vec<_> = tools[1..]
                .iter()
                .flat_map(|t| tool_capsules(&t.pose, t.jaw_rad))
                .collect();
            let side = rng.random_range(0.0..std::f64::consts::TAU);
            let length_m = rng.random_range(0.05..0.20);
            let thread = Thread::hanging(
                ThreadConfig {
                    length_m,
                    ..ThreadConfig::default()
                },
                ground,
                from,
                swage,
                Vector::new(side.cos(), side.sin(), 0.0),
                &capsules,
                40,
            )
            .expect("the default thread configuration is valid");
            let truth = thread.free.points.clone();
            OwnThreadSample {
                scene: SceneView {
                    needle: Some((needle, pose)),
                    thread: vec![truth.clone()],
                    tools,
                },
                sample: ThreadSample {
                    truth,
                    hint: ThreadHint {
                        start: Some(from),
                        swage,
                        length_m: None,
                    },
                    occluded,
                },
            }
        })
        .collect()
}

/// The independent set's pairs with their threads (the first `n` of its seed).
pub fn independent_set(
    n: usize,
    seed: u64,
    needle: Needle,
) -> Vec<(crate::independent::Sample, ThreadSample)> {
    crate::independent::dataset(n, seed, needle)
        .into_iter()
        .map(|s| {
            let (truth, start, swage) = s.thread_truth();
            let t = ThreadSample {
                truth,
                hint: ThreadHint {
                    start: Some(start),
                    swage,
                    length_m: None,
                },
                occluded: s.jaw.is_some(),
            };
            (s, t)
        })
        .collect()
}

/// Give every sample a length prior: its true length, off by a normal share of `share`
/// (one σ; drawn from `seed` and the sample's place in the set, cut at ±3σ): what a plan
/// knows when it knows how much thread it loaded and how much the stitches took, to so much.
pub fn give_length_prior<'a>(
    samples: impl IntoIterator<Item = &'a mut ThreadSample>,
    share: f64,
    seed: u64,
) {
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x1e46_74f0_0000_0000);
    for s in samples {
        let z = crate::independent::gaussian(&mut rng).clamp(-3.0, 3.0);
        let truth: f64 = s.truth.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
        s.hint.length_m = Some(truth * (1.0 + share * z).max(0.1));
    }
}

/// How one trace compares with its truth.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ThreadResult {
    /// The failure's kind, if it failed.
    pub failure: Option<String>,
    /// Each trace point's distance from the true curve, m.
    pub errors_m: Vec<f64>,
    /// The trace's length against the truth's, as a share of the truth's.
    pub length_error: f64,
    /// True points (every millimetre) within 2σ of the trace's nearest point, and all.
    pub within_2sigma: (usize, usize),
    /// Of those, the true points whose nearest point of the trace lies in one of its hidden
    /// spans: within 2σ, and all.
    pub within_2sigma_hidden: (usize, usize),
    /// The σ the band has at the trace's point nearest each true point, m (how wide the
    /// band is where the truth is judged; not written with the details).
    #[serde(skip)]
    pub band_sigma_m: Vec<f64>,
    /// Time to trace, s.
    pub seconds: f64,
    /// Whether another tool was over the thread.
    pub occluded: bool,
    /// The share of its path the left view showed as thread (NaN when it failed before).
    pub seen: f64,
    /// The share of the true thread the left view shows (from the renderer's labels; NaN
    /// where there are none).
    pub visible: f64,
}

/// Trace one pair and compare.
pub fn evaluate(
    params: &ThreadParams,
    segmenter: &dyn Segmenter,
    calib: &StereoCalibration,
    left: &RgbImage,
    right: &RgbImage,
    sample: &ThreadSample,
) -> (Result<ThreadTrace, PerceptionError>, ThreadResult) {
    let t0 = Instant::now();
    let out = trace(params, segmenter, calib, left, right, &sample.hint);
    let seconds = t0.elapsed().as_secs_f64();
    let result = match &out {
        Ok(t) => compare(t, &sample.truth, seconds, sample.occluded),
        Err(e) => ThreadResult {
            failure: Some(crate::failure_kind(e).to_string()),
            errors_m: vec![],
            length_error: f64::NAN,
            within_2sigma: (0, 0),
            within_2sigma_hidden: (0, 0),
            band_sigma_m: vec![],
            seconds,
            occluded: sample.occluded,
            visible: f64::NAN,
            seen: match e {
                PerceptionError::ThreadHidden { seen_share } => *seen_share,
                _ => f64::NAN,
            },
        },
    };
    (out, result)
}

/// A trace against its truth.
pub fn compare(t: &ThreadTrace, truth: &[Point], seconds: f64, occluded: bool) -> ThreadResult {
    let errors_m = t
        .points
        .iter()
        .map(|p| distance_to_polyline(p, truth))
        .collect();
    let true_len: f64 = truth.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    let dense = resample(truth, 0.001);
    // Where along the trace each of its points lies, m, to tell the hidden spans.
    let arc = arc_lengths(&t.points);
    let (mut inside, mut hidden) = ((0, 0), (0, 0));
    let mut band_sigma_m = Vec::with_capacity(dense.len());
    for p in &dense {
        let nearest = t.nearest_along(p, &arc);
        band_sigma_m.extend(nearest.map(|(_, s, _)| s));
        let covered = nearest.is_some_and(|(d, s, _)| d <= 2.0 * s);
        let in_hidden = nearest
            .is_some_and(|(_, _, a)| t.hidden.iter().any(|&[from, to]| (from..=to).contains(&a)));
        inside.0 += usize::from(covered);
        inside.1 += 1;
        if in_hidden {
            hidden.0 += usize::from(covered);
            hidden.1 += 1;
        }
    }
    ThreadResult {
        failure: None,
        errors_m,
        length_error: (t.length_m - true_len) / true_len.max(1e-9),
        within_2sigma: inside,
        within_2sigma_hidden: hidden,
        band_sigma_m,
        seconds,
        occluded,
        seen: t.seen_share,
        visible: f64::NAN,
    }
}

/// The tracer's accuracy over a set.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct ThreadAccuracy {
    /// Pairs.
    pub frames: usize,
    /// Pairs traced.
    pub traced: usize,
    /// Failures by kind.
    pub failures: Vec<(String, usize)>,
    /// Median of every traced point's distance from the truth, m.
    pub median_error_m: f64,
    /// Its 90th percentile, m.
    pub p90_error_m: f64,
    /// Median of the traces' absolute length errors, as a share.
    pub median_length_error: f64,
    /// Share of true points within 2σ of the trace.
    pub within_2sigma: f64,
    /// Share of the true points whose nearest point of the trace lies in a hidden span.
    pub hidden_points: f64,
    /// The share of those within 2σ.
    pub within_2sigma_hidden: f64,
    /// Median of the band's σ where each true point is judged, m.
    pub median_band_sigma_m: f64,
    /// Median time to trace a pair, s.
    pub median_seconds: f64,
}

/// Summarise results.
pub fn accuracy(results: &[ThreadResult]) -> ThreadAccuracy {
    let mut errors: Vec<f64> = results
        .iter()
        .flat_map(|r| r.errors_m.iter().copied())
        .collect();
    errors.sort_by(f64::total_cmp);
    let ok: Vec<&ThreadResult> = results.iter().filter(|r| r.failure.is_none()).collect();
    let mut lengths: Vec<f64> = ok.iter().map(|r| r.length_error.abs()).collect();
    lengths.sort_by(f64::total_cmp);
    let mut secs: Vec<f64> = results.iter().map(|r| r.seconds).collect();
    secs.sort_by(f64::total_cmp);
    let (inside, all) = ok.iter().fold((0, 0), |(a, b), r| {
        (a + r.within_2sigma.0, b + r.within_2sigma.1)
    });
    let (hidden_inside, hidden_all) = ok.iter().fold((0, 0), |(a, b), r| {
        (a + r.within_2sigma_hidden.0, b + r.within_2sigma_hidden.1)
    });
    let mut band: Vec<f64> = ok
        .iter()
        .flat_map(|r| r.band_sigma_m.iter().copied())
        .collect();
    band.sort_by(f64::total_cmp);
    let mut failures: Vec<(String, usize)> = Vec::new();
    for f in results.iter().filter_map(|r| r.failure.as_ref()) {
        match failures.iter_mut().find(|(k, _)| k == f) {
            Some((_, n)) => *n += 1,
            None => failures.push((f.clone(), 1)),
        }
    }
    ThreadAccuracy {
        frames: results.len(),
        traced: ok.len(),
        failures,
        median_error_m: crate::percentile(&errors, 0.5),
        p90_error_m: crate::percentile(&errors, 0.9),
        median_length_error: crate::percentile(&lengths, 0.5),
        within_2sigma: inside as f64 / all.max(1) as f64,
        hidden_points: hidden_all as f64 / all.max(1) as f64,
        within_2sigma_hidden: hidden_inside as f64 / hidden_all.max(1) as f64,
        median_band_sigma_m: crate::percentile(&band, 0.5),
        median_seconds: crate::percentile(&secs, 0.5),
    }
}

/// Render and trace every own-set sample; noise from `seed`.
pub fn run_own(
    params: &ThreadParams,
    segmenter: &dyn Segmenter,
    renderer: &StereoRenderer,
    samples: &[OwnThreadSample],
    seed: u64,
) -> Vec<ThreadResult> {
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    samples
        .iter()
        .map(|s| {
            let pair = renderer.render(&s.scene, &Pose::identity(), &mut rng);
            let visible = visible_share(
                &s.sample.truth,
                renderer.calibration(),
                &pair.truth.left_labels,
            );
            let mut r = evaluate(
                params,
                segmenter,
                renderer.calibration(),
                &pair.left,
                &pair.right,
                &s.sample,
            )
            .1;
            r.visible = visible;
            r
        })
        .collect()
}

/// The share of a true thread's length that the left view shows (its pixel, or one beside
/// it, labelled thread).
pub fn visible_share(truth: &[Point], calib: &StereoCalibration, labels: &[u8]) -> f64 {
    let dense = resample(truth, 0.0005);
    let (w, h) = (calib.width as i64, calib.height as i64);
    let seen = dense
        .iter()
        .filter(|p| {
            calib.left_pixel(p).is_some_and(|[u, v]| {
                let (x, y) = (u as i64, v as i64);
                (-1..=1).any(|dy| {
                    (-1..=1).any(|dx| {
                        let (xx, yy) = (x + dx, y + dy);
                        xx >= 0
                            && yy >= 0
                            && xx < w
                            && yy < h
                            && labels[(yy * w + xx) as usize] == stitch_sim::Label::Thread as u8
                    })
                })
            })
        })
        .count();
    seen as f64 / dense.len().max(1) as f64
}

/// Render (with `cache`, as the needle's evaluation does) and trace every independent pair.
pub fn run_independent(
    params: &ThreadParams,
    segmenter: &dyn Segmenter,
    samples: &[(crate::independent::Sample, ThreadSample)],
    cache: Option<&std::path::Path>,
) -> Vec<ThreadResult> {
    samples
        .iter()
        .map(|(s, t)| {
            let (l, r) = crate::independent::render_cached(s, cache);
            evaluate(params, segmenter, &s.calibration, &l, &r, t).1
        })
        .collect()
}

/// Points every `step` along a polyline, m.
pub fn resample(line: &[Point], step: f64) -> Vec<Point> {
    let mut out = line.first().copied().into_iter().collect::<Vec<_>>();
    let mut carry = 0.0;
    for w in line.windows(2) {
        let len = (w[1] - w[0]).norm();
        let mut s = step - carry;
        while s <= len {
            out.push(w[0] + (w[1] - w[0]) * (s / len));
            s += step;
        }
        carry = len - (s - step);
    }
    out
}
