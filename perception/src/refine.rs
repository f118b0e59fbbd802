//! The fitted circle refined against the needle masks of both views, and what the images
//! say of it.
//!
//! A cloud from disparities carries the matcher's depth error: on a rig whose pixel of
//! disparity spans a millimetre of depth at the needle, the wire's points scatter over more
//! than the RANSAC thresholds, and a glint or a jaw's metal beside the wire pulls the circle
//! off it. The masks themselves are sharp to a pixel in both views, and a circle of known
//! radius seen in two rectified views is fixed by where its projections lie: depth comes
//! from the horizontal offset between the two curves along the whole arc, not from one
//! pixel's match. So the circle is moved (six degrees of freedom about its centre) until
//! its projections run down the middle of the wire in both masks — for each sample along
//! the arc, the middle of the mask's run across the projected curve is the target, the
//! point-to-line offset the residual (the classic normal-search tracker, as in Harris's
//! RAPiD), Gauss–Newton with Levenberg damping and Huber weights — and then asked how much
//! of it the images support: the share of samples whose wire lies on the projected curve
//! in both views, and the arc the left view's mask covers along it.
//!
//! Written here because it is a few dozen lines over the project's own masks and
//! calibration; no crate offers a curve-to-mask tracker.

use crate::fit::{Circle, plane_basis};
use crate::segment::Masks;
use nalgebra::{Matrix3, Matrix6, Rotation3, SymmetricEigen, Vector3, Vector6};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use stitch_robot::{Point, StereoCalibration, Vector};

/// Samples along the arc per refinement.
const SAMPLES: usize = 64;
/// Gauss–Newton iterations at most.
const ITERATIONS: usize = 12;
/// Huber's threshold on a residual, pixels.
const HUBER_PX: f64 = 1.0;

/// The refined circle and the images' support for it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Refined {
    /// The circle, robot frame.
    pub circle: Circle,
    /// Share of the arc's samples whose wire lies within the tolerance of the projected
    /// curve in both views.
    pub support: f64,
    /// RMS of those samples' offsets from the middle of the wire, both views, pixels.
    pub rms_px: f64,
    /// The arc's start about the refined circle's `plane_basis`, rad (the same point of the
    /// needle as the start given).
    pub start: f64,
}

/// One view of a rectified pair: the left, or the right (shifted by the baseline).
#[derive(Clone, Copy, Debug)]
struct View<'a> {
    masks: &'a Masks,
    right: bool,
}

/// The two views and the camera.
#[derive(Debug)]
pub struct Images<'a> {
    calibration: &'a StereoCalibration,
    to_camera: stitch_robot::Pose,
    views: [View<'a>; 2],
    /// The wire's diameter, m (how far across the curve to look for it).
    wire_m: f64,
}

impl<'a> Images<'a> {
    /// Both views' needle masks under `calibration`.
    pub fn new(
        calibration: &'a StereoCalibration,
        left: &'a Masks,
        right: &'a Masks,
        wire_m: f64,
    ) -> Self {
        Self {
            calibration,
            to_camera: calibration.camera_to_robot.inverse(),
            views: [
                View {
                    masks: left,
                    right: false,
                },
                View {
                    masks: right,
                    right: true,
                },
            ],
            wire_m,
        }
    }

    /// Where robot-frame `p` falls in a view, pixels (continuous: pixel `(x, y)` covers
    /// `[x, x + 1) × [y, y + 1)`), and its depth.
    fn project(&self, p: &Point, right: bool) -> Option<([f64; 2], f64)> {
        let c = self.calibration;
        let q = self.to_camera * p;
        if q.z <= 1e-4 {
            return None;
        }
        let mut u = c.fx * q.x / q.z + c.cx;
        if right {
            u -= c.fx * c.baseline_m / q.z;
        }
        Some(([u, c.fy * q.y / q.z + c.cy], q.z))
    }

    /// The projected curve's unit normal at `p` (tangent `t`) in a view, and `p`'s pixel.
    fn normal_at(&self, p: &Point, t: &Vector, right: bool) -> Option<([f64; 2], [f64; 2], f64)> {
        let (a, z) = self.project(p, right)?;
        let (b, _) = self.project(&(p + t * 1e-4), right)?;
        let (tu, tv) = (b[0] - a[0], b[1] - a[1]);
        let n = tu.hypot(tv);
        (n > 1e-9).then(|| (a, [-tv / n, tu / n], z))
    }

