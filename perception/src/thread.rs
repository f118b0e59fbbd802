//! The thread tracer: where the free thread runs, from where it leaves the suture line to the
//! needle's swage, from one rectified stereo pair.
//!
//! The stages:
//! 1. **Masks**: the segmenter's thread mask in both views, over a region around the two ends
//!    (the last exit point, known to the plan, and the swage, pinned by the needle estimate)
//!    grown by `margin_m`; grown again while the thread runs off its edge. The right view's
//!    covers the band the left region may match in, or, when the segmenter's mask is local
//!    (`Segmenter::thread_mask_block_px`), only the part of it that stage 3 reads, computed
//!    once the centreline is known.
//! 2. **Centreline** in the left view, from the exit point's pixel to the swage's. Four
//!    candidates: the cheapest path through the mask, where a step on thread costs 1 and a
//!    step off it `gap_cost` (A* over 2 × 2 blocks), which bridges what a jaw or the needle
//!    hides with a straight line but cuts across loops where the thread touches itself; two
//!    walks along the thread from the exit (setting out along that path, or along the
//!    longest run of thread from it), straight on through crossings, round sharp kinks (up
//!    to 172°, a hairpin) onto thread not yet walked, across short gaps, and bridged to the
//!    swage by the cheapest path where they lose it; and a walk the other way, from the
//!    swage, bridged to the exit (for a thread whose first stretch from the tissue is
//!    hidden). The candidate with the most thread on it, less twice its gaps, wins.
//!    Off-thread steps are the hidden spans. Without an exit point (before the first
//!    stitch) the path runs from the swage to the farthest thread it reaches.
//! 3. **Correspondence**: along the path from its first end, each row the thread crosses
//!    steeply enough (more than `min_crossing_rad` from the epipolar lines) is looked up on
//!    the same row of the right view near the disparity the last match had; the two rows'
//!    sub-pixel centres (weighted by how violet each pixel is) give the disparity. Where the
//!    thread runs along the rows there is no disparity to measure: the fit bridges it.
//! 4. **Fit**: three penalised cubic B-splines (P-splines) over the path's length in pixels,
//!    for column, row and disparity, with the two ends as observations of their own
//!    uncertainty, outliers dropped once; their posterior variance gives each sample's
//!    uncertainty, back-projected into metres. A length prior, when the plan knows how much
//!    thread is free, picks the smoothing that brings the length nearest it.
//! 5. **Splices**: when a length prior says the trace is short by more than twice its
//!    uncertainty, thread the view shows apart from the path (a loop whose neck the raised
//!    wound hides) is spliced in, the largest piece first, up to three; the trace whose
//!    length comes nearest the prior wins. Without a prior nothing is spliced: not every
//!    thread pixel in the region need be this thread (a stitch's open loop).
//! 6. **Hidden spans' reach**: with a length prior, the thread the trace may be short of
//!    (the prior, plus `hidden_length_sigmas` of its σ, less the trace) may lie behind any
//!    hidden span; near each, σ grows to half the farthest a thread that long, pinned at
//!    the span's ends, can reach (an ellipsoid with those ends as foci).
//!
//! Hand-written (no crate traces thin curves in stereo): the path search is A* on a pixel
//! grid, the splines a penalised least-squares solve in band storage (`crate::band`).

use crate::PerceptionError;
use crate::band::{self, BandCholesky, LowerBand};
use crate::segment::{Rect, Segmenter};
use nalgebra::DVector;
use serde::{Deserialize, Serialize};
use stitch_robot::{Point, RgbImage, StereoCalibration};

/// What the tracer knows before it looks.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ThreadHint {
    /// Where the thread leaves the suture line (the last stitch's exit point), robot frame,
    /// m; `None` before the first stitch (the tail's end is then found, not given).
    pub start: Option<Point>,
    /// The needle's swage, robot frame, m (from the needle estimate).
    pub swage: Point,
    /// How much thread runs between them, m, if the plan knows (a length prior).
    pub length_m: Option<f64>,
}

/// The traced thread.
#[derive(Clone, Debug, PartialEq)]
pub struct ThreadTrace {
    /// Points along it from its first end (the exit point, or the tail) to the swage, robot
    /// frame, m: the fitted curve sampled about every millimetre.
    pub points: Vec<Point>,
    /// Each point's uncertainty: the root of its covariance's trace (its expected distance
    /// from the truth), m. Where a length prior says the trace may be short, near its hidden
    /// spans it is at least half the farthest the thread hidden there can reach (stage 6).
    pub sigma_m: Vec<f64>,
    /// The curve's length, m.
    pub length_m: f64,
    /// Stretches of it the left view does not show (behind a jaw, the needle, out of the
    /// image): `[from, to]` along the curve from its first end, m.
    pub hidden: Vec<[f64; 2]>,
    /// The share of the path's pixels that were thread in the left view.
    pub seen_share: f64,
    /// Points matched between the two views.
    pub matched: usize,
    /// The left-image path it followed, pixels `[column, row]` (for overlays).
    pub left_path_px: Vec<[f64; 2]>,
}

impl ThreadTrace {
    /// The trace's point nearest `p`, its distance from `p` and its uncertainty, m.
    pub fn nearest(&self, p: &Point) -> Option<(Point, f64, f64)> {
        let (q, i, t) = stitch_robot::nearest_on_polyline(p, &self.points)?;
        Some((q, (p - q).norm(), between(&self.sigma_m, i, t)))
    }

    /// As [`Self::nearest`], with where that point lies along the trace instead of the
    /// point: its distance from `p`, its uncertainty and its place from the first end, m
    /// (`arc_m` the trace's [`arc_lengths`]).
    pub fn nearest_along(&self, p: &Point, arc_m: &[f64]) -> Option<(f64, f64, f64)> {
        let (q, i, t) = stitch_robot::nearest_on_polyline(p, &self.points)?;
        Some((
            (p - q).norm(),
            between(&self.sigma_m, i, t),
            between(arc_m, i, t),
        ))
    }
}

/// `values[i]` to `values[i + 1]`, a share `t` of the way.
fn between(values: &[f64], i: usize, t: f64) -> f64 {
    let v = |k: usize| values.get(k).copied().unwrap_or(0.0);
    v(i) + (v(i + 1) - v(i)) * t
}

/// Each point's distance along the polyline from its first, m.
pub fn arc_lengths(points: &[Point]) -> Vec<f64> {
    let mut arc = vec![0.0; points.len()];
    for i in 1..points.len() {
        arc[i] = arc[i - 1] + (points[i] - points[i - 1]).norm();
    }
    arc
}

/// The tracer's settings.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ThreadParams {
    /// How far past the two ends the thread is looked for at first, m (the region grows
    /// while the thread runs off its edge).
    pub margin_m: f64,
    /// How much more a path step off the thread costs than one on it (bridging hidden
    /// stretches in straight lines).
    pub gap_cost: u32,
    /// The least share of the path the left view must show as thread.
    pub min_seen_share: f64,
    /// The least points matched between the views.
    pub min_matched: usize,
    /// The thread must cross the rows at least this steeply to be matched there, rad.
    pub min_crossing_rad: f64,
    /// How far from the predicted disparity a match may be, pixels.
    pub search_px: f64,
    /// Uncertainty of a centre in a view (column, row), pixels.
    pub centre_sigma_px: f64,
    /// Uncertainty of a measured disparity, pixels.
    pub disparity_sigma_px: f64,
    /// Uncertainty of the ends the hint gives, m.
    pub end_sigma_m: f64,
    /// Spacing of the splines' knots along the path, pixels.
    pub knot_px: f64,
    /// The splines' smoothing (weight of their coefficients' second differences).
    pub smoothing: f64,
    /// Uncertainty of the length prior, as a share of it.
    pub length_prior_share: f64,
    /// How far past a length prior the thread may run, in the prior's σ, where the hidden
    /// spans' reach is worked out (1: the least that put 90 % of the hidden thread inside
    /// the band on the own and independent sets, seed 1; `docs/perception.md`).
    pub hidden_length_sigmas: f64,
}

impl Default for ThreadParams {
    fn default() -> Self {
        Self {
            margin_m: 0.025,
            gap_cost: 8,
            min_seen_share: 0.6,
            min_matched: 6,
            min_crossing_rad: 25f64.to_radians(),
            search_px: 6.0,
            centre_sigma_px: 0.35,
            disparity_sigma_px: 0.45,
            end_sigma_m: 0.001,
            knot_px: 14.0,
            smoothing: 2.0,
            length_prior_share: 0.1,
            hidden_length_sigmas: 1.0,
        }
    }
}

/// Most times the region grows before the tracer gives up on containing the thread.
const MAX_GROWTH: usize = 3;

/// Trace the thread in a rectified pair.
pub fn trace(
    params: &ThreadParams,
    segmenter: &dyn Segmenter,
    calib: &StereoCalibration,
    left: &RgbImage,
    right: &RgbImage,
    hint: &ThreadHint,
) -> Result<ThreadTrace, PerceptionError> {
    let mut t = trace_regions(params, segmenter, calib, left, right, hint)?;
    if let Some(prior) = hint.length_m.filter(|l| *l > 0.0) {
        widen_hidden(
            &mut t,
            prior * (1.0 + params.hidden_length_sigmas * params.length_prior_share),
        );
    }
    Ok(t)
}

/// Where a trace is shorter than `most_m`, the most thread there can be between its ends
/// (from a length prior), the thread it is missing may lie in any of its hidden spans: each
/// span's σ is widened to half the distance from the span's chord to the ellipse that a
/// thread of the span's length plus the whole shortfall, pinned at the span's two ends,
/// cannot leave (the ends its foci, the length its major axis), there and past the span's
/// ends as far as the ellipse reaches. A bound, not a fit's posterior: the thread may take
/// any way behind what hides it, and 2σ is the farthest it can reach. A trace not shorter
/// than `most_m` keeps the fit's σ.
fn widen_hidden(t: &mut ThreadTrace, most_m: f64) {
    let excess = most_m - t.length_m;
    if excess <= 0.0 || t.hidden.is_empty() || t.points.len() < 2 {
        return;
    }
    let arc = arc_lengths(&t.points);
    let n = t.points.len();
    let mut widened = t.sigma_m.clone();
    for &[from, to] in &t.hidden {
        let (i0, i1) = (
            arc.partition_point(|&a| a < from).min(n - 1),
            arc.partition_point(|&a| a <= to).saturating_sub(1),
        );
        if i1 <= i0 {
            continue;
        }
        let chord = (t.points[i1] - t.points[i0]).norm();
        let span = arc[i1] - arc[i0];
        let semi_major = 0.5 * (span + excess);
        let semi_minor = (semi_major * semi_major - 0.25 * chord * chord)
            .max(0.0)
            .sqrt();
        // Each point's place along the ellipse's axis from its centre: on the chord within
        // the span, and past its ends (where the ellipse reaches beyond the foci) by the arc
        // length from the end.
        let axial = |k: usize| {
            if k < i0 {
                -0.5 * chord - (arc[i0] - arc[k])
            } else if k > i1 {
                0.5 * chord + (arc[k] - arc[i1])
            } else {
                ((arc[k] - arc[i0]) / span.max(1e-12) - 0.5) * chord
            }
        };
        for (i, w) in widened.iter_mut().enumerate() {
            // The ellipse's half-width is largest at the centre: at each point, take its
            // widest over the stretches to the points either side, so that the σ read
            // between two points (interpolated) still bounds it.
            let (xa, xb) = (axial(i.saturating_sub(1)), axial((i + 1).min(n - 1)));
            let x = if xa <= 0.0 && xb >= 0.0 {
                0.0
            } else {
                xa.abs().min(xb.abs())
            };
            if x < semi_major {
                let half_width = semi_minor * (1.0 - (x / semi_major).powi(2)).sqrt();
                *w = w.max(0.5 * half_width);
            }
        }
    }
    t.sigma_m = widened;
}

