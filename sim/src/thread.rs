//! The suture thread as a chain of short segments of fixed length, relaxed by position-based
//! dynamics (PBD) as the world moves.
//!
//! Why PBD, and quasi-static: a suture thread is light, limp and inextensible, and on a
//! dVRK (mm/s to cm/s) its inertia does not matter: where it lies follows from where its
//! ends are held, gravity, what it rests on and what pushes it. PBD keeps every segment's
//! length exactly (a projection, not a stiff spring), handles contact and friction as
//! projections too, and costs a few microseconds per relaxation; a discrete elastic rod would
//! add bending and twist that a braided suture barely has, at many times the cost. The chain
//! is relaxed a few iterations every 1.5 mm of every arm motion (less than a blade's
//! thickness, so no link slips through one) and more when a motion ends: the thread lags the
//! world by a millimetre or two, never by a motion.
//!
//! The thread in pieces:
//! - the **free** chain, from where it leaves the suture line (the last stitch's exit, or the
//!   tail's stopper knot before the first stitch) to the needle's swage;
//! - the **loop** of the stitch being made, once the needle is out of the tissue: from the
//!   previous stitch's exit (or the tail's knot) to this stitch's entry, a chain lying over
//!   the wound until the next needle goes in;
//! - the earlier stitches: each its path through the tissue and its loop's length (no
//!   longer simulated: they lie along the suture line).
//!
//! Pulling the free chain taut draws thread through the stitches: out of the open loop's
//! slack first, then out of the earlier loops', newest first, and last out of the tail until
//! its knot reaches the first entry (modelling choice: the phantom lets thread slide through
//! every stitch; `ThreadConfig::slides_through` holds slack behind more than so many). A
//! cinch does this on purpose; any motion that carries the needle away does it too. When no
//! slack is left anywhere, the thread is short.
//!
//! What happens to it is decided by its geometry: a closing jaw whose blades come within the
//! catch radius of a link catches it; a tool's blades, wrist and shaft push it (so an open
//! jaw sweeping the tissue drags the links in its way); a link hanging over a tool with the
//! chain turning round it tangles it; when the free chain is pulled taut and its loop has no
//! slack left, it is short. The only chance is which side the slack falls to when a needle
//! goes through (the seed's `Thread` stream).

use crate::SimError;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use stitch_robot::{Point, Pose, Vector};

/// The thread model's parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ThreadConfig {
    /// Thread length at the start (the paper's threads: 10–40 cm), m.
    pub length_m: f64,
    /// Length of one link of the chain (modelling choice: 2 mm), m.
    pub segment_m: f64,
    /// The thread's radius (a 3-0 suture: about 0.15 mm), m.
    pub radius_m: f64,
    /// A closing jaw catches thread whose links come within this distance of its closed
    /// blades' axis: between the blades (modelling choice: 1.2 mm, a large needle driver's
    /// jaw half-width plus the thread's radius), m.
    pub catch_radius_m: f64,
    /// Thread within this distance of the needle's tip or centre hides it from the camera
    /// (modelling choice), m.
    pub occlusion_radius_m: f64,
    /// Friction of thread resting on tissue: it slides only when pulled harder than this
    /// coefficient times its weight (static; modelling choice 0.8).
    pub friction: f64,
    /// When a needle goes through, the free thread's slack falls this far, at its middle,
    /// to a side drawn from the seed (modelling choice: 2 cm), m.
    pub slack_fall_m: f64,
    /// PBD iterations every 1.5 mm of a tool's travel (modelling choice: 2; 15 when a
    /// motion ends).
    pub iterations: u32,
    /// How many stitches a pull can draw thread through: slack in a loop behind more
    /// stitches than this stays there, held by the tissue's friction along their paths
    /// (modelling choice: 1,000, every stitch; 1 or 2 run the paper's cinch schedule short,
    /// docs/experiments.md).
    pub slides_through: u32,
}

impl Default for ThreadConfig {
    fn default() -> Self {
        Self {
            length_m: 0.30,
            segment_m: 0.002,
            radius_m: 0.00015,
            catch_radius_m: 0.0012,
            occlusion_radius_m: 0.004,
            friction: 0.8,
            slack_fall_m: 0.02,
            iterations: 2,
            slides_through: 1000,
        }
    }
}

impl ThreadConfig {
    /// Refuse parameters no thread has.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |what: &str, v: f64, range: &str| {
            Err(SimError::Config {
                what: format!("thread.{what}"),
                why: format!("{v}; expected {range}"),
            })
        };
        if !(self.length_m.is_finite() && (0.05..=1.0).contains(&self.length_m)) {
            return bad("length_m", self.length_m, "0.05 to 1.0 m");
        }
        if !(self.segment_m.is_finite() && (0.0005..=0.01).contains(&self.segment_m)) {
            return bad("segment_m", self.segment_m, "0.5 to 10 mm");
        }
        if self.length_m / self.segment_m > 2000.0 {
            return bad(
                "segment_m",
                self.segment_m,
                "at most 2,000 links over the thread's length",
            );
        }
        for (name, v) in [
            ("radius_m", self.radius_m),
            ("catch_radius_m", self.catch_radius_m),
            ("occlusion_radius_m", self.occlusion_radius_m),
            ("slack_fall_m", self.slack_fall_m),
        ] {
            if !(v.is_finite() && (0.0..=0.2).contains(&v)) {
                return bad(name, v, "0 to 0.2 m");
            }
        }
        if !(self.friction.is_finite() && (0.0..=5.0).contains(&self.friction)) {
            return bad("friction", self.friction, "a coefficient, 0 to 5");
        }
        if !(1..=100).contains(&self.iterations) {
            return bad("iterations", f64::from(self.iterations), "1 to 100");
        }
        if self.slides_through == 0 {
            return bad(
                "slides_through",
                f64::from(self.slides_through),
                "at least 1 stitch",
            );
        }
        Ok(())
    }
}

/// What the thread rests on: the pad (a plane) and the raised wound on it (a box along the
/// wound), as the renderer draws them.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Ground {
    /// Height of the pad, m.
    pub floor_z: f64,
    /// Height of the raised wound's top, m.
    pub top_z: f64,
    /// Where the raised wound starts (its centre line, at the first wound point), m.
    pub start: Point,
    /// Unit vector along the wound (horizontal).
    pub along: Vector,
    /// Half the raised wound's width across, m.
    pub half_width_m: f64,
    /// Its length beyond `start`, m; it also reaches `margin_m` before `start`.
    pub length_m: f64,
    /// How far the block reaches past the first and last wound points, m.
    pub margin_m: f64,
}