    /// The middle of the mask's run across the curve at pixel `a` along normal `n`, as an
    /// offset along `n`, pixels: the run containing `a` or the nearest one within `reach`.
    fn run_middle(&self, view: View, a: [f64; 2], n: [f64; 2], reach: f64) -> Option<f64> {
        const STEP: f64 = 0.5;
        let k = (reach / STEP).ceil() as i32;
        let mut best: Option<(f64, f64)> = None; // (distance from 0, middle)
        let mut run: Option<(f64, f64)> = None; // (first, last) offsets in the run
        let close = |run: (f64, f64), best: &mut Option<(f64, f64)>| {
            let d = if run.0 <= 0.0 && run.1 >= 0.0 {
                0.0
            } else {
                run.0.abs().min(run.1.abs())
            };
            if best.is_none_or(|b| d < b.0) {
                *best = Some((d, (run.0 + run.1) / 2.0));
            }
        };
        for i in -k..=k {
            let s = f64::from(i) * STEP;
            let (x, y) = (a[0] + n[0] * s, a[1] + n[1] * s);
            let on = x >= 0.0 && y >= 0.0 && view.masks.is_needle(x as u32, y as u32);
            match (on, run) {
                (true, None) => run = Some((s, s)),
                (true, Some((f, _))) => run = Some((f, s)),
                (false, Some(r)) => {
                    close(r, &mut best);
                    run = None;
                }
                (false, None) => {}
            }
        }
        if let Some(r) = run {
            close(r, &mut best);
        }
        best.map(|b| b.1)
    }

    /// How far across the curve to look, pixels, at depth `z`.
    fn reach(&self, z: f64) -> f64 {
        2.0 * self.calibration.fx * self.wire_m / z + 4.0
    }

    /// Samples of `circle` at `angles` (about its `plane_basis`): each point and tangent.
    fn samples(circle: &Circle, angles: impl Iterator<Item = f64>) -> Vec<(Point, Vector)> {
        let (e1, e2) = plane_basis(&circle.normal);
        angles
            .map(|a| {
                let (s, c) = a.sin_cos();
                (
                    circle.center + (e1 * c + e2 * s) * circle.radius,
                    e2 * c - e1 * s,
                )
            })
            .collect()
    }