/// [`trace`] before the hidden spans are widened: the region grown while the thread runs
/// off it.
fn trace_regions(
    params: &ThreadParams,
    segmenter: &dyn Segmenter,
    calib: &StereoCalibration,
    left: &RgbImage,
    right: &RgbImage,
    hint: &ThreadHint,
) -> Result<ThreadTrace, PerceptionError> {
    for (name, im) in [("left", left), ("right", right)] {
        if (im.width, im.height) != (calib.width, calib.height) {
            return Err(PerceptionError::Config {
                message: format!(
                    "the {name} image is {}×{}, the calibration's {}×{}",
                    im.width, im.height, calib.width, calib.height
                ),
            });
        }
    }
    let to_uvd = |p: &Point| -> Option<[f64; 3]> {
        let q = calib.camera_to_robot.inverse() * p;
        (q.z > 1e-4).then(|| {
            [
                calib.fx * q.x / q.z + calib.cx,
                calib.fy * q.y / q.z + calib.cy,
                calib.fx * calib.baseline_m / q.z,
            ]
        })
    };
    let swage = to_uvd(&hint.swage).ok_or_else(|| PerceptionError::Config {
        message: "the swage is behind the camera".into(),
    })?;
    let start = match &hint.start {
        Some(p) => Some(to_uvd(p).ok_or_else(|| PerceptionError::Config {
            message: "the exit point is behind the camera".into(),
        })?),
        None => None,
    };
    let fb = calib.fx * calib.baseline_m;
    let mut margin = params.margin_m;
    let mut last = None;
    for _ in 0..=MAX_GROWTH {
        let ends: Vec<[f64; 3]> = std::iter::once(swage).chain(start).collect();
        let z_near = ends.iter().map(|e| fb / e[2]).fold(f64::INFINITY, f64::min);
        let m_px = calib.fx * margin / z_near.max(0.01);
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for e in &ends {
            for i in 0..2 {
                lo[i] = lo[i].min(e[i]);
                hi[i] = hi[i].max(e[i]);
            }
        }
        let clip = |v: f64, max: u32| v.clamp(0.0, f64::from(max)) as u32;
        let roi = Rect {
            x0: clip(lo[0] - m_px, calib.width),
            y0: clip(lo[1] - m_px, calib.height),
            x1: clip(hi[0] + m_px, calib.width),
            y1: clip(hi[1] + m_px, calib.height),
        };
        if roi.is_empty() {
            return Err(PerceptionError::NoThread {
                view: "left".into(),
            });
        }
        // Depths within the margin of the ends' (and the pad below them): the disparities
        // the right view's band must cover.
        let d_hi = ends.iter().map(|e| e[2]).fold(0.0, f64::max);
        let z_far = ends.iter().map(|e| fb / e[2]).fold(0.0, f64::max) + margin;
        let d_lo = fb / z_far;
        let d_hi = fb / (fb / d_hi - margin).max(0.01);
        let full = roi == Rect::full(calib.width, calib.height);
        match trace_in(
            params,
            segmenter,
            calib,
            left,
            right,
            roi,
            [d_lo, d_hi],
            swage,
            start,
            hint,
        ) {
            Ok((t, touches)) if !touches || full => return Ok(t),
            Ok((t, _)) => last = Some(Ok(t)),
            // A thread that leaves the region may be found in a larger one.
            Err(
                e @ (PerceptionError::NoThread { .. }
                | PerceptionError::ThreadHidden { .. }
                | PerceptionError::ThreadUntraced { .. }),
            ) if !full => {
                last = Some(Err(e));
            }
            Err(e) => return Err(e),
        }
        margin *= 2.0;
    }
    last.unwrap_or(Err(PerceptionError::NoThread {
        view: "left".into(),
    }))
}