impl Ground {
    /// Height of what holds a link at `q` up: the raised wound's top over it, else the pad, m.
    fn support_z(&self, q: &Point) -> f64 {
        let across = Vector::z().cross(&self.along);
        let rel = *q - self.start;
        let (u, v) = (rel.dot(&across), rel.dot(&self.along));
        let over =
            u.abs() < self.half_width_m && v > -self.margin_m && v < self.length_m + self.margin_m;
        if over { self.top_z } else { self.floor_z }
    }

    /// Push `q` (a link of radius `r`) out of the pad and the raised wound; the contact's
    /// penetration and whether it rests on an upward face (where friction holds it).
    fn push_out(&self, q: &mut Point, r: f64) -> Option<(f64, bool)> {
        let across = Vector::z().cross(&self.along);
        let rel = *q - self.start;
        let (u, v) = (rel.dot(&across), rel.dot(&self.along));
        let hw = self.half_width_m + r;
        let in_block = u.abs() < hw
            && v > -self.margin_m - r
            && v < self.length_m + self.margin_m + r
            && q.z < self.top_z + r;
        if in_block {
            // Out through the nearest face: the top or a side.
            let up = self.top_z + r - q.z;
            let side = hw - u.abs();
            let ends = (v + self.margin_m + r).min(self.length_m + self.margin_m + r - v);
            if up <= side && up <= ends {
                q.z = self.top_z + r;
                return Some((up, true));
            }
            if side <= ends {
                *q += across * (side * u.signum());
            } else if v < self.length_m / 2.0 {
                *q -= self.along * ends;
            } else {
                *q += self.along * ends;
            }
            return Some((side.min(ends), false));
        }
        let floor = self.floor_z + r;
        if q.z < floor {
            let pen = floor - q.z;
            q.z = floor;
            return Some((pen, true));
        }
        None
    }
}

/// A solid a tool presents to the thread: the points within `radius` of a segment.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Capsule {
    /// One end of the axis, m.
    pub a: Point,
    /// The other end, m.
    pub b: Point,
    /// Radius, m.
    pub radius: f64,
}

impl Capsule {
    /// The point of the axis nearest `q`.
    fn nearest(&self, q: &Point) -> Point {
        stitch_robot::nearest_on_segment(q, &self.a, &self.b).0
    }

    /// Distance from `q` to the axis, m.
    pub fn axis_distance(&self, q: &Point) -> f64 {
        (q - self.nearest(q)).norm()
    }
}

/// A dVRK large needle driver's jaw blades, wrist and shaft as capsules, for a tool at `pose`
/// (tip at the origin, the blades back along −z, opening in the tool's y–z plane) with its
/// jaw open `jaw_rad`: the shapes the renderer draws.
pub fn tool_capsules(pose: &Pose, jaw_rad: f64) -> [Capsule; 5] {
    let l = crate::JAW_LENGTH_M;
    let half = (jaw_rad / 2.0).clamp(0.0, 1.2);
    let wrist = pose * Point::new(0.0, 0.0, -l);
    let tip = |side: f64| pose * Point::new(0.0, side * l * half.sin(), -l * (1.0 - half.cos()));
    let (t1, t2) = (tip(-1.0), tip(1.0));
    [
        Capsule {
            a: wrist,
            b: t1,
            radius: 0.0009,
        },
        Capsule {
            a: wrist,
            b: t2,
            radius: 0.0009,
        },
        // The blades' tips together, open or not: what a sweep drags thread with.
        Capsule {
            a: t1,
            b: t2,
            radius: 0.0009,
        },
        Capsule {
            a: wrist,
            b: pose * Point::new(0.0, 0.0, -l - 0.006),
            radius: 0.0025,
        },
        Capsule {
            a: pose * Point::new(0.0, 0.0, -l - 0.006),
            b: pose * Point::new(0.0, 0.0, -l - 0.05),
            radius: 0.0042,
        },
    ]
}

/// A chain of links of one length; its first and last points may be held.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Chain {
    /// The links' ends, m.
    pub points: Vec<Point>,
    /// Whether the first point is held where it is.
    pub first_held: bool,
    /// Whether the last point is held where it is.
    pub last_held: bool,
    /// Which links came to rest in the last relaxation (moved less than [`REST_M`] in its
    /// last iteration), and where the ends were then; empty: none known to rest.
    #[serde(skip)]
    pub resting: (Vec<bool>, Option<(Point, Point)>),
}

/// A link that moves less than this in an iteration is at rest, m.
const REST_M: f64 = 1e-6;
/// A resting link wakes when a link beside it is stretched by more than this share.
const WAKE_STRAIN: f64 = 0.01;
/// Links on each side of a moving one that move with it.
const WAKE_REACH: usize = 2;

/// The box around `points`, grown by `margin` on every side.
fn bounds(points: &[Point], margin: f64) -> (Point, Point) {
    let mut lo = Point::new(f64::INFINITY, f64::INFINITY, f64::INFINITY);
    let mut hi = Point::new(f64::NEG_INFINITY, f64::NEG_INFINITY, f64::NEG_INFINITY);
    for p in points {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k] - margin);
            hi[k] = hi[k].max(p[k] + margin);
        }
    }
    (lo, hi)
}

/// PBD iterations when the world comes to rest (a motion's end, a needle let go).
const SETTLE_ITERATIONS: u32 = 15;
/// Sweeps over the links' lengths per iteration, alternating in direction.
const LENGTH_PASSES: usize = 2;
/// How far an unsupported link falls in one PBD iteration (gravity, quasi-static), m.
const FALL_PER_ITERATION_M: f64 = 0.0001;

impl Chain {
    /// The chain's length at rest, m.
    fn rest_length(&self, segment: f64) -> f64 {
        segment * self.points.len().saturating_sub(1) as f64
    }

    /// Distance between its ends, m.
    fn span(&self) -> f64 {
        match (self.points.first(), self.points.last()) {
            (Some(a), Some(b)) => (b - a).norm(),
            _ => 0.0,
        }
    }

    fn held(&self, i: usize) -> bool {
        (i == 0 && self.first_held) || (i + 1 == self.points.len() && self.last_held)
    }