    /// The circle moved so that its arc from `start` over `extent` (rad, about the circle's
    /// `plane_basis`) runs down the wire in both views; `None` if too little of it finds
    /// the wire.
    pub fn refine(
        &self,
        circle: &Circle,
        start: f64,
        extent: f64,
        tolerance_px: f64,
    ) -> Option<Refined> {
        let angles = |c: &Circle, from: &Circle| {
            let shift = carried_shift(from, c);
            (0..SAMPLES).map(move |i| start + shift + extent * (i as f64 + 0.5) / SAMPLES as f64)
        };
        let first = *circle;
        let mut c = *circle;
        for _ in 0..ITERATIONS {
            let pts = Self::samples(&c, angles(&c, &first));
            // (sample, view, pixel normal, target pixel)
            let mut corr: Vec<(Point, bool, [f64; 2], [f64; 2])> = Vec::new();
            for (p, t) in &pts {
                for v in self.views {
                    let Some((a, n, z)) = self.normal_at(p, t, v.right) else {
                        continue;
                    };
                    if let Some(m) = self.run_middle(v, a, n, self.reach(z)) {
                        corr.push((*p, v.right, n, [a[0] + n[0] * m, a[1] + n[1] * m]));
                    }
                }
            }
            if corr.len() < SAMPLES / 2 {
                return None;
            }
            let centre = c.center;
            let moved = |x: &Vector6<f64>, p: &Point| {
                let rot = Rotation3::new(Vector3::new(x[0], x[1], x[2]));
                centre + Vector3::new(x[3], x[4], x[5]) + rot * (p - centre)
            };
            let residual = |x: &Vector6<f64>, k: &(Point, bool, [f64; 2], [f64; 2])| {
                let (q, _) = self.project(&moved(x, &k.0), k.1)?;
                Some(k.2[0] * (q[0] - k.3[0]) + k.2[1] * (q[1] - k.3[1]))
            };
            let steps = [1e-5, 1e-5, 1e-5, 1e-6, 1e-6, 1e-6];
            let zero = Vector6::zeros();
            let mut h = Matrix6::zeros();
            let mut g = Vector6::zeros();
            for k in &corr {
                let Some(r0) = residual(&zero, k) else {
                    continue;
                };
                let mut j = Vector6::zeros();
                for (i, s) in steps.iter().enumerate() {
                    let mut x = zero;
                    x[i] = *s;
                    j[i] = (residual(&x, k)? - r0) / s;
                }
                let w = if r0.abs() <= HUBER_PX {
                    1.0
                } else {
                    HUBER_PX / r0.abs()
                };
                h += j * j.transpose() * w;
                g += j * (w * r0);
            }
            // Levenberg damping; the rotation about the circle's own axis moves the arc
            // along itself and is barely seen, so a small ridge keeps it still.
            let mut damped = h;
            for i in 0..6 {
                damped[(i, i)] += 1e-3 * h[(i, i)] + 1e-9 * h.trace().max(1.0);
            }
            let dx = damped.lu().solve(&(-g))?;
            let rot = Rotation3::new(Vector3::new(dx[0], dx[1], dx[2]));
            c = Circle {
                center: c.center + Vector3::new(dx[3], dx[4], dx[5]),
                normal: (rot * c.normal).normalize(),
                radius: c.radius,
            };
            if dx.fixed_rows::<3>(3).norm() < 1e-6 && dx.fixed_rows::<3>(0).norm() < 1e-5 {
                break;
            }
        }
        let pts = Self::samples(&c, angles(&c, &first));
        let (mut held, mut sq, mut n) = (0usize, 0.0, 0usize);
        for (p, t) in &pts {
            let mut both = true;
            for v in self.views {
                let m = self
                    .normal_at(p, t, v.right)
                    .and_then(|(a, nn, z)| self.run_middle(v, a, nn, self.reach(z)));
                match m {
                    Some(m) if m.abs() <= tolerance_px => {
                        sq += m * m;
                        n += 1;
                    }
                    _ => both = false,
                }
            }
            held += usize::from(both);
        }
        Some(Refined {
            circle: c,
            support: held as f64 / pts.len() as f64,
            rms_px: if n == 0 {
                f64::INFINITY
            } else {
                (sq / n as f64).sqrt()
            },
            start: start + carried_shift(&first, &c),
        })
    }