/// One try over the left region `roi`: the trace and whether the thread ran off the region.
#[allow(clippy::too_many_arguments)]
fn trace_in(
    params: &ThreadParams,
    segmenter: &dyn Segmenter,
    calib: &StereoCalibration,
    left: &RgbImage,
    right: &RgbImage,
    roi: Rect,
    disparity: [f64; 2],
    swage: [f64; 3],
    start: Option<[f64; 3]>,
    hint: &ThreadHint,
) -> Result<(ThreadTrace, bool), PerceptionError> {
    let mask = segmenter.thread_mask(left, roi)?;
    let (w, h) = (roi.width() as usize, roi.height() as usize);
    if mask.iter().filter(|&&v| v != 0).count() < 20 {
        return Err(PerceptionError::NoThread {
            view: "left".into(),
        });
    }
    // The right view's band: every pixel the left region's may match.
    let band = Rect {
        x0: roi.x0.saturating_sub(disparity[1].ceil() as u32 + 2),
        y0: roi.y0,
        x1: (roi.x1 as f64 - disparity[0].floor() + 2.0).clamp(0.0, f64::from(calib.width)) as u32,
        y1: roi.y1,
    };
    // Its mask over the whole band unless the segmenter's is local; then only where the
    // rows of the left trace read it, once they are known (below).
    let band_mask = match segmenter.thread_mask_block_px() {
        Some(_) => None,
        None => Some(right_mask(segmenter, right, band)?),
    };
    // The path is searched on 2×2 blocks (a block is thread if any of its pixels is): a
    // thread two or three pixels wide stays connected, and the search is four times smaller.
    let (cw, ch) = (w.div_ceil(2), h.div_ceil(2));
    let mut coarse = vec![0u8; cw * ch];
    for (i, _) in mask.iter().enumerate().filter(|(_, v)| **v != 0) {
        coarse[(i / w / 2) * cw + (i % w) / 2] = 1;
    }
    let cell = |u: f64, v: f64| -> usize {
        let x = ((u - f64::from(roi.x0)) / 2.0).clamp(0.0, cw as f64 - 1.0) as usize;
        let y = ((v - f64::from(roi.y0)) / 2.0).clamp(0.0, ch as f64 - 1.0) as usize;
        y * cw + x
    };
    let grid = Grid {
        w: cw,
        h: ch,
        mask: &coarse,
        gap: params.gap_cost.max(1),
    };
    let from = cell(swage[0], swage[1]);
    // The path from the first end to the swage, image pixels, and whether each point is on
    // the thread.
    let local = |u: f64, v: f64| (u - f64::from(roi.x0), v - f64::from(roi.y0));
    let to_image =
        |(x, y, on): (f64, f64, bool)| (x + f64::from(roi.x0), y + f64::from(roi.y0), on);
    let block_path = |cells: &[usize]| -> Vec<(f64, f64, bool)> {
        cells
            .iter()
            .map(|&i| {
                let (bx, by) = (2 * (i % cw), 2 * (i / cw));
                let on = (0..4)
                    .map(|k| (bx + k % 2, by + k / 2))
                    .find(|&(x, y)| x < w && y < h && mask[y * w + x] != 0);
                let (x, y) = on.map_or((bx as f64 + 1.0, by as f64 + 1.0), |(x, y)| {
                    (x as f64 + 0.5, y as f64 + 0.5)
                });
                (x, y, on.is_some())
            })
            .collect()
    };
    let local_path: Vec<(f64, f64, bool)> = match start {
        // Walk along the thread from the exit point, straight on through crossings, as far
        // as it goes; the cheapest path bridges the rest to the swage.
        Some(s) => {
            let walker = Walker { mask: &mask, w, h };
            let mut walk_cells = Vec::new();
            // The last bridge from the swage: the two walks often lose the thread at the same
            // place.
            let mut bridged: Option<(usize, Vec<usize>)> = None;
            let goal = local(swage[0], swage[1]);
            let score = |path: &[(f64, f64, bool)]| -> f64 {
                path.windows(2)
                    .map(|q| {
                        let d = (q[1].0 - q[0].0).hypot(q[1].1 - q[0].1);
                        if q[0].2 && q[1].2 { d } else { -2.0 * d }
                    })
                    .sum()
            };
            // Which way the thread leaves the start: where the cheapest path goes. Its
            // search from the swage is kept for the bridges below, which also start there.
            let mut from_swage = grid.search(from, Some(cell(s[0], s[1])));
            let mut cheapest = from_swage.path_to(None).unwrap_or_else(|| vec![from]);
            cheapest.reverse();
            let first = block_path(&cheapest);
            let from_start = local(s[0], s[1]);
            let ahead = first
                .iter()
                .find(|&&(x, y, _)| (x - from_start.0).hypot(y - from_start.1) >= 12.0)
                .map_or(goal, |&(x, y, _)| (x, y));
            // Three candidates: the cheapest path, and walks setting out along it or along
            // the longest run of thread from the start, each bridged to the swage where it
            // loses the thread. The one with the most thread on it (less twice its gaps)
            // wins: a walk round a loop beats a path cutting across it.
            let mut best = (score(&first), first);
            for toward in [Some(ahead), None] {
                let mut walked = walker.walk(from_start, toward, goal, &mut walk_cells);
                let reached = walked
                    .last()
                    .is_some_and(|&(x, y, _)| (x - goal.0).hypot(y - goal.1) < 2.0);
                if !reached {
                    let &(x, y, _) = walked.last().unwrap_or(&(goal.0, goal.1, false));
                    let to = cell(x + f64::from(roi.x0), y + f64::from(roi.y0));
                    let mut cells = match &bridged {
                        Some((t, c)) if *t == to => c.clone(),
                        _ => {
                            let c = grid.path_via(&mut from_swage, to);
                            bridged = Some((to, c.clone()));
                            c
                        }
                    };
                    cells.reverse();
                    walked.extend(block_path(&cells).into_iter().skip(1));
                }
                let sc = score(&walked);
                if sc > best.0 {
                    best = (sc, walked);
                }
            }
            // And a walk from the swage towards the start, for a thread whose first stretch
            // from the tissue is hidden (behind the raised wound, a jaw): bridged to the start
            // where it loses the thread, then turned round.
            let mut walked = walker.walk(goal, None, from_start, &mut walk_cells);
            let reached = walked
                .last()
                .is_some_and(|&(x, y, _)| (x - from_start.0).hypot(y - from_start.1) < 2.0);
            if !reached {
                let &(x, y, _) = walked
                    .last()
                    .unwrap_or(&(from_start.0, from_start.1, false));
                let cells = grid.path(
                    cell(x + f64::from(roi.x0), y + f64::from(roi.y0)),
                    Some(cell(s[0], s[1])),
                );
                walked.extend(block_path(&cells).into_iter().skip(1));
            }
            walked.reverse();
            let sc = score(&walked);
            if sc > best.0 {
                best = (sc, walked);
            }
            best.1
        }
        None => {
            let mut cells = grid.path(from, None);
            cells.reverse();
            block_path(&cells)
        }
    };
    // The rest, from a path: correspondences between the views (`observe`), and the fit
    // (`fit`; `prior`: the length prior the fit's smoothing is chosen by, if any).
    let observe = |local_path: Vec<(f64, f64, bool)>| -> Result<Observed, PerceptionError> {
        let cells: Vec<usize> = local_path
            .iter()
            .map(|&(x, y, _)| cell(x + f64::from(roi.x0), y + f64::from(roi.y0)))
            .collect();
        let path: Vec<(f64, f64, bool)> = local_path.into_iter().map(to_image).collect();
        if path.len() < 3 {
            return Err(PerceptionError::ThreadUntraced {
                why: "the ends are too close together in the image to trace between".into(),
            });
        }
        let touches = path.iter().any(|&(x, y, on)| {
            on && (x < f64::from(roi.x0) + 2.0
                || y < f64::from(roi.y0) + 2.0
                || x > f64::from(roi.x1) - 2.0
                || y > f64::from(roi.y1) - 2.0)
        }) || {
            // Thread connected to the path that leaves the region is as telling.
            let border = |i: usize| {
                let (x, y) = (i % cw, i / cw);
                x == 0 || y == 0 || x + 1 == cw || y + 1 == ch
            };
            grid.reaches_border(&cells, border)
        };
        // Arc length along the path (smoothed), pixels.
        let smooth: Vec<[f64; 2]> = (0..path.len())
            .map(|k| {
                let (a, b) = (k.saturating_sub(3), (k + 3).min(path.len() - 1));
                let n = (b - a + 1) as f64;
                let s = path[a..=b]
                    .iter()
                    .fold([0.0, 0.0], |s, p| [s[0] + p.0, s[1] + p.1]);
                [s[0] / n, s[1] / n]
            })
            .collect();
        let mut t = vec![0.0; path.len()];
        for k in 1..path.len() {
            t[k] =
                t[k - 1] + (smooth[k][0] - smooth[k - 1][0]).hypot(smooth[k][1] - smooth[k - 1][1]);
        }
        let total = t[path.len() - 1].max(1.0);
        let on_len: f64 = (1..path.len())
            .filter(|&k| path[k].2 && path[k - 1].2)
            .map(|k| t[k] - t[k - 1])
            .sum();
        let seen_share = on_len / total;
        if seen_share < params.min_seen_share {
            return Err(PerceptionError::ThreadHidden { seen_share });
        }

        // Observations: centres in the left view, disparities where the rows cross it.
        let lview = View {
            image: left,
            roi,
            mask: &mask,
        };
        let sin_min = params.min_crossing_rad.sin();
        let mut uv = Vec::new(); // (t, u, v)
        // Every row crossing: its arc length, its centre in the left view and its row.
        let mut rows_crossed: Vec<(f64, f64, u32)> = Vec::new();
        let mut measured_rows = std::collections::HashSet::new();
        for k in 0..path.len() {
            let (x, y, on) = path[k];
            if !on {
                continue;
            }
            let (a, b) = (k.saturating_sub(4), (k + 4).min(path.len() - 1));
            let (tx, ty) = (smooth[b][0] - smooth[a][0], smooth[b][1] - smooth[a][1]);
            let n = tx.hypot(ty);
            if n < 1e-9 {
                continue;
            }
            let row = y as u32;
            if (ty / n).abs() >= sin_min {
                let Some((l0, l1)) = lview.run(x as i64, row) else {
                    continue;
                };
                let xl = lview.centre(l0, l1, row);
                uv.push((t[k], xl, y));
                if measured_rows.insert((row, l0)) {
                    rows_crossed.push((t[k], xl, row));
                }
            } else if let Some(yc) = lview.column_centre(x as i64, row) {
                uv.push((t[k], x, yc));
            }
        }
        let (right_roi, rmask) = match &band_mask {
            Some(m) => (band, std::borrow::Cow::Borrowed(m.as_slice())),
            None => {
                let block = segmenter.thread_mask_block_px().unwrap_or(1);
                let roi = read_region(band, &rows_crossed, disparity, block);
                if roi.is_empty() {
                    (roi, std::borrow::Cow::Owned(Vec::new()))
                } else {
                    (
                        roi,
                        std::borrow::Cow::Owned(right_mask(segmenter, right, roi)?),
                    )
                }
            }
        };
        let rview = View {
            image: right,
            roi: right_roi,
            mask: &rmask,
        };
        // Every disparity the right view's row allows, at each crossing.
        let crossings: Vec<(f64, Vec<f64>)> = rows_crossed // (t, candidate disparities)
            .iter()
            .filter_map(|&(t, xl, row)| {
                let c: Vec<f64> = rview
                    .runs(xl - disparity[1], xl - disparity[0], row)
                    .into_iter()
                    .map(|xr| xl - xr)
                    .collect();
                (!c.is_empty()).then_some((t, c))
            })
            .collect();
        let disp = smoothest(
            &crossings,
            start.map(|s| (0.0, s[2])),
            (total, swage[2]),
            params.search_px,
        );
        if disp.len() < params.min_matched {
            return Err(PerceptionError::ThreadUntraced {
                why: format!(
                    "only {} points matched between the views ({} needed)",
                    disp.len(),
                    params.min_matched
                ),
            });
        }

        // The ends, as observations with the hint's uncertainty.
        let end_obs = |e: [f64; 3]| -> [f64; 3] {
            let z = calib.fx * calib.baseline_m / e[2];
            let s_px = calib.fx * params.end_sigma_m / z;
            let s_d = e[2] / z * params.end_sigma_m;
            [s_px, s_px, s_d.max(0.1)]
        };
        let mut ends: Vec<(f64, [f64; 3], [f64; 3])> = vec![(total, swage, end_obs(swage))];
        if let Some(s) = start {
            ends.push((0.0, s, end_obs(s)));
        }
        Ok(Observed {
            path,
            t,
            total,
            seen_share,
            uv,
            disp,
            ends,
            touches,
        })
    };
    let fit = |o: &Observed, prior: Option<f64>| -> Result<(ThreadTrace, bool), PerceptionError> {
        let Observed {
            path,
            t,
            uv,
            disp,
            ends,
            ..
        } = o;
        let (total, seen_share, touches) = (o.total, o.seen_share, o.touches);
        let k_count = ((total / params.knot_px).ceil() as usize + 3).clamp(6, 80);
        let basis = Basis {
            count: k_count,
            span: total,
        };
        let cs = params.centre_sigma_px;
        let ds = params.disparity_sigma_px;
        let axis_obs = |axis: usize| -> Vec<(f64, f64, f64)> {
            let mut o: Vec<(f64, f64, f64)> = match axis {
                0 => uv.iter().map(|&(t, u, _)| (t, u, cs)).collect(),
                1 => uv.iter().map(|&(t, _, v)| (t, v, cs)).collect(),
                _ => disp.iter().map(|&(t, d)| (t, d, ds)).collect(),
            };
            o.extend(ends.iter().map(|(t, e, s)| (*t, e[axis], s[axis])));
            o
        };
        // Each axis's observations with their basis weights and the data's part of the
        // normal equations, once for every smoothing tried.
        let prepared: Vec<Prepared> = (0..3).map(|axis| basis.prepare(axis_obs(axis))).collect();
        let fit_all = |smoothing: f64| -> Option<[Fit; 3]> {
            let mut fits = Vec::with_capacity(3);
            for (axis, p) in prepared.iter().enumerate() {
                let mut f = basis.fit_prepared(p, smoothing)?;
                // Once: drop observations far off the first fit (a wrong match, a speck).
                let floor = if axis == 2 { 1.5 } else { 2.0 };
                let keep: Vec<bool> = p
                    .weights
                    .iter()
                    .zip(&p.obs)
                    .map(|(&(i, w), &(_, y, s))| {
                        (dot(&f.coef, i, &w) - y).abs() <= (4.0 * s).max(floor)
                    })
                    .collect();
                if keep.contains(&false) {
                    let kept: Vec<(f64, f64, f64)> = p
                        .obs
                        .iter()
                        .zip(&keep)
                        .filter(|(_, k)| **k)
                        .map(|(o, _)| *o)
                        .collect();
                    f = basis.fit(&kept, smoothing)?;
                }
                fits.push(f);
            }
            fits.try_into().ok()
        };
        let samples = ((total / 3.0).ceil() as usize).clamp(16, 600);
        // (`sigma`: whether to work out each point's uncertainty too; the choice of smoothing
        // needs only the points.)
        let curve = |fits: &[Fit; 3], sigma: bool| -> (Vec<Point>, Vec<f64>, Vec<f64>) {
            let mut pts = Vec::with_capacity(samples + 1);
            let mut sig = Vec::with_capacity(samples + 1);
            let mut ts = Vec::with_capacity(samples + 1);
            for i in 0..=samples {
                let tt = total * i as f64 / samples as f64;
                let (u, v, d) = (
                    basis.eval(&fits[0].coef, tt),
                    basis.eval(&fits[1].coef, tt),
                    basis.eval(&fits[2].coef, tt).max(1.0),
                );
                let z = calib.fx * calib.baseline_m / d;
                let (xc, yc) = ((u - calib.cx) * z / calib.fx, (v - calib.cy) * z / calib.fy);
                pts.push(calib.camera_to_robot * Point::new(xc, yc, z));
                ts.push(tt);
                if !sigma {
                    continue;
                }
                // Back-projection's Jacobian, applied to each axis's posterior variance.
                let (su2, sv2, sd2) = (
                    fits[0].variance(&basis, tt) + cs * cs * 0.25,
                    fits[1].variance(&basis, tt) + cs * cs * 0.25,
                    fits[2].variance(&basis, tt) + ds * ds * 0.25,
                );
                let dz_dd = z / d;
                let var = su2 * (z / calib.fx).powi(2)
                    + sv2 * (z / calib.fy).powi(2)
                    + sd2 * (dz_dd.powi(2) * (1.0 + (xc / z).powi(2) + (yc / z).powi(2)));
                sig.push(var.sqrt());
            }
            (pts, sig, ts)
        };
        let length = |pts: &[Point]| pts.windows(2).map(|w| (w[1] - w[0]).norm()).sum::<f64>();
        let mut best: Option<([Fit; 3], f64)> = None;
        match prior {
            // A length prior: the smoothing whose curve's length comes nearest it, weighed
            // against how much the fit strays from the data.
            Some(prior) => {
                let sigma = (prior * params.length_prior_share).max(1e-4);
                for scale in [0.1, 0.3, 1.0, 3.0, 10.0, 30.0] {
                    let Some(fits) = fit_all(params.smoothing * scale) else {
                        continue;
                    };
                    let (pts, _, _) = curve(&fits, false);
                    let chi: f64 = fits.iter().map(|f| f.chi2).sum::<f64>()
                        / (uv.len() + disp.len()).max(1) as f64;
                    let score = ((length(&pts) - prior) / sigma).powi(2) + chi;
                    if best.as_ref().is_none_or(|(_, s)| score < *s) {
                        best = Some((fits, score));
                    }
                }
            }
            None => best = fit_all(params.smoothing).map(|f| (f, 0.0)),
        }
        let Some((fits, _)) = best else {
            return Err(PerceptionError::ThreadUntraced {
                why: "the spline fit was singular".into(),
            });
        };
        let (points, sigma_m, ts) = curve(&fits, true);
        // Arc length in metres at each sample, to place the hidden spans.
        let arc = arc_lengths(&points);
        let at = |tt: f64| -> f64 {
            let i = ts.partition_point(|&x| x < tt).min(ts.len() - 1);
            arc[i]
        };
        let mut hidden = Vec::new();
        let mut k = 0;
        while k < path.len() {
            if path[k].2 {
                k += 1;
                continue;
            }
            let s = k;
            while k < path.len() && !path[k].2 {
                k += 1;
            }
            if t[k.min(path.len() - 1)] - t[s] >= 3.0 {
                hidden.push([at(t[s.saturating_sub(1)]), at(t[k.min(path.len() - 1)])]);
            }
        }
        let length_m = arc.last().copied().unwrap_or(0.0);
        Ok((
            ThreadTrace {
                points,
                sigma_m,
                length_m,
                hidden,
                seen_share,
                matched: disp.len(),
                left_path_px: path.iter().map(|&(x, y, _)| [x, y]).collect(),
            },
            touches,
        ))
    };
    let prior = hint.length_m.filter(|l| *l > 0.0);
    let first = observe(local_path.clone()).and_then(|o| fit(&o, prior));
    // With a length prior the trace falls well short of: thread the path does not pass (a
    // strand the view shows apart from it, a loop whose neck the raised wound or a tool
    // hides) spliced in where its ends lie nearest the path, the largest first, one more at
    // a time while the trace stays short. The trace whose length comes nearest the prior
    // wins.
    let (Some(prior), Some(_)) = (prior, start) else {
        return first;
    };
    let floor = prior * (1.0 - 2.0 * params.length_prior_share);
    if matches!(&first, Ok((t, _)) if t.length_m >= floor) {
        return first;
    }
    let lcell = |(x, y, _): (f64, f64, bool)| cell(x + f64::from(roi.x0), y + f64::from(roi.y0));
    // A splice's bridge: the cheapest path between the two (it may run along thread).
    let bridge =
        |a: (f64, f64, bool), b: (f64, f64, bool)| block_path(&grid.path(lcell(a), Some(lcell(b))));
    // The splices are fitted at the default smoothing; the one chosen is fitted again, from
    // the same observations, with the prior's.
    let mut traces = vec![(first, None)];
    let mut path = local_path;
    for _ in 0..MAX_STRANDS {
        let on_path: Vec<usize> = path.iter().map(|&q| lcell(q)).collect();
        let Some(strand) = grid.strands(&on_path).into_iter().next() else {
            break;
        };
        path = splice(&path, block_path(&strand), bridge);
        let (t, observed) = match observe(path.clone()) {
            Ok(o) => (fit(&o, None), Some(o)),
            Err(e) => (Err(e), None),
        };
        let enough = matches!(&t, Ok((t, _)) if t.length_m >= floor);
        traces.push((t, observed));
        if enough {
            break;
        }
    }
    let off = |t: &Result<(ThreadTrace, bool), PerceptionError>| {
        t.as_ref()
            .map_or(f64::INFINITY, |(t, _)| (t.length_m - prior).abs())
    };
    let best = (1..traces.len()).fold(0, |b, k| {
        if off(&traces[k].0) < off(&traces[b].0) {
            k
        } else {
            b
        }
    });
    match traces.swap_remove(best) {
        // (A splice beats the first trace only with a trace, so it was observed.)
        (_, Some(observed)) if best > 0 => fit(&observed, Some(prior)),
        (t, _) => t,
    }
}