    /// Relax `iterations` times: gravity, lengths, the ground (with friction against where
    /// the links were when this relaxation began) and the tools.
    /// Relax `iterations` times: gravity, lengths, the ground (with friction against where
    /// each link was when the iteration began) and the tools. Links at rest stay asleep, held
    /// where they are, unless something near them moves: a tool, a held end, a link beside
    /// them pulled off its length (most of a long thread lies still on the pad).
    fn relax(
        &mut self,
        config: &ThreadConfig,
        ground: &Ground,
        tools: &[Capsule],
        iterations: u32,
    ) {
        let n = self.points.len();
        if n < 2 {
            return;
        }
        let seg = config.segment_m;
        let r = config.radius_m;
        // Only the tools near the chain can touch it.
        let (lo, hi) = bounds(&self.points, 0.001 + r);
        let near: Vec<(Capsule, Point, Point)> = tools
            .iter()
            .filter_map(|t| {
                let (a, b) = bounds(&[t.a, t.b], t.radius + r);
                let overlaps = (0..3).all(|k| a[k] <= hi[k] && b[k] >= lo[k]);
                overlaps.then_some((*t, a, b))
            })
            .collect();
        let inside = |q: &Point, a: &Point, b: &Point| (0..3).all(|k| q[k] >= a[k] && q[k] <= b[k]);
        // Which links move this time.
        let ends = (self.points[0], self.points[n - 1]);
        let (resting, rested_ends) = &self.resting;
        let mut awake: Vec<bool> = if resting.len() == n {
            resting.iter().map(|r| !r).collect()
        } else {
            vec![true; n]
        };
        if let Some((a, b)) = rested_ends {
            if (a - ends.0).norm() > REST_M {
                awake[0] = true;
            }
            if (b - ends.1).norm() > REST_M {
                awake[n - 1] = true;
            }
        }
        for (a, p) in awake.iter_mut().zip(&self.points) {
            if !*a && near.iter().any(|(_, lo, hi)| inside(p, lo, hi)) {
                *a = true;
            }
        }
        for i in 0..n - 1 {
            let len = (self.points[i + 1] - self.points[i]).norm();
            // Stretched, not bunched: links pressed together lie slack, as thread does.
            if len - seg > WAKE_STRAIN * seg {
                awake[i] = true;
                awake[i + 1] = true;
            }
        }
        let seeds: Vec<usize> = (0..n).filter(|&i| awake[i]).collect();
        if seeds.is_empty() {
            return;
        }
        for i in seeds {
            let (lo, hi) = (i.saturating_sub(WAKE_REACH), (i + WAKE_REACH).min(n - 1));
            awake[lo..=hi].fill(true);
        }
        let w: Vec<f64> = (0..n)
            .map(|i| if self.held(i) || !awake[i] { 0.0 } else { 1.0 })
            .collect();
        let mut start = self.points.clone();
        for _ in 0..iterations {
            start.copy_from_slice(&self.points);
            for (p, wi) in self.points.iter_mut().zip(&w) {
                if *wi > 0.0 {
                    p.z -= FALL_PER_ITERATION_M;
                }
            }
            // Lengths, sweeps each way so that neither end lags.
            for pass in 0..LENGTH_PASSES {
                for k in 0..n - 1 {
                    let i = if pass % 2 == 0 { k } else { n - 2 - k };
                    let (wa, wb) = (w[i], w[i + 1]);
                    if wa + wb == 0.0 {
                        continue;
                    }
                    let d = self.points[i + 1] - self.points[i];
                    let len = d.norm();
                    if len < 1e-12 {
                        continue;
                    }
                    let c = (len - seg) / (len * (wa + wb));
                    self.points[i] += d * (c * wa);
                    self.points[i + 1] -= d * (c * wb);
                }
            }
            // Long-range attachments (Kim, Chentanez and Müller 2012): no link farther from a
            // held end than the chain between them, so a hanging thread does not stretch under
            // its own weight however few the iterations.
            for (held, h) in [(self.first_held, 0), (self.last_held, n - 1)] {
                if !held {
                    continue;
                }
                let anchor = self.points[h];
                for (i, (p, wi)) in self.points.iter_mut().zip(&w).enumerate() {
                    if *wi == 0.0 {
                        continue;
                    }
                    let max = seg * i.abs_diff(h) as f64;
                    let d = *p - anchor;
                    let len = d.norm();
                    if len > max {
                        *p = anchor + d * (max / len);
                    }
                }
            }
            for i in 0..n {
                if w[i] == 0.0 {
                    continue;
                }
                let q = &mut self.points[i];
                if let Some((pen, upward)) = ground.push_out(q, r) {
                    if upward {
                        // Friction (Macklin et al. 2014, per iteration): a resting link keeps
                        // its place unless pulled along the surface farther than friction
                        // times how hard it pressed on it.
                        let mut slide = *q - start[i];
                        slide.z = 0.0;
                        let s = slide.norm();
                        let hold = config.friction * pen;
                        if s <= hold {
                            q.x = start[i].x;
                            q.y = start[i].y;
                        } else {
                            *q -= slide * (hold / s);
                        }
                    }
                }
                // The tools last: nothing pushes a link into a tool.
                for (t, a, b) in &near {
                    if !inside(q, a, b) {
                        continue;
                    }
                    let c = t.nearest(q);
                    let d = *q - c;
                    let reach = t.radius + r;
                    let dist = d.norm();
                    if dist < reach {
                        let dir = if dist > 1e-12 { d / dist } else { Vector::z() };
                        let out = c + dir * reach;
                        // A link pressed between a tool and the tissue goes out sideways, as
                        // thread does under a blade scraping the tissue, not into the tissue.
                        let floor = ground.support_z(q) + r;
                        let flat = Vector::new(d.x, d.y, 0.0);
                        let dz = q.z - c.z;
                        if out.z < floor - 1e-9 && dz.abs() < reach && flat.norm() > 1e-12 {
                            let h = (reach * reach - dz * dz).sqrt();
                            let f = flat / flat.norm();
                            q.x = c.x + f.x * h;
                            q.y = c.y + f.y * h;
                        } else {
                            *q = out;
                        }
                    }
                }
            }
        }
        let resting: Vec<bool> = self
            .points
            .iter()
            .zip(&start)
            .map(|(p, s)| (p - s).norm() < REST_M)
            .collect();
        self.resting = (resting, Some((self.points[0], self.points[n - 1])));
    }