    /// The circles of the needle's radius whose left projection is the ellipse the left
    /// mask draws: an ellipse found by RANSAC over the mask's pixels (five at a time, the
    /// Sampson distance within the wire's half width) and refitted to its inliers, then the
    /// two circles of that radius the cone through it holds (Chen, Wu and Wada's
    /// decomposition), robot frame. Empty if the mask draws no ellipse. Needs no disparity:
    /// for a cloud too noisy or cluttered to fit, this is where the refinement starts.
    pub fn circles_from_left_silhouette(&self, radius_m: f64, rng: &mut ChaCha8Rng) -> Vec<Circle> {
        let c = self.calibration;
        let m = self.views[0].masks;
        let r = &m.roi;
        let mut px: Vec<[f64; 2]> = Vec::new();
        for y in r.y0..r.y1 {
            for x in r.x0..r.x1 {
                if m.is_needle(x, y) {
                    px.push([f64::from(x) + 0.5, f64::from(y) + 0.5]);
                }
            }
        }
        if px.len() < 20 {
            return Vec::new();
        }
        if px.len() > 1500 {
            let step = px.len() as f64 / 1500.0;
            px = (0..1500).map(|i| px[(i as f64 * step) as usize]).collect();
        }
        // Centred and scaled pixel coordinates keep the conic's equations well conditioned.
        let n = px.len() as f64;
        let (u0, v0) = (
            px.iter().map(|p| p[0]).sum::<f64>() / n,
            px.iter().map(|p| p[1]).sum::<f64>() / n,
        );
        let scale = 100.0;
        let pts: Vec<[f64; 2]> = px
            .iter()
            .map(|p| [(p[0] - u0) / scale, (p[1] - v0) / scale])
            .collect();
        // Within the wire's half width and a pixel of the ellipse, in the scaled units: the
        // wire's width from the mask, the shorter of each pixel's horizontal and vertical
        // runs (between its width and √2 times it), the median over the mask.
        let tol = (0.6 * wire_width_px(m)).max(2.5) / scale;
        let mut best: Option<(usize, [f64; 6])> = None;
        for _ in 0..300 {
            let idx: Vec<usize> = (0..5).map(|_| rng.random_range(0..pts.len())).collect();
            let Some(conic) = fit_conic(idx.iter().map(|&i| pts[i])) else {
                continue;
            };
            if !is_ellipse(&conic) {
                continue;
            }
            let count = pts.iter().filter(|p| sampson(&conic, p) <= tol).count();
            if best.is_none_or(|b| count > b.0) {
                best = Some((count, conic));
            }
        }
        let Some((_, mut conic)) = best else {
            return Vec::new();
        };
        for _ in 0..3 {
            let inliers: Vec<[f64; 2]> = pts
                .iter()
                .copied()
                .filter(|p| sampson(&conic, p) <= tol)
                .collect();
            match fit_conic(inliers.into_iter()) {
                Some(k) if is_ellipse(&k) => conic = k,
                _ => break,
            }
        }
        // The conic in normalised camera coordinates: p = M x̃.
        let [a, b, cc, d, e, f] = conic;
        let cp = Matrix3::new(
            a,
            b / 2.0,
            d / 2.0,
            b / 2.0,
            cc,
            e / 2.0,
            d / 2.0,
            e / 2.0,
            f,
        );
        let mm = Matrix3::new(
            c.fx / scale,
            0.0,
            (c.cx - u0) / scale,
            0.0,
            c.fy / scale,
            (c.cy - v0) / scale,
            0.0,
            0.0,
            1.0,
        );
        let q = mm.transpose() * cp * mm;
        cone_circles(&q, radius_m)
            .into_iter()
            .map(|(centre, normal)| Circle {
                center: c.camera_to_robot * Point::from(centre),
                normal: c.camera_to_robot.rotation * normal,
                radius: radius_m,
            })
            .collect()
    }

    /// The arc of `circle` the left view's mask covers (within `tolerance_px`), stepping
    /// `step` rad around it: the longest run of covered steps, gaps up to `gap` bridged, as
    /// (start, extent) about the circle's `plane_basis`; `None` if nothing is covered.
    pub fn left_arc(
        &self,
        circle: &Circle,
        tolerance_px: f64,
        step: f64,
        gap: f64,
    ) -> Option<(f64, f64)> {
        let k = (std::f64::consts::TAU / step).round() as usize;
        let pts = Self::samples(circle, (0..k).map(|i| i as f64 * step));
        let v = self.views[0];
        let seen: Vec<bool> = pts
            .iter()
            .map(|(p, t)| {
                self.normal_at(p, t, false)
                    .and_then(|(a, n, z)| self.run_middle(v, a, n, self.reach(z)))
                    .is_some_and(|m| m.abs() <= tolerance_px)
            })
            .collect();
        let first_unseen = seen.iter().position(|s| !s)?;
        // Runs around the circle starting after an unseen step; gaps up to `gap` bridged.
        let max_gap = (gap / step).floor() as usize;
        let mut best: Option<(usize, usize)> = None; // (start index, length)
        let mut run: Option<(usize, usize, usize)> = None; // (start, length, gap so far)
        for j in 1..=k {
            let i = (first_unseen + j) % k;
            match (seen[i], run) {
                (true, None) => run = Some((i, 1, 0)),
                (true, Some((s0, len, g))) => run = Some((s0, len + g + 1, 0)),
                (false, Some((s0, len, g))) if g < max_gap => run = Some((s0, len, g + 1)),
                (false, Some((s0, len, _))) => {
                    if best.is_none_or(|b| len > b.1) {
                        best = Some((s0, len));
                    }
                    run = None;
                }
                (false, None) => {}
            }
        }
        if let Some((s0, len, _)) = run {
            if best.is_none_or(|b| len > b.1) {
                best = Some((s0, len));
            }
        }
        best.map(|(s0, len)| (s0 as f64 * step, len as f64 * step))
    }