/// What a path gives before the fit: the path in image pixels, its smoothed arc length at
/// each point and in all (pixels), the share of it on thread, the left view's centres
/// `(t, u, v)`, the matched disparities `(t, d)`, the ends as observations `(t, [u, v, d],
/// their σ)`, and whether thread on it runs off the region.
struct Observed {
    path: Vec<(f64, f64, bool)>,
    t: Vec<f64>,
    total: f64,
    seen_share: f64,
    uv: Vec<(f64, f64, f64)>,
    disp: Vec<(f64, f64)>,
    ends: Vec<(f64, [f64; 3], [f64; 3])>,
    touches: bool,
}

/// Most strands spliced into one path.
const MAX_STRANDS: usize = 3;
/// The fewest 2 × 2 blocks a strand apart from the path has to be spliced in.
const MIN_STRAND_CELLS: usize = 10;

/// `path` with `strand` spliced in: from the path's point nearest one of the strand's ends,
/// bridged to it, along the strand, bridged back to the path's point nearest its other end,
/// and on (what the path did between those two points is left out).
fn splice(
    path: &[(f64, f64, bool)],
    mut strand: Vec<(f64, f64, bool)>,
    bridge: impl Fn((f64, f64, bool), (f64, f64, bool)) -> Vec<(f64, f64, bool)>,
) -> Vec<(f64, f64, bool)> {
    let (Some(&a), Some(&b), false) = (strand.first(), strand.last(), path.is_empty()) else {
        return path.to_vec();
    };
    let nearest = |q: (f64, f64, bool)| {
        (0..path.len())
            .min_by(|&i, &j| {
                let d = |k: usize| (path[k].0 - q.0).hypot(path[k].1 - q.1);
                d(i).total_cmp(&d(j))
            })
            .unwrap_or(0)
    };
    let (mut i, mut j) = (nearest(a), nearest(b));
    if i > j {
        strand.reverse();
        std::mem::swap(&mut i, &mut j);
    }
    let (a, b) = (strand[0], strand[strand.len() - 1]);
    let mut out = path[..=i].to_vec();
    out.extend(bridge(path[i], a).into_iter().skip(1));
    out.extend(strand.into_iter().skip(1));
    out.extend(bridge(b, path[j]).into_iter().skip(1));
    out.extend(path[j + 1..].iter().copied());
    out
}

/// The smoothest sequence of disparities through the crossings (Viterbi): one candidate
/// (or none) at each, the disparity a random walk along the path (a step of `step_px` over
/// a hundred pixels of path costs 1; a skipped crossing 4), pinned loosely at the ends.
fn smoothest(
    crossings: &[(f64, Vec<f64>)],
    start: Option<(f64, f64)>,
    end: (f64, f64),
    step_px: f64,
) -> Vec<(f64, f64)> {
    /// Crossings a transition may skip.
    const REACH: usize = 12;
    const SKIP: f64 = 4.0;
    let var = step_px * step_px / 100.0;
    let walk =
        |d0: f64, t0: f64, d1: f64, t1: f64| (d1 - d0).powi(2) / (var * (t1 - t0).abs().max(1.0));
    // The ends are known to a few pixels of disparity: loose, so a wrong hint does not
    // choose the matches.
    let end_walk = |d0: f64, t0: f64, d1: f64, t1: f64| walk(d0, t0, d1, t1) / 16.0;
    let m = crossings.len();
    let mut cost: Vec<Vec<f64>> = Vec::with_capacity(m);
    let mut back: Vec<Vec<Option<(usize, usize)>>> = Vec::with_capacity(m);
    for j in 0..m {
        let (tj, cj) = &crossings[j];
        let mut cj_cost = Vec::with_capacity(cj.len());
        let mut cj_back = Vec::with_capacity(cj.len());
        for &d in cj {
            // From the start (skipping every crossing before this one).
            let mut best = SKIP * j as f64 + start.map_or(0.0, |(t0, d0)| end_walk(d0, t0, d, *tj));
            let mut from = None;
            for i in j.saturating_sub(REACH)..j {
                let (ti, ci) = &crossings[i];
                for (a, &da) in ci.iter().enumerate() {
                    let c = cost[i][a] + walk(da, *ti, d, *tj) + SKIP * (j - i - 1) as f64;
                    if c < best {
                        best = c;
                        from = Some((i, a));
                    }
                }
            }
            cj_cost.push(best);
            cj_back.push(from);
        }
        cost.push(cj_cost);
        back.push(cj_back);
    }
    let mut best: Option<(f64, usize, usize)> = None;
    for j in m.saturating_sub(REACH)..m {
        for (a, &da) in crossings[j].1.iter().enumerate() {
            let c =
                cost[j][a] + end_walk(da, crossings[j].0, end.1, end.0) + SKIP * (m - j - 1) as f64;
            if best.is_none_or(|(b, _, _)| c < b) {
                best = Some((c, j, a));
            }
        }
    }
    let mut out = Vec::new();
    let mut at = best.map(|(_, j, a)| (j, a));
    while let Some((j, a)) = at {
        out.push((crossings[j].0, crossings[j].1[a]));
        at = back[j][a];
    }
    out.reverse();
    out
}

/// The left region's thread mask, as a graph of pixels.
/// The open set of an A* search with a consistent heuristic, whose f never falls below the
/// last popped and never rises more than the ring's length above it (Dial's buckets): pops
/// give the least f, and among equal f the least cell — the order a binary heap of (f, cell)
/// gives, without sifting through every entry. Written here because it is a dozen lines
/// tied to this search's bounds.
struct Buckets {
    ring: Vec<Vec<u32>>,
    /// The f of the bucket at the ring's cursor: the last popped (the first pushed before
    /// any pop).
    f: Option<u32>,
    len: usize,
}

impl Buckets {
    fn new(span: usize) -> Self {
        Self {
            ring: vec![Vec::new(); span + 1],
            f: None,
            len: 0,
        }
    }

    fn push(&mut self, f: u32, cell: u32) {
        let at = *self.f.get_or_insert(f);
        debug_assert!(f >= at && ((f - at) as usize) < self.ring.len());
        let n = self.ring.len();
        self.ring[f as usize % n].push(cell);
        self.len += 1;
    }

    fn pop(&mut self) -> Option<(u32, u32)> {
        if self.len == 0 {
            return None;
        }
        let n = self.ring.len();
        let mut f = self.f?;
        loop {
            let b = &mut self.ring[f as usize % n];
            if let Some((k, _)) = b.iter().enumerate().min_by_key(|&(_, &c)| c) {
                let cell = b.swap_remove(k);
                self.len -= 1;
                self.f = Some(f);
                return Some((f, cell));
            }
            f += 1;
        }
    }
}

/// An A* search's open set: pops the least f, and among equal f the least cell.
trait Open {
    fn push(&mut self, f: u32, cell: u32);
    fn pop(&mut self) -> Option<(u32, u32)>;
}