    /// Distance from `p` to the chain, m.
    fn distance_to(&self, p: &Point) -> f64 {
        stitch_robot::distance_to_polyline(p, &self.points)
    }
}

/// Points from `a` to `b`, `n` of them, one `segment` apart along a curve that bows out by
/// the amount that gives it that length, towards `side` (horizontal) and resting on the
/// ground: a thread laid down with its slack to one side.
fn bowed(a: Point, b: Point, n: usize, segment: f64, side: Vector, ground: &Ground) -> Vec<Point> {
    let n = n.max(2);
    let length = segment * (n - 1) as f64;
    // Straight down from each end to the pad, and the rest on the pad, bowed to `side`.
    let (fa, fb) = (
        Point::new(a.x, a.y, ground.floor_z.min(a.z)),
        Point::new(b.x, b.y, ground.floor_z.min(b.z)),
    );
    let (da, db) = ((a.z - fa.z).max(0.0), (b.z - fb.z).max(0.0));
    let total = length.max(1e-9);
    let (ta, tb) = ((da / total).min(0.45), 1.0 - (db / total).min(0.45));
    let at = |amp: f64, t: f64| {
        if t < ta {
            a + (fa - a) * (t / ta)
        } else if t > tb {
            fb + (b - fb) * ((t - tb) / (1.0 - tb))
        } else {
            let u = (t - ta) / (tb - ta).max(1e-9);
            fa + (fb - fa) * u + side * (amp * (std::f64::consts::PI * u).sin())
        }
    };
    let curve_length = |amp: f64| {
        let k = 64;
        (0..k)
            .map(|i| (at(amp, (i + 1) as f64 / k as f64) - at(amp, i as f64 / k as f64)).norm())
            .sum::<f64>()
    };
    let (mut lo, mut hi) = (0.0, length);
    if curve_length(0.0) < length {
        for _ in 0..40 {
            let mid = (lo + hi) / 2.0;
            if curve_length(mid) < length {
                lo = mid;
            } else {
                hi = mid;
            }
        }
    }
    // Resample at equal arc length.
    let k = 8 * n;
    let dense: Vec<Point> = (0..=k).map(|i| at(lo, i as f64 / k as f64)).collect();
    let mut cum = vec![0.0];
    for w in dense.windows(2) {
        cum.push(cum.last().copied().unwrap_or(0.0) + (w[1] - w[0]).norm());
    }
    let total = cum.last().copied().unwrap_or(0.0).max(1e-12);
    let mut out = Vec::with_capacity(n);
    let mut j = 0;
    for i in 0..n {
        let s = total * i as f64 / (n - 1) as f64;
        while j + 2 < cum.len() && cum[j + 1] < s {
            j += 1;
        }
        let span = (cum[j + 1] - cum[j]).max(1e-12);
        let f = ((s - cum[j]) / span).clamp(0.0, 1.0);
        out.push(dense[j] + (dense[j + 1] - dense[j]) * f);
    }
    out
}

/// A finished stitch: the thread through its tissue and its loop.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct Stitch {
    /// Thread through the tissue, m.
    pub tissue_m: f64,
    /// Thread in its loop (from the previous exit, or the tail's knot, to its entry), m.
    pub loop_m: f64,
    /// The loop's length pulled tight, m.
    pub taut_m: f64,
}

/// The thread's state.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Thread {
    /// Its parameters.
    pub config: ThreadConfig,
    /// What it rests on.
    pub ground: Ground,
    /// The earlier stitches, first first.
    pub stitches: Vec<Stitch>,
    /// The free chain: from where it leaves the suture line (the tail's knot, free, before
    /// the first stitch) to the swage.
    pub free: Chain,
    /// The loop of the stitch being made (from the previous exit, or the tail's knot, to this
    /// stitch's entry), once its needle is out of the tissue and until the next goes in.
    pub open_loop: Option<Chain>,
    /// Whether the loop starts at the tail's knot (the first stitch), which pulls through
    /// until the knot reaches the entry, rather than at a stitch.
    pub loop_is_tail: bool,
    /// Thread through the open loop's stitch (its path in the tissue, in whole links), m.
    pub tissue_m: f64,
    /// Whether a jaw holds it (with or without the needle).
    pub caught: bool,
    /// Whether it is tangled around a jaw.
    pub tangled: bool,
    /// Whether it was pulled taut with no slack left to give.
    pub short: bool,
    /// Where the suture line last held it (the last stitch's exit), if any stitch has.
    pub anchor: Option<Point>,
}

/// Links at the swage end that belong to the needle's grasp, not to be caught or tangled by
/// the jaw holding the needle (the thread leaves the swage within them), 3 links.
const AT_SWAGE_LINKS: usize = 5;

impl Thread {
    /// A fresh thread, `config.length_m` of it free: its tail's knot at `tail` on the pad,
    /// its slack laid to `side` and its end at the needle's swage.
    pub fn new(
        config: ThreadConfig,
        ground: Ground,
        tail: Point,
        swage: Point,
        side: Vector,
    ) -> Result<Self, SimError> {
        let mut t = Self::laid(config, ground, tail, swage, side, None)?;
        t.settle(swage, &[]);
        Ok(t)
    }

    /// A thread after a stitch: `config.length_m` of it free from `from` (the stitch's exit,
    /// held there by the tissue) to the swage, laid to `side` and settled `settles` times
    /// (each [`SETTLE_ITERATIONS`] iterations; gravity lowers a link 0.1 mm an iteration)
    /// round `tools`.
    /// What the thread tracer's evaluation draws.
    pub fn hanging(
        config: ThreadConfig,
        ground: Ground,
        from: Point,
        swage: Point,
        side: Vector,
        tools: &[Capsule],
        settles: u32,
    ) -> Result<Self, SimError> {
        let mut t = Self::laid(config, ground, from, swage, side, Some(from))?;
        for _ in 0..settles.max(1) {
            t.settle(swage, tools);
        }
        Ok(t)
    }