    /// Where the wire's middle is across the circle at `angle` in each view (left, right),
    /// as an offset from the projected curve, pixels; `None` where no wire is near.
    pub fn offsets_at(&self, circle: &Circle, angle: f64) -> [Option<f64>; 2] {
        let pts = Self::samples(circle, std::iter::once(angle));
        let (p, t) = &pts[0];
        self.views.map(|v| {
            self.normal_at(p, t, v.right)
                .and_then(|(a, n, z)| self.run_middle(v, a, n, self.reach(z)))
        })
    }

    /// Whether the wire lies on the circle at `angle` in both views (its middle within
    /// `tolerance_px` of the projected curve).
    pub fn seen_at(&self, circle: &Circle, angle: f64, tolerance_px: f64) -> bool {
        self.offsets_at(circle, angle)
            .iter()
            .all(|m| m.is_some_and(|m| m.abs() <= tolerance_px))
    }
}

/// The same point of the needle after its circle moved from `from` to `to`: the angle to add
/// to an angle about `from`'s `plane_basis` to get it about `to`'s (the basis carried by the
/// rotation between the two normals).
fn carried_shift(from: &Circle, to: &Circle) -> f64 {
    let (o1, _) = plane_basis(&from.normal);
    let (n1, n2) = plane_basis(&to.normal);
    let carried = Rotation3::rotation_between(&from.normal, &to.normal).map_or(o1, |r| r * o1);
    carried.dot(&n2).atan2(carried.dot(&n1))
}

/// The median over a needle mask's pixels of the shorter of the horizontal and vertical
/// runs through each, pixels (0 for an empty mask).
fn wire_width_px(m: &Masks) -> f64 {
    let (w, h) = (m.roi.width() as usize, m.roi.height() as usize);
    let at = |x: usize, y: usize| m.needle[y * w + x] != 0;
    let mut hrun = vec![0u32; w * h];
    for y in 0..h {
        for (x0, x1) in runs(w, |x| at(x, y)) {
            hrun[y * w + x0..y * w + x1].fill((x1 - x0) as u32);
        }
    }
    let mut widths: Vec<u32> = Vec::new();
    for x in 0..w {
        for (y0, y1) in runs(h, |y| at(x, y)) {
            widths.extend((y0..y1).map(|y| hrun[y * w + x].min((y1 - y0) as u32)));
        }
    }
    if widths.is_empty() {
        return 0.0;
    }
    let mid = widths.len() / 2;
    f64::from(*widths.select_nth_unstable(mid).1)
}

/// The runs `[start, end)` of indices below `len` where `on` holds.
fn runs(len: usize, on: impl Fn(usize) -> bool) -> Vec<(usize, usize)> {
    let mut out = Vec::new();
    let mut i = 0;
    while i < len {
        if on(i) {
            let start = i;
            while i < len && on(i) {
                i += 1;
            }
            out.push((start, i));
        } else {
            i += 1;
        }
    }
    out
}