impl Open for Buckets {
    fn push(&mut self, f: u32, cell: u32) {
        Buckets::push(self, f, cell);
    }

    fn pop(&mut self) -> Option<(u32, u32)> {
        Buckets::pop(self)
    }
}

/// For a search carried on towards another end, whose open f's span more than the buckets'.
impl Open for std::collections::BinaryHeap<std::cmp::Reverse<(u32, u32)>> {
    fn push(&mut self, f: u32, cell: u32) {
        std::collections::BinaryHeap::push(self, std::cmp::Reverse((f, cell)));
    }

    fn pop(&mut self) -> Option<(u32, u32)> {
        std::collections::BinaryHeap::pop(self).map(|std::cmp::Reverse(k)| k)
    }
}

/// A path search from one cell (`Grid::search`), kept to be read or carried on.
struct Search {
    from: usize,
    /// Where it was going: its target, or the thread farthest along from `from`.
    end: usize,
    /// Each cell's cost from `from` so far (final where settled).
    g: Vec<u32>,
    parent: Vec<u32>,
    /// The cells whose cost it made final; every one's way back to `from` is a cheapest path.
    settled: Vec<bool>,
}

impl Search {
    /// The cheapest path from the search's start to `to` (its own end without one), cells
    /// from the start; none if the search did not settle it.
    fn path_to(&self, to: Option<usize>) -> Option<Vec<usize>> {
        let end = to.unwrap_or(self.end);
        if !self.settled[end] {
            return None;
        }
        let mut out = vec![end];
        let mut i = end;
        while i != self.from {
            i = self.parent[i] as usize;
            out.push(i);
        }
        out.reverse();
        Some(out)
    }
}

struct Grid<'a> {
    w: usize,
    h: usize,
    mask: &'a [u8],
    gap: u32,
}

impl Grid<'_> {
    /// A step's cost into cell `i`: 5 along a row or column, 7 diagonally (≈ 5√2), times
    /// the gap cost off the thread.
    fn step(&self, i: usize, diagonal: bool) -> u32 {
        let base = if diagonal { 7 } else { 5 };
        if self.mask[i] != 0 {
            base
        } else {
            base * self.gap
        }
    }

    fn neighbours(&self, i: usize) -> impl Iterator<Item = (usize, bool)> + '_ {
        let (x, y) = ((i % self.w) as i64, (i / self.w) as i64);
        const D: [(i64, i64); 8] = [
            (-1, 0),
            (1, 0),
            (0, -1),
            (0, 1),
            (-1, -1),
            (1, -1),
            (-1, 1),
            (1, 1),
        ];
        D.iter().filter_map(move |&(dx, dy)| {
            let (nx, ny) = (x + dx, y + dy);
            (nx >= 0 && ny >= 0 && (nx as usize) < self.w && (ny as usize) < self.h)
                .then(|| (ny as usize * self.w + nx as usize, dx != 0 && dy != 0))
        })
    }

    /// The cheapest path from `from` to `to` (A*, the octile distance on thread as its
    /// heuristic), cells from `from`; without `to`, the path to the thread farthest from
    /// `from` along the thread (steps off it allowed only across gaps of a few pixels).
    fn path(&self, from: usize, to: Option<usize>) -> Vec<usize> {
        self.search(from, to)
            .path_to(None)
            .unwrap_or_else(|| vec![from])
    }

    /// The search behind `path`, kept: the paths to other cells it settled on the way come
    /// from it for nothing.
    fn search(&self, from: usize, to: Option<usize>) -> Search {
        let n = self.w * self.h;
        let mut s = Search {
            from,
            end: from,
            g: vec![u32::MAX; n],
            parent: vec![u32::MAX; n],
            settled: vec![false; n],
        };
        // A step costs at most 7·gap and moves the heuristic by at most 7: a new entry's f is
        // within that of the one popped.
        let mut open = Buckets::new(7 * self.gap as usize + 8);
        // Without an end: off the thread only within a few pixels of it (or of the swage).
        let near = if to.is_none() {
            Some(self.near_thread(4, from))
        } else {
            None
        };
        s.g[from] = 0;
        open.push(self.heuristic(to)(from), from as u32);
        let farthest = self.expand(&mut s, &mut open, to, near.as_deref());
        s.end = to.unwrap_or(farthest);
        s
    }

    /// The cheapest path from `s`'s start to `to`: read from `s` where it settled `to`,
    /// else `s` carried on until it does (its open set ordered again by the distance to
    /// `to`; what it settled stays settled). Cells from the start.
    fn path_via(&self, s: &mut Search, to: usize) -> Vec<usize> {
        if !s.settled[to] {
            let h = self.heuristic(Some(to));
            let mut open = std::collections::BinaryHeap::new();
            for (i, &g) in s.g.iter().enumerate() {
                if g != u32::MAX && !s.settled[i] {
                    open.push(std::cmp::Reverse((g + h(i), i as u32)));
                }
            }
            self.expand(s, &mut open, Some(to), None);
        }
        s.path_to(Some(to)).unwrap_or_else(|| vec![s.from])
    }

    /// The A* heuristic towards `to` (none without): the octile distance in on-thread
    /// steps, which no path beats (consistent).
    fn heuristic(&self, to: Option<usize>) -> impl Fn(usize) -> u32 + use<> {
        let w = self.w;
        let target = to.map(|t| (t % w, t / w));
        move |i: usize| {
            target.map_or(0, |(tx, ty)| {
                let (dx, dy) = ((i % w).abs_diff(tx) as u32, (i / w).abs_diff(ty) as u32);
                5 * dx.max(dy) + 2 * dx.min(dy)
            })
        }
    }

    /// A* from `s`'s state and `open` until `to` is settled or nothing is left open (`near`:
    /// the only cells it may enter); the thread cell settled farthest from the start along
    /// the way, which a search without an end goes to.
    fn expand(
        &self,
        s: &mut Search,
        open: &mut impl Open,
        to: Option<usize>,
        near: Option<&[bool]>,
    ) -> usize {
        let (w, hh) = (self.w as i64, self.h as i64);
        let h = self.heuristic(to);
        const D: [(i64, i64, bool); 8] = [
            (-1, 0, false),
            (1, 0, false),
            (0, -1, false),
            (0, 1, false),
            (-1, -1, true),
            (1, -1, true),
            (-1, 1, true),
            (1, 1, true),
        ];
        let mut farthest = s.from;
        while let Some((f, i)) = open.pop() {
            let i = i as usize;
            if f > s.g[i].saturating_add(h(i)) {
                continue;
            }
            // Popped with its own f: its cost is final (the heuristic is consistent).
            s.settled[i] = true;
            if to.is_none() && self.mask[i] != 0 && s.g[i] > s.g[farthest] {
                farthest = i;
            }
            let (x, y) = ((i % self.w) as i64, (i / self.w) as i64);
            for &(dx, dy, diag) in &D {
                let (nx, ny) = (x + dx, y + dy);
                if nx < 0 || ny < 0 || nx >= w || ny >= hh {
                    continue;
                }
                let j = (ny * w + nx) as usize;
                if near.is_some_and(|m| !m[j]) {
                    continue;
                }
                let c = s.g[i] + self.step(j, diag);
                if c < s.g[j] {
                    s.g[j] = c;
                    s.parent[j] = i as u32;
                    open.push(c + h(j), j as u32);
                }
            }
            // (Its neighbours seen first: every settled cell's are, which a search carried on
            // needs.)
            if Some(i) == to {
                break;
            }
        }
        farthest
    }

    /// Cells within `r` (Chebyshev) of thread or of `seed`.
    fn near_thread(&self, r: usize, seed: usize) -> Vec<bool> {
        let mut out = vec![false; self.w * self.h];
        let mark = |out: &mut Vec<bool>, i: usize, r: usize| {
            let (x, y) = (i % self.w, i / self.w);
            for yy in y.saturating_sub(r)..(y + r + 1).min(self.h) {
                for xx in x.saturating_sub(r)..(x + r + 1).min(self.w) {
                    out[yy * self.w + xx] = true;
                }
            }
        };
        for i in 0..self.w * self.h {
            if self.mask[i] != 0 {
                mark(&mut out, i, r);
            }
        }
        mark(&mut out, seed, 3 * r);
        out
    }

    /// Thread apart from a path: the 8-connected pieces of thread more than two cells from
    /// every cell of `path`, of `MIN_STRAND_CELLS` or more, the largest first; each as the
    /// cells from one of its ends to the other (the two farthest apart along it).
    fn strands(&self, path: &[usize]) -> Vec<Vec<usize>> {
        let n = self.w * self.h;
        // 0: free thread, 1: not thread or near the path, 2: taken into a piece.
        let mut state: Vec<u8> = self.mask.iter().map(|&m| u8::from(m == 0)).collect();
        for &i in path {
            let (x, y) = (i % self.w, i / self.w);
            for yy in y.saturating_sub(2)..(y + 3).min(self.h) {
                for xx in x.saturating_sub(2)..(x + 3).min(self.w) {
                    state[yy * self.w + xx] = 1;
                }
            }
        }
        let mut pieces: Vec<Vec<usize>> = Vec::new();
        for seed in 0..n {
            if state[seed] != 0 {
                continue;
            }
            state[seed] = 2;
            let mut piece = vec![seed];
            let mut k = 0;
            while k < piece.len() {
                let i = piece[k];
                k += 1;
                for (j, _) in self.neighbours(i) {
                    if state[j] == 0 {
                        state[j] = 2;
                        piece.push(j);
                    }
                }
            }
            if piece.len() >= MIN_STRAND_CELLS {
                pieces.push(piece);
            }
        }
        pieces.sort_by_key(|p| std::cmp::Reverse(p.len()));
        // Breadth first within a piece: the cell farthest from `from`, and the way there.
        let mut dist = vec![u32::MAX; n];
        let mut parent = vec![u32::MAX; n];
        let mut farthest = |piece: &[usize], from: usize| -> Vec<usize> {
            for &i in piece {
                dist[i] = u32::MAX;
            }
            dist[from] = 0;
            let mut queue = std::collections::VecDeque::from([from]);
            let mut last = from;
            while let Some(i) = queue.pop_front() {
                last = i;
                for (j, _) in self.neighbours(i) {
                    if state[j] == 2 && dist[j] == u32::MAX {
                        dist[j] = dist[i] + 1;
                        parent[j] = i as u32;
                        queue.push_back(j);
                    }
                }
            }
            let mut way = vec![last];
            while *way.last().unwrap_or(&from) != from {
                way.push(parent[way[way.len() - 1]] as usize);
            }
            way
        };
        pieces
            .iter()
            .map(|p| {
                let end = farthest(p, p[0])[0];
                farthest(p, end)
            })
            .collect()
    }

    /// Whether thread 8-connected to the path's thread cells touches the region's border.
    fn reaches_border(&self, path: &[usize], border: impl Fn(usize) -> bool) -> bool {
        let mut seen = vec![false; self.w * self.h];
        let mut stack: Vec<usize> = path
            .iter()
            .copied()
            .filter(|&i| self.mask[i] != 0)
            .collect();
        for &i in &stack {
            seen[i] = true;
        }
        while let Some(i) = stack.pop() {
            if border(i) {
                return true;
            }
            for (j, _) in self.neighbours(i) {
                if !seen[j] && self.mask[j] != 0 {
                    seen[j] = true;
                    stack.push(j);
                }
            }
        }
        false
    }
}