    /// `config.length_m` of thread laid from `from` to the swage, bowed to `side`, unsettled:
    /// its first end free (a tail) or held where a stitch left it (`anchor`).
    fn laid(
        config: ThreadConfig,
        ground: Ground,
        from: Point,
        swage: Point,
        side: Vector,
        anchor: Option<Point>,
    ) -> Result<Self, SimError> {
        config.validate()?;
        let n = (config.length_m / config.segment_m).round() as usize + 1;
        Ok(Self {
            config,
            ground,
            stitches: vec![],
            free: Chain {
                points: bowed(from, swage, n, config.segment_m, side, &ground),
                first_held: anchor.is_some(),
                last_held: true,
                resting: (vec![], None),
            },
            open_loop: None,
            loop_is_tail: anchor.is_none(),
            tissue_m: 0.0,
            caught: false,
            tangled: false,
            short: false,
            anchor,
        })
    }

    /// Free thread on the needle's side of the suture line, m.
    pub fn remaining_m(&self) -> f64 {
        self.free.rest_length(self.config.segment_m)
    }

    /// Links the open loop must keep: one for the tail's knot, else its span.
    fn open_loop_keeps(&self, l: &Chain) -> usize {
        if self.loop_is_tail {
            2
        } else {
            (l.span() / self.config.segment_m).ceil() as usize + 1
        }
    }

    /// Slack a pull could still draw through the stitches, m.
    pub fn slack_m(&self) -> f64 {
        let seg = self.config.segment_m;
        let open = self.open_loop.as_ref().map_or(0.0, |l| {
            l.points.len().saturating_sub(self.open_loop_keeps(l)) as f64 * seg
        });
        open + self
            .stitches
            .iter()
            .map(|s| (s.loop_m - s.taut_m).max(0.0))
            .sum::<f64>()
    }

    /// Every piece of thread the camera may see, each a polyline, m.
    pub fn pieces(&self) -> Vec<Vec<Point>> {
        let mut out = vec![self.free.points.clone()];
        if let Some(l) = &self.open_loop {
            out.push(l.points.clone());
        }
        out
    }

    /// Total length of the thread: sutured, in the open loop, through the tissue of the open
    /// loop's stitch, and free, m. Conserved.
    pub fn total_m(&self) -> f64 {
        let seg = self.config.segment_m;
        self.stitches
            .iter()
            .map(|s| s.tissue_m + s.loop_m)
            .sum::<f64>()
            + self.remaining_m()
            + self
                .open_loop
                .as_ref()
                .map_or(0.0, |l| l.rest_length(seg) + self.tissue_m)
    }

    /// The distance from `p` to the thread, m.
    pub fn distance_to(&self, p: &Point) -> f64 {
        let d = self.free.distance_to(p);
        self.open_loop
            .as_ref()
            .map_or(d, |l| d.min(l.distance_to(p)))
    }

    /// Whether the thread hides a needle with this centre and tip.
    pub fn occludes(&self, center: &Point, tip: &Point) -> bool {
        let r = self.config.occlusion_radius_m;
        self.distance_to(center) <= r || self.distance_to(tip) <= r
    }

    /// Follow the world: the swage where it is now, the tools as they are; a few
    /// iterations (`settle` does more). Draws thread through the open stitch when the free
    /// chain is pulled taut.
    pub fn follow(&mut self, swage: Point, tools: &[Capsule]) {
        // Nothing that holds or touches it moved: it settles when the motion ends.
        let still = self
            .free
            .points
            .last()
            .is_some_and(|p| (p - swage).norm() < 1e-9);
        if still && !self.near(tools) {
            return;
        }
        self.relax(swage, tools, self.config.iterations);
    }

    /// Whether any of `tools` comes within a millimetre of the thread's bounding boxes: a
    /// moving tool that may push it (the world then follows it at every half millimetre, so
    /// that a link pushed ahead of a blade stays ahead of it).
    pub fn near(&self, tools: &[Capsule]) -> bool {
        let r = self.config.radius_m;
        let near = |c: &Chain| {
            let (lo, hi) = bounds(&c.points, 0.001 + r);
            tools.iter().any(|t| {
                let (a, b) = bounds(&[t.a, t.b], t.radius + r);
                (0..3).all(|k| a[k] <= hi[k] && b[k] >= lo[k])
            })
        };
        near(&self.free) || self.open_loop.as_ref().is_some_and(near)
    }

    /// Let the thread come to rest around the world as it is now.
    pub fn settle(&mut self, swage: Point, tools: &[Capsule]) {
        self.relax(swage, tools, SETTLE_ITERATIONS);
    }

    fn relax(&mut self, swage: Point, tools: &[Capsule], iterations: u32) {
        if let Some(last) = self.free.points.last_mut() {
            *last = swage;
        }
        self.draw_through();
        let (config, ground) = (self.config, self.ground);
        self.free.relax(&config, &ground, tools, iterations);
        if let Some(l) = &mut self.open_loop {
            l.relax(&config, &ground, tools, iterations);
        }
    }

    /// The free chain pulled taut draws thread through the open stitch out of its loop; with
    /// none to give, the thread is short.
    fn draw_through(&mut self) {
        let seg = self.config.segment_m;
        if !self.free.first_held {
            // The tail is free: the whole thread follows the needle.
            return;
        }
        let rest = self.free.rest_length(seg);
        let span = self.free.span();
        if span < rest - 0.5 * seg {
            return;
        }
        let want = ((span - rest) / seg + 1.0).ceil().max(1.0) as usize;
        // The open loop's slack first.
        let from_loop = match &self.open_loop {
            Some(l) => l
                .points
                .len()
                .saturating_sub(self.open_loop_keeps(l))
                .min(want),
            None => 0,
        };
        if let Some(l) = &mut self.open_loop {
            let end = l.points.len() - 1;
            l.points.drain(end - from_loop..end);
        }
        // Then the earlier stitches'.
        let give = from_loop + self.take_slack(want - from_loop);
        if give < want && span > rest + 0.5 * seg {
            self.short = true;
        }
        if give == 0 {
            return;
        }
        // The links come out of the exit towards the next link.
        let a = self.free.points[0];
        let b = self.free.points.get(1).copied().unwrap_or(a);
        let dir = (b - a).try_normalize(1e-12).unwrap_or_else(Vector::z);
        for k in (1..=give).rev() {
            let f = k as f64 / (give + 1) as f64;
            self.free.points.insert(1, a + dir * (seg * f));
        }
        self.free.resting = (vec![], None);
        if let Some(l) = &mut self.open_loop {
            l.resting = (vec![], None);
        }
    }