/// The conic `a x² + b xy + c y² + d x + e y + f = 0` through the points (least squares,
/// unit coefficient vector): the eigenvector of the scatter matrix with the least
/// eigenvalue. `None` for fewer than five points.
fn fit_conic(points: impl Iterator<Item = [f64; 2]>) -> Option<[f64; 6]> {
    let mut s = Matrix6::<f64>::zeros();
    let mut n = 0;
    for [x, y] in points {
        let row = Vector6::new(x * x, x * y, y * y, x, y, 1.0);
        s += row * row.transpose();
        n += 1;
    }
    if n < 5 {
        return None;
    }
    let eig = SymmetricEigen::new(s);
    let (i, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let v = eig.eigenvectors.column(i);
    v.iter()
        .all(|x| x.is_finite())
        .then(|| [v[0], v[1], v[2], v[3], v[4], v[5]])
}

fn is_ellipse(k: &[f64; 6]) -> bool {
    k[1] * k[1] - 4.0 * k[0] * k[2] < 0.0
}

/// The Sampson distance of a point from a conic (its first-order geometric distance).
fn sampson(k: &[f64; 6], p: &[f64; 2]) -> f64 {
    let [a, b, c, d, e, f] = *k;
    let [x, y] = *p;
    let val = a * x * x + b * x * y + c * y * y + d * x + e * y + f;
    let gx = 2.0 * a * x + b * y + d;
    let gy = b * x + 2.0 * c * y + e;
    val.abs() / gx.hypot(gy).max(1e-12)
}

/// The circles of radius `r` whose image is the cone `xᵀ Q x = 0` (camera frame, `x` in
/// normalised coordinates): centre and unit normal of each, in front of the camera. Chen,
/// Wu and Wada, "Camera calibration with two arbitrary coplanar circles" (ECCV 2004), §3.
fn cone_circles(q: &Matrix3<f64>, r: f64) -> Vec<(Vector3<f64>, Vector3<f64>)> {
    let eig = SymmetricEigen::new(*q);
    let mut l: Vec<(f64, Vector3<f64>)> = (0..3)
        .map(|i| (eig.eigenvalues[i], eig.eigenvectors.column(i).into_owned()))
        .collect();
    // Two eigenvalues of one sign and one of the other: scale so that two are positive.
    let positive = l.iter().filter(|v| v.0 > 0.0).count();
    if positive == 1 {
        for v in &mut l {
            v.0 = -v.0;
        }
    } else if positive != 2 {
        return Vec::new();
    }
    // λ1 ≥ λ2 > 0 > λ3.
    l.sort_by(|a, b| b.0.total_cmp(&a.0));
    let ((l1, v1), (l2, v2), (l3, v3)) = (l[0], l[1], l[2]);
    if !(l2 > 0.0 && l3 < 0.0) {
        return Vec::new();
    }
    let v = Matrix3::from_columns(&[v1, v2, v3]);
    let a = ((l1 - l2) / (l1 - l3)).sqrt();
    let b = ((l2 - l3) / (l1 - l3)).sqrt();
    let z0 = r * l2 / (-l1 * l3).sqrt();
    let mut out = Vec::new();
    for s2 in [1.0, -1.0] {
        let centre = v * Vector3::new(s2 * l3 / l2 * a, 0.0, -l1 / l2 * b) * z0;
        let normal = v * Vector3::new(s2 * a, 0.0, -b);
        let (centre, normal) = if centre.z < 0.0 {
            (-centre, -normal)
        } else {
            (centre, normal)
        };
        if centre.iter().all(|x| x.is_finite()) && normal.iter().all(|x| x.is_finite()) {
            out.push((centre, normal.normalize()));
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::Rect;
    use rand_chacha::rand_core::SeedableRng;
    use stitch_robot::Pose;

    fn camera() -> StereoCalibration {
        StereoCalibration {
            fx: 1200.0,
            fy: 1200.0,
            cx: 640.0,
            cy: 480.0,
            baseline_m: 0.01,
            width: 1280,
            height: 960,
            camera_to_robot: Pose::identity(),
        }
    }

    /// Both views' masks of the arc `from`..`to` (rad about the circle's `plane_basis`) of
    /// a wire `wire_px` pixels wide.
    fn masks(
        c: &StereoCalibration,
        circle: &Circle,
        from: f64,
        to: f64,
        wire_px: f64,
    ) -> [Masks; 2] {
        [false, true].map(|right| {
            let roi = Rect {
                x0: 0,
                y0: 0,
                x1: c.width,
                y1: c.height,
            };
            let mut needle = vec![0u8; (c.width * c.height) as usize];
            let (e1, e2) = plane_basis(&circle.normal);
            for i in 0..=4000 {
                let a = from + (to - from) * f64::from(i) / 4000.0;
                let p = circle.center + (e1 * a.cos() + e2 * a.sin()) * circle.radius;
                let mut u = c.fx * p.x / p.z + c.cx;
                if right {
                    u -= c.fx * c.baseline_m / p.z;
                }
                let v = c.fy * p.y / p.z + c.cy;
                let h = wire_px / 2.0;
                for y in (v - h).floor() as i64..=(v + h).ceil() as i64 {
                    for x in (u - h).floor() as i64..=(u + h).ceil() as i64 {
                        let (dx, dy) = (x as f64 + 0.5 - u, y as f64 + 0.5 - v);
                        if dx * dx + dy * dy <= h * h
                            && (0..i64::from(c.width)).contains(&x)
                            && (0..i64::from(c.height)).contains(&y)
                        {
                            needle[(y as u32 * c.width + x as u32) as usize] = 1;
                        }
                    }
                }
            }
            Masks {
                roi,
                thread: vec![0; needle.len()],
                needle,
            }
        })
    }

    fn truth() -> Circle {
        Circle {
            center: Point::new(0.01, -0.005, 0.11),
            normal: Vector::new(0.3, -0.5, -0.8).normalize(),
            radius: 0.012,
        }
    }

    /// The camera, the true circle, and both views' masks of half of it (a 7 px wire).
    fn half_circle_seen() -> (StereoCalibration, Circle, [Masks; 2]) {
        let (c, t) = (camera(), truth());
        let m = masks(&c, &t, 0.3, 0.3 + std::f64::consts::PI, 7.0);
        (c, t, m)
    }

    fn close(a: &Circle, b: &Circle) -> (f64, f64) {
        (
            (a.center - b.center).norm(),
            a.normal.dot(&b.normal).abs().min(1.0).acos().to_degrees(),
        )
    }

    #[test]
    fn the_left_silhouette_of_a_half_circle_gives_the_circle_among_its_two_candidates() {
        let (c, t, [l, r]) = half_circle_seen();
        let images = Images::new(&c, &l, &r, 0.0007);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let cands = images.circles_from_left_silhouette(0.012, &mut rng);
        assert_eq!(cands.len(), 2, "{cands:?}");
        let best = cands
            .iter()
            .map(|k| close(k, &t))
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .expect("a candidate");
        // From one view's silhouette alone: depth from the ellipse's size.
        assert!(best.0 < 0.002 && best.1 < 4.0, "{best:?} {cands:?}");
    }

    #[test]
    fn a_circle_off_in_depth_and_tilt_is_moved_onto_the_wire_in_both_views() {
        let (c, t, [l, r]) = half_circle_seen();
        let images = Images::new(&c, &l, &r, 0.0007);
        let rot = Rotation3::new(Vector3::new(0.03, -0.02, 0.0));
        // 1.5 mm farther along the line of sight (6 px of disparity at this rig), 2° tilted.
        let off = Circle {
            center: t.center + t.center.coords.normalize() * 0.0015,
            normal: rot * t.normal,
            radius: t.radius,
        };
        let (start, extent) = images
            .left_arc(&off, 3.0, 1f64.to_radians(), 0.2)
            .expect("an arc");
        assert!(extent > 2.0, "{extent}");
        let f = images.refine(&off, start, extent, 1.5).expect("refined");
        let (d, deg) = close(&f.circle, &t);
        assert!(d < 1e-4 && deg < 0.5, "{d} m, {deg}°: {f:?}");
        assert!(f.support > 0.9 && f.rms_px < 0.5, "{f:?}");
    }

    #[test]
    fn the_silhouettes_candidate_the_right_view_holds_is_the_circle() {
        let (c, t, [l, r]) = half_circle_seen();
        let images = Images::new(&c, &l, &r, 0.0007);
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        let best = images
            .circles_from_left_silhouette(0.012, &mut rng)
            .iter()
            .filter_map(|k| {
                let (start, extent) = images.left_arc(k, 3.0, 1f64.to_radians(), 0.2)?;
                images.refine(k, start, extent, 1.5)
            })
            .max_by(|a, b| a.support.total_cmp(&b.support))
            .expect("a refined candidate");
        let (d, deg) = close(&best.circle, &t);
        assert!(d < 1e-4 && deg < 0.5, "{d} m, {deg}°: {best:?}");
    }

    #[test]
    fn a_circle_the_masks_do_not_show_is_not_held() {
        let (c, t, [l, r]) = half_circle_seen();
        let images = Images::new(&c, &l, &r, 0.0007);
        let elsewhere = Circle {
            center: t.center + Vector3::new(0.02, 0.0, 0.0),
            ..t
        };
        let held = images
            .refine(&elsewhere, 0.0, std::f64::consts::PI, 1.5)
            .is_some_and(|f| f.support > 0.5);
        assert!(!held);
    }
}