/// Follows a thread mask from one end: a step of `WALK_STEP_PX` at a time in the middle of
/// the directions that stay on the thread nearest straight on (so it runs down the
/// centreline, and through a crossing rather than round the corner), jumping gaps of up to
/// `WALK_GAP_PX` ahead. Unlike a cheapest path it keeps to loops the thread makes instead of
/// cutting across where the thread touches itself.
struct Walker<'a> {
    mask: &'a [u8],
    w: usize,
    h: usize,
}

/// The walk's trail around each point it passes: the thread's width.
const BRUSH: [(f64, f64); 13] = [
    (0.0, 0.0),
    (1.0, 0.0),
    (-1.0, 0.0),
    (0.0, 1.0),
    (0.0, -1.0),
    (1.0, 1.0),
    (1.0, -1.0),
    (-1.0, 1.0),
    (-1.0, -1.0),
    (2.0, 0.0),
    (-2.0, 0.0),
    (0.0, 2.0),
    (0.0, -2.0),
];
/// The walk's step, pixels.
const WALK_STEP_PX: f64 = 3.0;
/// The widest gap the walk jumps, pixels.
const WALK_GAP_PX: f64 = 24.0;
/// The most the walk turns in one step, rad.
const WALK_TURN: f64 = 1.05;
/// A walk's mark on a pixel it has passed.
const TRAIL: u8 = 0x80;
/// The most it turns at a kink, rad (172°: a hairpin's strands 8° apart).
const KINK_TURN: f64 = 3.0;

impl Walker<'_> {
    fn on(&self, x: f64, y: f64) -> bool {
        let (xi, yi) = (x.floor() as i64, y.floor() as i64);
        xi >= 0
            && yi >= 0
            && (xi as usize) < self.w
            && (yi as usize) < self.h
            && self.mask[yi as usize * self.w + xi as usize] != 0
    }

    /// The thread pixel nearest `p` within `r` pixels, as its centre.
    fn nearest(&self, p: (f64, f64), r: i64) -> Option<(f64, f64)> {
        let (px, py) = (p.0.floor() as i64, p.1.floor() as i64);
        let mut best: Option<((f64, f64), f64)> = None;
        for y in py - r..=py + r {
            for x in px - r..=px + r {
                let c = (x as f64 + 0.5, y as f64 + 0.5);
                if self.on(c.0, c.1) {
                    let d = (c.0 - p.0).hypot(c.1 - p.1);
                    if best.is_none_or(|(_, b)| d < b) {
                        best = Some((c, d));
                    }
                }
            }
        }
        best.map(|(c, _)| c)
    }

    /// Share of the segment from `p`, `len` pixels at angle `a`, that is thread.
    fn coverage(&self, p: (f64, f64), a: f64, len: f64) -> f64 {
        let n = len.ceil().max(1.0) as usize;
        (1..=n)
            .filter(|&k| {
                let t = len * k as f64 / n as f64;
                self.on(p.0 + t * a.cos(), p.1 + t * a.sin())
            })
            .count() as f64
            / n as f64
    }

    /// The walk from `start`, setting out towards `ahead` (or along the thread), to `goal` (pixels of the region):
    /// points about a pixel apart and whether each is on the thread. It ends at `goal` when it comes within a few
    /// pixels of it, or where it loses the thread.
    fn walk(
        &self,
        start: (f64, f64),
        ahead: Option<(f64, f64)>,
        goal: (f64, f64),
        cells: &mut Vec<u8>,
    ) -> Vec<(f64, f64, bool)> {
        let Some(mut p) = self.nearest(start, 8) else {
            return vec![(start.0, start.1, false)];
        };
        let mut out = vec![(start.0, start.1, self.on(start.0, start.1))];
        // The first direction: towards `ahead`, or the longest run of thread from the start
        // (towards the goal when two are as long).
        let to_goal = (goal.1 - p.1).atan2(goal.0 - p.0);
        let mut dir = match ahead {
            Some(a) => (a.1 - p.1).atan2(a.0 - p.0),
            None => (0..48)
                .map(|k| f64::from(k) * std::f64::consts::TAU / 48.0)
                .max_by(|a, b| {
                    let score = |x: f64| self.coverage(p, x, 12.0) + 0.01 * (x - to_goal).cos();
                    score(*a).total_cmp(&score(*b))
                })
                .unwrap_or(to_goal),
        };
        let goal_r = 4.0 * WALK_STEP_PX;
        let budget = (20 * (self.w + self.h)) as f64 / WALK_STEP_PX * 4.0;
        // Per pixel: how often a step landed on it (the low bits), and whether the walk has
        // passed it (`TRAIL`, so that a sharp turn does not lead back). The caller's buffer,
        // cleared: walks one after another reuse its memory.
        cells.clear();
        cells.resize(self.w * self.h, 0);
        let trail = cells;
        let index = |x: f64, y: f64| -> Option<usize> {
            (x >= 0.0 && y >= 0.0 && (x as usize) < self.w && (y as usize) < self.h)
                .then(|| y as usize * self.w + x as usize)
        };
        let push =
            |out: &mut Vec<(f64, f64, bool)>, trail: &mut Vec<u8>, q: (f64, f64), gap: bool| {
                let &(x0, y0, _) = out.last().expect("a first point");
                let n = (q.0 - x0).hypot(q.1 - y0).ceil().max(1.0) as usize;
                for k in 1..=n {
                    let t = k as f64 / n as f64;
                    let (x, y) = (x0 + t * (q.0 - x0), y0 + t * (q.1 - y0));
                    out.push((x, y, if gap && k < n { false } else { self.on(x, y) }));
                    // A brush as wide as the thread, so that a sharp turn cannot lead back
                    // along the thread's other edge.
                    for (dx, dy) in BRUSH {
                        if let Some(i) = index(x + dx, y + dy) {
                            trail[i] |= TRAIL;
                        }
                    }
                }
            };
        push(&mut out, trail, p, false);
        let mut steps = 0.0;
        while steps < budget {
            steps += 1.0;
            if (p.0 - goal.0).hypot(p.1 - goal.1) < goal_r {
                push(&mut out, trail, goal, !self.on(goal.0, goal.1));
                return out;
            }
            // Directions within the turn limit, in order, and whether each stays on thread.
            const N: i32 = 14;
            let angles: Vec<f64> = (-N..=N)
                .map(|k| dir + WALK_TURN * f64::from(k) / f64::from(N))
                .collect();
            let ok: Vec<bool> = angles
                .iter()
                .map(|&a| self.on(p.0 + WALK_STEP_PX * a.cos(), p.1 + WALK_STEP_PX * a.sin()))
                .collect();
            // The run of good directions nearest straight on; its middle.
            let mut best: Option<(usize, usize, i32)> = None;
            let mut k = 0;
            while k < ok.len() {
                if !ok[k] {
                    k += 1;
                    continue;
                }
                let a = k;
                while k < ok.len() && ok[k] {
                    k += 1;
                }
                let b = k - 1;
                let off = if a as i32 <= N && N <= b as i32 {
                    0
                } else {
                    (a as i32 - N).abs().min((b as i32 - N).abs())
                };
                if best.is_none_or(|(_, _, o)| off < o) {
                    best = Some((a, b, off));
                }
            }
            let next = match best {
                Some((a, b, _)) => {
                    let a = (angles[a] + angles[b]) / 2.0;
                    Some((a, WALK_STEP_PX, false))
                }
                // No thread a step away within the turn: a sharp bend (a kink, the thread
                // doubling back beside itself) onto thread the walk has not passed, 9 to 18 px
                // on (a hairpin's strands part slowly from its bend), the nearest and least
                // turn first; else the nearest thread ahead across a gap.
                None => (3..=6)
                    .flat_map(|m| {
                        (1..=16).flat_map(move |k| {
                            let t = WALK_TURN + (KINK_TURN - WALK_TURN) * f64::from(k) / 16.0;
                            [
                                (dir + t, WALK_STEP_PX * f64::from(m)),
                                (dir - t, WALK_STEP_PX * f64::from(m)),
                            ]
                        })
                    })
                    .find(|&(a, d)| {
                        let (x, y) = (p.0 + d * a.cos(), p.1 + d * a.sin());
                        self.on(x, y) && index(x, y).is_some_and(|i| trail[i] & TRAIL == 0)
                    })
                    .map(|(a, d)| (a, d, false))
                    .or_else(|| {
                        (2..=(WALK_GAP_PX / WALK_STEP_PX) as i32)
                            .flat_map(|m| {
                                (-4..=4).map(move |k| {
                                    (dir + 0.35 * f64::from(k) / 4.0, WALK_STEP_PX * f64::from(m))
                                })
                            })
                            .find(|&(a, d)| self.on(p.0 + d * a.cos(), p.1 + d * a.sin()))
                            .map(|(a, d)| (a, d, true))
                    }),
            };
            let Some((a, d, gap)) = next else {
                break;
            };
            let q = (p.0 + d * a.cos(), p.1 + d * a.sin());
            // Round a closed loop too often: lost.
            let (qx, qy) = (q.0.floor() as usize, q.1.floor() as usize);
            if qx < self.w && qy < self.h {
                let v = &mut trail[qy * self.w + qx];
                *v += 1;
                if *v & !TRAIL > 3 {
                    break;
                }
            }
            push(&mut out, trail, q, gap);
            dir = a;
            p = q;
        }
        out
    }
}

/// The right view's thread mask over `roi`, refused when it holds too little thread.
fn right_mask(
    segmenter: &dyn Segmenter,
    right: &RgbImage,
    roi: Rect,
) -> Result<Vec<u8>, PerceptionError> {
    let mask = segmenter.thread_mask(right, roi)?;
    if mask.iter().filter(|&&v| v != 0).count() < 20 {
        return Err(PerceptionError::NoThread {
            view: "right".into(),
        });
    }
    Ok(mask)
}