    /// Draw up to `links` links of slack out of the earlier stitches' loops, newest first;
    /// how many it got.
    fn take_slack(&mut self, links: usize) -> usize {
        let seg = self.config.segment_m;
        // The newest finished stitch's loop lies behind that stitch, and behind the open
        // loop's stitch too when there is one.
        let behind = usize::from(self.open_loop.is_some());
        let reach = (self.config.slides_through as usize).saturating_sub(behind);
        let mut got = 0;
        for st in self.stitches.iter_mut().rev().take(reach) {
            if got == links {
                break;
            }
            let spare = ((st.loop_m - st.taut_m) / seg + 1e-9).floor().max(0.0) as usize;
            let take = spare.min(links - got);
            st.loop_m -= take as f64 * seg;
            got += take;
        }
        got
    }

    /// A needle went through the tissue and was let go: the open loop lies down along the
    /// suture line with its stitch, and the free thread's slack falls to a side drawn from
    /// `rng`.
    pub fn on_insertion(&mut self, swage: Point, rng: &mut ChaCha8Rng) {
        let seg = self.config.segment_m;
        if let Some(l) = self.open_loop.take() {
            let taut = if self.loop_is_tail { seg } else { l.span() };
            self.stitches.push(Stitch {
                tissue_m: self.tissue_m,
                loop_m: l.rest_length(seg),
                taut_m: taut,
            });
            self.tissue_m = 0.0;
        }
        let angle = rng.random_range(0.0..std::f64::consts::TAU);
        let side = Vector::new(angle.cos(), angle.sin(), 0.0);
        let n = self.free.points.len();
        let fall = self.config.slack_fall_m;
        for (i, p) in self.free.points.iter_mut().enumerate() {
            let t = i as f64 / (n.max(2) - 1) as f64;
            if i > 0 && i + 1 < n {
                *p += side * (fall * (std::f64::consts::PI * t).sin());
            }
        }
        self.free.resting = (vec![], None);
        self.settle(swage, &[]);
    }

    /// The needle came out of the tissue through `exit`, having gone in at `entry` along
    /// `in_tissue_m` of path: the thread behind the swage followed it through. The free
    /// chain becomes the open loop up to the entry, and a new free chain runs from the exit to
    /// the swage.
    pub fn on_extraction(&mut self, entry: Point, exit: Point, in_tissue_m: f64, swage: Point) {
        let seg = self.config.segment_m;
        let out = (swage - exit).norm();
        let tissue_links = (in_tissue_m / seg).round() as usize;
        let free_links = ((out / seg).ceil() as usize).max(1);
        let through = tissue_links + free_links;
        let mut old = std::mem::replace(
            &mut self.free,
            Chain {
                points: vec![],
                first_held: true,
                last_held: true,
                resting: (vec![], None),
            },
        );
        // The loop's side keeps at least the knot and one link, or its span; what the free
        // chain lacks for that was drawn through the earlier stitches as the needle came out.
        let min_keep = if self.anchor.is_none() {
            2
        } else {
            (old.span() / seg).ceil() as usize + 1
        };
        let lacking = (through + min_keep).saturating_sub(old.points.len());
        if lacking > 0 {
            let got = self.take_slack(lacking);
            if got < lacking {
                self.short = true;
            }
            let a = old.points[0];
            let b = old.points.get(1).copied().unwrap_or(a);
            let dir = (b - a).try_normalize(1e-12).unwrap_or_else(Vector::z);
            for k in (1..=got).rev() {
                let f = k as f64 / (got + 1) as f64;
                old.points.insert(1, a + dir * (seg * f));
            }
        }
        let n_old = old.points.len();
        let keep = n_old.saturating_sub(through).max(2);
        let mut loop_points: Vec<Point> = old.points[..keep].to_vec();
        if let Some(last) = loop_points.last_mut() {
            *last = entry;
        }
        let loop_is_tail = self.anchor.is_none();
        self.open_loop = Some(Chain {
            points: loop_points,
            first_held: !loop_is_tail,
            last_held: true,
            resting: (vec![], None),
        });
        self.loop_is_tail = loop_is_tail;
        self.tissue_m = tissue_links as f64 * seg;
        let n_free = n_old + 1 - keep - tissue_links;
        let dir = (swage - exit)
            .try_normalize(1e-12)
            .unwrap_or_else(Vector::z);
        let step = out / (n_free - 1) as f64;
        self.free.points = (0..n_free)
            .map(|i| exit + dir * (step.min(seg) * i as f64))
            .collect();
        if let Some(last) = self.free.points.last_mut() {
            *last = swage;
        }
        self.anchor = Some(exit);
        self.settle(swage, &[]);
    }

    /// A jaw closed with these blades (its closed blades' axis): thread within the catch
    /// radius is caught; `holds_needle`: the links at the swage are the jaw's own grasp.
    pub fn on_grasp(&mut self, blades: &Capsule, holds_needle: bool) {
        let r = self.config.catch_radius_m;
        let n = self.free.points.len();
        let skip = if holds_needle { AT_SWAGE_LINKS } else { 1 };
        let free = self.free.points[..n.saturating_sub(skip)]
            .iter()
            .any(|p| blades.axis_distance(p) <= r);
        let in_loop = self.open_loop.as_ref().is_some_and(|l| {
            l.points[..l.points.len().saturating_sub(1)]
                .iter()
                .any(|p| blades.axis_distance(p) <= r)
        });
        if free || in_loop {
            self.caught = true;
        }
    }

    /// After a motion: the thread hanging over a tool, turning round it by more than 90°, is
    /// wrapped around it (tangled). `tools`: the tools' capsules.
    pub fn check_tangle(&mut self, tools: &[Capsule]) {
        let reach = |c: &Capsule| c.radius + self.config.radius_m + 0.0003;
        let hangs = |p: &Point| p.z > self.ground.top_z + 0.003;
        let mut chains: Vec<&[Point]> =
            vec![&self.free.points[..self.free.points.len().saturating_sub(AT_SWAGE_LINKS + 2)]];
        if let Some(l) = &self.open_loop {
            chains.push(&l.points);
        }
        let wrapped = chains.iter().any(|pts| {
            (2..pts.len().saturating_sub(2)).any(|i| {
                let p = &pts[i];
                let touching = tools.iter().any(|c| c.axis_distance(p) <= reach(c));
                if !touching || !hangs(p) {
                    return false;
                }
                let (a, b) = (pts[i] - pts[i - 2], pts[i + 2] - pts[i]);
                match (a.try_normalize(1e-12), b.try_normalize(1e-12)) {
                    (Some(a), Some(b)) => a.dot(&b) < 0.0,
                    _ => false,
                }
            })
        });
        if wrapped {
            self.tangled = true;
        }
    }