/// The part of the right view's `band` that [`View::runs`] reads for the left crossings
/// `rows_crossed` (`(t, x, row)`), cut on the segmenter's grid of `block`-pixel blocks laid
/// from the band's corner, with a block to spare all round (see
/// [`Segmenter::thread_mask_block_px`]), so that the mask there is the band's. A run
/// reaching past the search's right end is followed until it ends or is too long
/// (`MAX_RUN_PX`): so many columns more. Empty when nothing was crossed.
fn read_region(
    band: Rect,
    rows_crossed: &[(f64, f64, u32)],
    disparity: [f64; 2],
    block: u32,
) -> Rect {
    let (mut lo, mut hi) = (i64::MAX, i64::MIN);
    let (mut top, mut bottom) = (u32::MAX, 0);
    for &(_, xl, row) in rows_crossed {
        lo = lo.min((xl - disparity[1]).floor() as i64);
        hi = hi.max((xl - disparity[0]).ceil() as i64 + MAX_RUN_PX + 1);
        top = top.min(row);
        bottom = bottom.max(row + 1);
    }
    if rows_crossed.is_empty() {
        return Rect {
            x1: band.x0,
            y1: band.y0,
            ..band
        };
    }
    let b = i64::from(block.max(1));
    // Down to the start of the block before the first one read; up to the end of the block
    // after the last one; within the band.
    let down = |v: i64, origin: u32| {
        let o = i64::from(origin);
        (o + ((v - o).max(0) / b - 1) * b).max(o) as u32
    };
    let up = |v: i64, origin: u32, end: u32| {
        let o = i64::from(origin);
        (o + ((v - o).max(0) + b - 1) / b * b + b)
            .min(i64::from(end))
            .max(o) as u32
    };
    Rect {
        x0: down(lo, band.x0),
        y0: down(i64::from(top), band.y0),
        x1: up(hi, band.x0, band.x1),
        y1: up(i64::from(bottom), band.y0, band.y1),
    }
}

/// One view's image and thread mask over a region.
struct View<'a> {
    image: &'a RgbImage,
    roi: Rect,
    mask: &'a [u8],
}

/// The longest run of thread along a row the tracer takes as a crossing, pixels.
const MAX_RUN_PX: i64 = 12;

impl View<'_> {
    fn on(&self, x: i64, y: u32) -> bool {
        let r = &self.roi;
        x >= i64::from(r.x0)
            && x < i64::from(r.x1)
            && y >= r.y0
            && y < r.y1
            && self.mask[((y - r.y0) * r.width()) as usize + (x - i64::from(r.x0)) as usize] != 0
    }

    /// How violet a pixel is: blue over the mean of red and green, levels (0 outside).
    fn weight(&self, x: i64, y: u32) -> f64 {
        if x < 0 || x >= i64::from(self.image.width) || y >= self.image.height {
            return 0.0;
        }
        let i = (y as usize * self.image.width as usize + x as usize) * 3;
        let p = &self.image.data[i..i + 3];
        f64::from(p[2]) - (f64::from(p[0]) + f64::from(p[1])) / 2.0
    }

    /// The run of thread on row `y` through column `x`: first and last columns.
    fn run(&self, x: i64, y: u32) -> Option<(i64, i64)> {
        if !self.on(x, y) {
            return None;
        }
        let (mut a, mut b) = (x, x);
        while self.on(a - 1, y) && x - a < MAX_RUN_PX {
            a -= 1;
        }
        while self.on(b + 1, y) && b - x < MAX_RUN_PX {
            b += 1;
        }
        (b - a < MAX_RUN_PX).then_some((a, b))
    }

    /// The sub-pixel centre of a run on row `y`: columns weighted by how violet they are
    /// above the row's background beside the run (pixel centres at +0.5).
    fn centre(&self, a: i64, b: i64, y: u32) -> f64 {
        let bg = self.weight(a - 2, y).min(self.weight(b + 2, y));
        let (mut sw, mut sx) = (0.0, 0.0);
        for x in a - 1..=b + 1 {
            let w = (self.weight(x, y) - bg).max(0.0);
            sw += w;
            sx += w * (x as f64 + 0.5);
        }
        if sw > 0.0 {
            sx / sw
        } else {
            (a + b) as f64 / 2.0 + 0.5
        }
    }

    /// The sub-pixel row centre of the run of thread down column `x` through row `y`.
    fn column_centre(&self, x: i64, y: u32) -> Option<f64> {
        let (mut a, mut b) = (y, y);
        while a > 0 && self.on(x, a - 1) && y - a < MAX_RUN_PX as u32 {
            a -= 1;
        }
        while self.on(x, b + 1) && b - y < MAX_RUN_PX as u32 {
            b += 1;
        }
        if b - a >= MAX_RUN_PX as u32 {
            return None;
        }
        let (mut sw, mut sy) = (0.0, 0.0);
        let bg = self
            .weight(x, a.saturating_sub(2))
            .min(self.weight(x, b + 2));
        for yy in a.saturating_sub(1)..=b + 1 {
            let w = (self.weight(x, yy) - bg).max(0.0);
            sw += w;
            sy += w * (f64::from(yy) + 0.5);
        }
        Some(if sw > 0.0 {
            sy / sw
        } else {
            f64::from(a + b) / 2.0 + 0.5
        })
    }

    /// The centres of the runs on row `y` between columns `lo` and `hi`.
    fn runs(&self, lo: f64, hi: f64, y: u32) -> Vec<f64> {
        let (lo, hi) = (lo.floor() as i64, hi.ceil() as i64);
        let mut out = Vec::new();
        let mut c = lo.max(i64::from(self.roi.x0));
        let hi = hi.min(i64::from(self.roi.x1) - 1);
        while c <= hi {
            if self.on(c, y) {
                let a = c;
                while self.on(c + 1, y) {
                    c += 1;
                }
                if c - a < MAX_RUN_PX {
                    out.push(self.centre(a, c, y));
                }
            }
            c += 1;
        }
        out
    }
}

/// A spline's value from the four basis functions non-zero at a point: the first's index
/// and their values.
fn dot(coef: &DVector<f64>, i: usize, w: &[f64; 4]) -> f64 {
    (0..4).map(|k| w[k] * coef[i + k]).sum()
}

/// Observations ready for fits at several smoothings (`Basis::prepare`).
struct Prepared {
    /// The data's part of the normal matrix (band, lower) and right-hand side.
    a: LowerBand,
    rhs: Vec<f64>,
    /// Each observation's first basis function and the four values there.
    weights: Vec<(usize, [f64; 4])>,
    /// The observations, `(t, value, σ)`.
    obs: Vec<(f64, f64, f64)>,
}

/// A uniform cubic B-spline basis of `count` functions over `[0, span]`.
struct Basis {
    count: usize,
    span: f64,
}

/// One axis's fitted spline: coefficients, its normal matrix's Cholesky factor (whose
/// inverse, scaled, is the posterior covariance of the coefficients, in the observations'
/// units; its band, all a pointwise variance reads, is worked out when first asked for,
/// since most fits are only looked at for their curve) and its χ².
struct Fit {
    coef: DVector<f64>,
    chol: BandCholesky,
    /// The covariance's scale: the reduced χ² where it exceeds 1.
    scale: f64,
    cov: std::cell::OnceCell<LowerBand>,
    chi2: f64,
}

impl Fit {
    fn variance(&self, b: &Basis, t: f64) -> f64 {
        let cov = self.cov.get_or_init(|| self.chol.inverse_band());
        let (i, w) = b.weights(t);
        let mut v = 0.0;
        for (a, wa) in w.iter().enumerate() {
            for (c, wc) in w.iter().enumerate() {
                v += wa * wc * band::at(cov, i + a, i + c);
            }
        }
        (v * self.scale).max(0.0)
    }
}

impl Basis {
    /// The first of the four functions non-zero at `t`, and their values.
    fn weights(&self, t: f64) -> (usize, [f64; 4]) {
        let segments = (self.count - 3) as f64;
        let s = (t / self.span).clamp(0.0, 1.0) * segments;
        let i = (s.floor() as usize).min(self.count - 4);
        let u = s - i as f64;
        let u2 = u * u;
        let u3 = u2 * u;
        (
            i,
            [
                (1.0 - u).powi(3) / 6.0,
                (3.0 * u3 - 6.0 * u2 + 4.0) / 6.0,
                (-3.0 * u3 + 3.0 * u2 + 3.0 * u + 1.0) / 6.0,
                u3 / 6.0,
            ],
        )
    }

    fn eval(&self, coef: &DVector<f64>, t: f64) -> f64 {
        let (i, w) = self.weights(t);
        dot(coef, i, &w)
    }

    /// `(t, value, sigma)` observations' weights and the data's part of the normal
    /// equations.
    fn prepare(&self, obs: Vec<(f64, f64, f64)>) -> Prepared {
        let n = self.count;
        let mut a: LowerBand = vec![[0.0; band::HALF_BANDWIDTH + 1]; n];
        let mut rhs = vec![0.0; n];
        let mut weights = Vec::with_capacity(obs.len());
        for &(t, y, s) in &obs {
            let (i, w) = self.weights(t);
            let wt = 1.0 / (s * s).max(1e-12);
            for p in 0..4 {
                rhs[i + p] += wt * w[p] * y;
                for q in 0..=p {
                    a[i + p][p - q] += wt * w[p] * w[q];
                }
            }
            weights.push((i, w));
        }
        Prepared {
            a,
            rhs,
            weights,
            obs,
        }
    }

    /// Penalised least squares: `(t, value, sigma)` observations, `smoothing` on the
    /// coefficients' second differences.
    fn fit(&self, obs: &[(f64, f64, f64)], smoothing: f64) -> Option<Fit> {
        self.fit_prepared(&self.prepare(obs.to_vec()), smoothing)
    }

    /// `fit` from prepared observations.
    fn fit_prepared(&self, prepared: &Prepared, smoothing: f64) -> Option<Fit> {
        let n = self.count;
        let mut a = prepared.a.clone();
        let rhs = &prepared.rhs;
        let d = [1.0, -2.0, 1.0];
        for k in 0..n - 2 {
            for p in 0..3 {
                for q in 0..=p {
                    a[k + p][p - q] += smoothing * d[p] * d[q];
                }
            }
        }
        let chol = BandCholesky::factor(a)?;
        let coef = DVector::from_vec(chol.solve(rhs));
        let chi2: f64 = prepared
            .weights
            .iter()
            .zip(&prepared.obs)
            .map(|(&(i, w), &(_, y, s))| {
                let r = (dot(&coef, i, &w) - y) / s.max(1e-12);
                r * r
            })
            .sum();
        // Residuals larger than the stated uncertainties say the uncertainties were too
        // small: scale the covariance by the reduced χ² when it exceeds 1.
        let dof = prepared.obs.len().saturating_sub(n / 2).max(1) as f64;
        Some(Fit {
            coef,
            chol,
            scale: (chi2 / dof).max(1.0),
            cov: std::cell::OnceCell::new(),
            chi2,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The buckets pop what a binary heap of (f, cell) would, stale duplicates included, on
    /// any sequence an A* with a consistent heuristic makes (each push at most `span` above
    /// the last pop's f, never below it).
    #[test]
    fn the_buckets_pop_in_the_binary_heaps_order() {
        use rand::Rng;
        use rand_chacha::ChaCha8Rng;
        use rand_chacha::rand_core::SeedableRng;
        use std::cmp::Reverse;
        use std::collections::BinaryHeap;
        for seed in 0..200u64 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let span = rng.random_range(1..70usize);
            let mut buckets = Buckets::new(span);
            let mut heap = BinaryHeap::new();
            let mut last = rng.random_range(0..1000u32);
            let (f0, c0) = (last, rng.random_range(0..50u32));
            buckets.push(f0, c0);
            heap.push(Reverse((f0, c0)));
            for _ in 0..400 {
                for _ in 0..rng.random_range(0..4) {
                    let f = last + rng.random_range(0..=span as u32);
                    let c = rng.random_range(0..50u32);
                    buckets.push(f, c);
                    heap.push(Reverse((f, c)));
                }
                let want = heap.pop().map(|Reverse(k)| k);
                assert_eq!(buckets.pop(), want, "seed {seed}");
                match want {
                    Some((f, _)) => last = f,
                    None => break,
                }
            }
        }
    }

    /// A path read from a search made for another target, to any cell that search settled,
    /// costs what a search of its own finds: it is a cheapest path too; and so does one
    /// from a search carried on to new ends, one after another.
    #[test]
    fn a_settled_cells_path_from_another_search_is_a_cheapest_path() {
        use rand::Rng;
        use rand_chacha::ChaCha8Rng;
        use rand_chacha::rand_core::SeedableRng;
        let mut reused = 0;
        for seed in 0..60u64 {
            let mut rng = ChaCha8Rng::seed_from_u64(seed);
            let (w, h) = (rng.random_range(5..40usize), rng.random_range(5..40usize));
            let mask: Vec<u8> = (0..w * h).map(|_| u8::from(rng.random_bool(0.4))).collect();
            let grid = Grid {
                w,
                h,
                mask: &mask,
                gap: rng.random_range(1..10u32),
            };
            let cost = |path: &[usize]| -> u32 {
                path.windows(2)
                    .map(|q| {
                        let (dx, dy) =
                            ((q[0] % w).abs_diff(q[1] % w), (q[0] / w).abs_diff(q[1] / w));
                        assert!(dx <= 1 && dy <= 1 && dx + dy > 0, "not a step: {q:?}");
                        grid.step(q[1], dx + dy == 2)
                    })
                    .sum()
            };
            let from = rng.random_range(0..w * h);
            let search = grid.search(from, Some(rng.random_range(0..w * h)));
            for to in 0..w * h {
                let Some(p) = search.path_to(Some(to)) else {
                    continue;
                };
                reused += 1;
                let own = grid.path(from, Some(to));
                assert_eq!((p[0], p[p.len() - 1]), (from, to));
                assert_eq!(cost(&p), cost(&own), "seed {seed}, {from} → {to}");
            }
            let mut carried = search;
            for _ in 0..5 {
                let to = rng.random_range(0..w * h);
                let p = grid.path_via(&mut carried, to);
                let own = grid.path(from, Some(to));
                assert_eq!((p[0], p[p.len() - 1]), (from, to));
                assert_eq!(
                    cost(&p),
                    cost(&own),
                    "seed {seed}, {from} → {to}, carried on"
                );
            }
        }
        assert!(reused > 1000, "{reused}");
    }

    #[test]
    fn the_basis_sums_to_one_and_fits_a_line_exactly() {
        let b = Basis {
            count: 10,
            span: 100.0,
        };
        for t in [0.0, 3.3, 50.0, 99.9, 100.0] {
            let (_, w) = b.weights(t);
            assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12);
        }
        let obs: Vec<_> = (0..=50)
            .map(|k| {
                let t = 2.0 * k as f64;
                (t, 3.0 + 0.5 * t, 0.3)
            })
            .collect();
        let f = b.fit(&obs, 10.0).expect("fits");
        for t in [0.0, 17.0, 64.0, 100.0] {
            assert!((b.eval(&f.coef, t) - (3.0 + 0.5 * t)).abs() < 1e-6, "{t}");
        }
        // Where there is no data, the fit is less sure.
        let gappy: Vec<_> = obs
            .iter()
            .filter(|o| !(30.0..70.0).contains(&o.0))
            .copied()
            .collect();
        let g = b.fit(&gappy, 10.0).expect("fits");
        assert!(g.variance(&b, 50.0) > 3.0 * g.variance(&b, 10.0));
    }

    proptest::proptest! {
        /// A splice keeps the path's two ends, takes in the whole strand in its order (or
        /// reversed), and adds nothing off the thread but its two bridges.
        #[test]
        fn a_splice_keeps_the_ends_and_takes_in_the_whole_strand(
            path in proptest::collection::vec((0.0..100.0f64, 0.0..100.0f64), 1..30),
            strand in proptest::collection::vec((0.0..100.0f64, 0.0..100.0f64), 1..20),
        ) {
            let path: Vec<(f64, f64, bool)> = path.into_iter().map(|(x, y)| (x, y, true)).collect();
            let strand: Vec<(f64, f64, bool)> =
                strand.into_iter().map(|(x, y)| (x, y, true)).collect();
            // Bridges as their two ends and a point half way, off the thread.
            let bridge = |a: (f64, f64, bool), b: (f64, f64, bool)| {
                vec![a, ((a.0 + b.0) / 2.0, (a.1 + b.1) / 2.0, false), b]
            };
            let out = splice(&path, strand.clone(), bridge);
            proptest::prop_assert_eq!(out[0], path[0]);
            let (first, last) = (out[out.len() - 1], path[path.len() - 1]);
            proptest::prop_assert_eq!((first.0, first.1), (last.0, last.1));
            let on: Vec<(f64, f64, bool)> = out.iter().copied().filter(|q| q.2).collect();
            let mut back = strand.clone();
            back.reverse();
            let holds = |s: &[(f64, f64, bool)]| {
                on.windows(s.len()).any(|w| w == s)
            };
            proptest::prop_assert!(holds(&strand) || holds(&back), "{:?}", out);
            proptest::prop_assert_eq!(on.len(), out.len() - 2);
        }

        /// The right view's mask cut to where the crossings read it gives every crossing the
        /// runs the whole band's mask gives: rows of colours in runs of 1 to 30 pixels (thread
        /// runs longer than `MAX_RUN_PX` included), any band, any crossings.
        #[test]
        fn the_read_region_gives_the_bands_runs(
            seed in 0u64..1_000_000,
            band in (0u32..60, 0u32..40, 20u32..200, 10u32..80),
            crossings in proptest::collection::vec((0.0f64..260.0, 0u32..120), 0..12),
            d in (0.0f64..40.0, 0.0f64..60.0),
        ) {
            use rand::Rng;
            use rand_chacha::rand_core::SeedableRng;
            let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
            let (w, h) = (260u32, 120u32);
            let mut image = RgbImage { width: w, height: h, data: Vec::with_capacity((w * h * 3) as usize) };
            for _ in 0..h {
                let mut x = 0;
                while x < w {
                    let len = rng.random_range(1..=30).min(w - x);
                    // Any colour: the contrast rule (against the surroundings' mean)
                    // decides as often as the fixed one.
                    let base = [rng.random_range(40..200u8), rng.random_range(30..160u8), rng.random_range(40..200u8)];
                    for _ in 0..len {
                        let n = rng.random_range(0..30u8);
                        image.data.extend_from_slice(&[base[0] + n, base[1] + n, base[2] + n]);
                    }
                    x += len;
                }
            }
            let band = Rect {
                x0: band.0,
                y0: band.1,
                x1: (band.0 + band.2).min(w),
                y1: (band.1 + band.3).min(h),
            };
            let disparity = [d.0, d.0 + d.1];
            let rows: Vec<(f64, f64, u32)> = crossings
                .iter()
                .filter(|c| c.1 >= band.y0 && c.1 < band.y1)
                .map(|&(x, row)| (0.0, x, row))
                .collect();
            let seg = crate::ColorSegmenter::default();
            let block = seg.thread_mask_block_px().expect("the colour segmenter's mask is local");
            let part = read_region(band, &rows, disparity, block);
            proptest::prop_assert!(
                part.x0 >= band.x0 && part.y0 >= band.y0 && part.x1 <= band.x1 && part.y1 <= band.y1
            );
            let whole = seg.thread_mask(&image, band).expect("mask");
            let cut = if part.is_empty() { Vec::new() } else { seg.thread_mask(&image, part).expect("mask") };
            let (a, b) = (
                View { image: &image, roi: band, mask: &whole },
                View { image: &image, roi: part, mask: &cut },
            );
            for &(_, xl, row) in &rows {
                let lo = xl - disparity[1];
                let hi = xl - disparity[0];
                proptest::prop_assert_eq!(a.runs(lo, hi, row), b.runs(lo, hi, row), "row {}", row);
            }
        }
    }

    /// A thread hidden behind a span, as long as the trace's shortfall allows, lies within
    /// 2σ of the trace wherever it runs: points drawn inside the ellipsoid whose foci are the
    /// span's ends (every point of such a thread is), each against the trace's nearest point
    /// and the σ there; a trace as long as the most there can be keeps its σ.
    #[test]
    fn the_band_over_a_hidden_span_holds_any_thread_the_shortfall_allows() {
        use rand::Rng;
        use rand_chacha::ChaCha8Rng;
        use rand_chacha::rand_core::SeedableRng;
        // A straight trace 100 mm long, a point every 3 mm, hidden from 30 to 51 mm.
        let points: Vec<Point> = (0..=33)
            .map(|i| Point::new(0.003 * f64::from(i), 0.0, 0.0))
            .collect();
        let trace = ThreadTrace {
            sigma_m: vec![0.0002; points.len()],
            length_m: 0.099,
            hidden: vec![[0.0299, 0.0511]],
            seen_share: 0.8,
            matched: 20,
            left_path_px: vec![],
            points,
        };
        let mut same = trace.clone();
        widen_hidden(&mut same, 0.099);
        assert_eq!(same, trace, "a trace not short keeps its σ");
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        for excess in [0.002, 0.01, 0.04] {
            let mut t = trace.clone();
            widen_hidden(&mut t, trace.length_m + excess);
            assert_eq!(
                (t.sigma_m[0], t.sigma_m[33]),
                (0.0002, 0.0002),
                "past the ellipse the fit's σ stays"
            );
            let (f1, f2) = (Point::new(0.030, 0.0, 0.0), Point::new(0.051, 0.0, 0.0));
            let reach = 0.021 + excess;
            let mut tried = 0;
            while tried < 5000 {
                let p = Point::new(
                    rng.random_range(0.0..0.1),
                    rng.random_range(-0.03..0.03),
                    rng.random_range(-0.03..0.03),
                );
                if (p - f1).norm() + (p - f2).norm() > reach {
                    continue;
                }
                tried += 1;
                let (_, d, sigma) = t.nearest(&p).expect("a trace");
                assert!(
                    d <= 2.0 * sigma + 1e-12,
                    "{p:?}, excess {excess}: {d} from the trace, σ {sigma}"
                );
            }
            // And not wider than it: the middle's σ is half the ellipse's semi-minor axis.
            let middle = t.sigma_m[13..=17].iter().copied().fold(0.0, f64::max);
            let semi_minor = ((reach / 2.0).powi(2) - (0.021f64 / 2.0).powi(2)).sqrt();
            assert!(
                (middle - 0.5 * semi_minor).abs() < 1e-9,
                "{middle} against {semi_minor}"
            );
        }
    }
}