    /// The surgeon frees the thread and lays its slack along `side`, away from the wound:
    /// neither caught nor tangled; short stays short.
    pub fn lay_aside(&mut self, swage: Point, side: Vector) {
        self.caught = false;
        self.tangled = false;
        let n = self.free.points.len();
        let first = self.free.points[0];
        self.free.points = bowed(first, swage, n, self.config.segment_m, side, &self.ground);
        self.free.resting = (vec![], None);
        if let Some(l) = &mut self.open_loop {
            let (a, b) = (l.points[0], l.points[l.points.len() - 1]);
            l.points = bowed(
                a,
                b,
                l.points.len(),
                self.config.segment_m,
                side,
                &self.ground,
            );
            l.resting = (vec![], None);
        }
        self.settle(swage, &[]);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use stitch_robot::nalgebra::{Rotation3, Translation3, UnitQuaternion};

    fn ground() -> Ground {
        Ground {
            floor_z: -0.126,
            top_z: -0.116,
            start: Point::new(0.0, 0.0, -0.116),
            along: Vector::y(),
            half_width_m: 0.005,
            length_m: 0.04,
            margin_m: 0.004,
        }
    }

    fn thread(length: f64) -> Thread {
        let config = ThreadConfig {
            length_m: length,
            ..ThreadConfig::default()
        };
        Thread::new(
            config,
            ground(),
            Point::new(-0.015, 0.0, -0.126),
            Point::new(-0.03, 0.0, -0.09),
            -Vector::y(),
        )
        .expect("thread")
    }

    #[test]
    fn slack_rests_on_the_pad_with_every_link_its_length() {
        let mut t = thread(0.1);
        for _ in 0..20 {
            t.settle(Point::new(-0.03, 0.0, -0.09), &[]);
        }
        // Links resting on the pad keep their length; links hanging from the needle stretch
        // a little under the chain's weight (a few PBD passes an iteration), never much.
        for w in t.free.points.windows(2) {
            let l = (w[1] - w[0]).norm();
            let hanging = w[0].z.max(w[1].z) > -0.1255 + 1e-6;
            let tol = if hanging { 0.1 } else { 0.05 };
            assert!(
                (l / 0.002 - 1.0).abs() <= tol,
                "link {l} m, hanging: {hanging}"
            );
        }
        let resting = t
            .free
            .points
            .iter()
            .filter(|p| p.z < -0.1255 + 1e-6)
            .count();
        assert!(resting > 20, "{resting} links on the pad");
        assert!((t.remaining_m() - 0.1).abs() < 1e-9);
    }

    #[test]
    fn a_tool_pushes_the_links_in_its_way_and_not_others() {
        let mut t = thread(0.1);
        t.settle(Point::new(-0.03, 0.0, -0.09), &[]);
        let before = t.free.points.clone();
        // A closed jaw pointing down, its tip on the pad at a link lying there.
        let k = before
            .iter()
            .enumerate()
            .position(|(i, p)| i > 0 && p.z < -0.1255)
            .expect("a link on the pad");
        let at = before[k];
        // Beside it on the pad, half a millimetre off across the chain.
        let along = before[k + 1] - before[k - 1];
        let across = Vector::z().cross(&along).normalize();
        let tip = at + across * 0.0005;
        let pose = Pose::from_parts(
            Translation3::new(tip.x, tip.y, tip.z),
            UnitQuaternion::from_axis_angle(&Vector::x_axis(), std::f64::consts::PI),
        );
        let tools = tool_capsules(&pose, 0.0);
        t.follow(Point::new(-0.03, 0.0, -0.09), &tools);
        let moved = (t.free.points[k] - at).norm();
        assert!(moved > 0.0005, "the link under the tool moved {moved} m");
        for c in &tools {
            for p in &t.free.points {
                assert!(c.axis_distance(p) >= c.radius + 0.00015 - 1e-9);
            }
        }
        let far = before
            .iter()
            .zip(&t.free.points)
            .enumerate()
            .filter(|(i, _)| i.abs_diff(k) > 10)
            .filter(|(_, (a, _))| a.z < -0.1255)
            .map(|(_, (a, b))| (b - a).norm())
            .fold(0.0, f64::max);
        assert!(far < 1e-4, "links far from it moved {far} m");
    }

    /// An open jaw, held across its path like a broom with its blade tips on the pad, moved
    /// along +y in 0.5 mm steps from `x`, as the world moves a tool near the thread.
    fn sweep_at(t: &mut Thread, x: f64) {
        let open = 60f64.to_radians();
        let lift = 0.009 * (1.0 - (open / 2.0).cos());
        // Tool z down, tool y (the blades' spread) along x.
        let broom = UnitQuaternion::from_rotation_matrix(&Rotation3::from_basis_unchecked(&[
            Vector::y(),
            Vector::x(),
            -Vector::z(),
        ]));
        let swage = *t.free.points.last().expect("links");
        for k in 0..=120 {
            let y = -0.03 + 0.0005 * f64::from(k);
            let pose = Pose::from_parts(Translation3::new(x, y, -0.126 - lift + 0.0003), broom);
            t.follow(swage, &tool_capsules(&pose, open));
        }
        t.settle(swage, &[]);
    }

    #[test]
    fn a_sweep_through_the_thread_pushes_it_ahead_and_one_beside_it_moves_nothing() {
        // Thread lying along x on the pad at y = 0, from 6 cm on the −x side of the wound.
        let mut t = thread(0.1);
        t.free.points = (0..t.free.points.len())
            .map(|i| Point::new(-0.06 + 0.002 * i as f64, 0.0, -0.126 + 0.00015))
            .collect();
        // Its far end free, so the push can drag it.
        t.free.first_held = false;
        t.free.resting = (vec![], None);
        let swage = *t.free.points.last().expect("links");
        for _ in 0..40 {
            t.settle(swage, &[]);
        }
        let before = t.free.points.clone();
        let at = |pts: &[Point]| {
            pts.iter()
                .filter(|p| (p.x + 0.03).abs() < 0.002)
                .map(|p| p.y)
                .fold(f64::NEG_INFINITY, f64::max)
        };
        let mut through = t.clone();
        sweep_at(&mut through, -0.03);
        assert!(
            // Pushed ahead until its tension slides it round the blades' ends (the blades do
            // not hold it: no friction between tool and thread).
            at(&through.free.points) > at(&before) + 0.004,
            "the links under the sweep went from y {:.4} to {:.4}",
            at(&before),
            at(&through.free.points)
        );
        let mut beside = t.clone();
        // 1.5 cm beyond the chain's free end.
        sweep_at(&mut beside, -0.06 - 0.015);
        let moved = before
            .iter()
            .zip(&beside.free.points)
            .map(|(a, b)| (b - a).norm())
            .fold(0.0, f64::max);
        assert!(
            moved < 1e-4,
            "a sweep 1.5 cm past the thread moved it {moved} m"
        );
    }

    #[test]
    fn pulling_the_free_chain_draws_thread_out_of_the_loop_until_it_is_taut() {
        let mut rng = crate::Streams::new(1).rng(crate::Subsystem::Thread);
        let mut t = thread(0.3);
        let (entry, exit) = (
            Point::new(-0.005, 0.0, -0.12),
            Point::new(0.005, 0.0, -0.12),
        );
        t.on_insertion(Point::new(-0.01, 0.0, -0.11), &mut rng);
        let total = t.total_m();
        t.on_extraction(entry, exit, 0.01, Point::new(0.02, 0.0, -0.11));
        assert!(t.loop_is_tail);
        assert!((t.total_m() - total).abs() < 1e-9, "conserved");
        let free0 = t.remaining_m();
        // Pull the needle 8 cm away: the tail slides through.
        for k in 1..=80 {
            t.follow(Point::new(0.02 + 0.001 * f64::from(k), 0.0, -0.11), &[]);
        }
        assert!(t.remaining_m() > free0 + 0.07, "{} m free", t.remaining_m());
        assert!(!t.short);
        assert!((t.total_m() - total).abs() < 1e-9, "conserved");
    }

    /// Two stitches, the tail's slack left behind the first, then the needle pulled 12 cm
    /// away: what the pull could draw, and the thread.
    fn two_stitches_then_pull(slides_through: u32) -> Thread {
        let mut rng = crate::Streams::new(1).rng(crate::Subsystem::Thread);
        let mut t = thread(0.3);
        t.config.slides_through = slides_through;
        t.on_insertion(Point::new(-0.01, 0.0, -0.11), &mut rng);
        let total = t.total_m();
        t.on_extraction(
            Point::new(-0.005, 0.0, -0.12),
            Point::new(0.005, 0.0, -0.12),
            0.01,
            Point::new(0.02, 0.0, -0.11),
        );
        t.on_insertion(Point::new(-0.01, 0.006, -0.11), &mut rng);
        t.on_extraction(
            Point::new(-0.005, 0.006, -0.12),
            Point::new(0.005, 0.006, -0.12),
            0.01,
            Point::new(0.02, 0.006, -0.11),
        );
        assert_eq!(t.stitches.len(), 1);
        assert!(
            t.stitches[0].loop_m - t.stitches[0].taut_m > 0.2,
            "the tail keeps its slack behind the first stitch: {:?}",
            t.stitches[0]
        );
        for k in 1..=120 {
            t.follow(Point::new(0.02 + 0.001 * f64::from(k), 0.006, -0.11), &[]);
        }
        assert!((t.total_m() - total).abs() < 1e-9, "conserved");
        t
    }

    #[test]
    fn slack_behind_more_stitches_than_a_pull_slides_through_stays_there() {
        let free = two_stitches_then_pull(1000);
        assert!(!free.short, "the tail slides through both stitches");
        let held = two_stitches_then_pull(1);
        assert!(held.short, "the tail's slack is behind two stitches");
        assert!(
            held.stitches[0].loop_m > free.stitches[0].loop_m + 0.1,
            "{} against {} m left in the tail",
            held.stitches[0].loop_m,
            free.stitches[0].loop_m
        );
        let two = two_stitches_then_pull(2);
        assert!(!two.short, "two stitches reach the tail");
    }

    #[test]
    fn a_taut_loop_gives_nothing_and_the_thread_runs_short() {
        let mut rng = crate::Streams::new(1).rng(crate::Subsystem::Thread);
        let mut t = thread(0.08);
        t.on_insertion(Point::new(-0.01, 0.0, -0.11), &mut rng);
        t.on_extraction(
            Point::new(-0.005, 0.0, -0.12),
            Point::new(0.005, 0.0, -0.12),
            0.01,
            Point::new(0.02, 0.0, -0.11),
        );
        for k in 1..=150 {
            t.follow(Point::new(0.02 + 0.001 * f64::from(k), 0.0, -0.11), &[]);
        }
        assert!(t.short, "8 cm of thread cannot reach 17 cm");
    }

    #[test]
    fn a_jaw_closing_on_a_link_catches_it_and_one_a_centimetre_away_does_not() {
        let mut t = thread(0.1);
        t.settle(Point::new(-0.03, 0.0, -0.09), &[]);
        let at = t.free.points[10];
        let down = UnitQuaternion::from_axis_angle(&Vector::x_axis(), std::f64::consts::PI);
        let blades =
            |p: Point| tool_capsules(&Pose::from_parts(Translation3::from(p.coords), down), 0.0)[0];
        let mut near = t.clone();
        near.on_grasp(&blades(at + Vector::new(0.0, 0.0, 0.001)), false);
        assert!(near.caught);
        let mut far = t.clone();
        far.on_grasp(&blades(at + Vector::new(0.0, 0.0, 0.011)), false);
        assert!(!far.caught);
    }

    #[test]
    fn bad_parameters_are_refused() {
        for c in [
            ThreadConfig {
                friction: -1.0,
                ..ThreadConfig::default()
            },
            ThreadConfig {
                slides_through: 0,
                ..ThreadConfig::default()
            },
            ThreadConfig {
                length_m: 2.0,
                ..ThreadConfig::default()
            },
            ThreadConfig {
                segment_m: 0.0,
                ..ThreadConfig::default()
            },
            ThreadConfig {
                iterations: 0,
                ..ThreadConfig::default()
            },
        ] {
            assert!(c.validate().is_err(), "{c:?}");
        }
    }
}
