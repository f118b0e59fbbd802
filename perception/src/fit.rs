//! Stages 4–6: RANSAC plane (the needle's normal), RANSAC circle of known radius in that
//! plane (its centre), then a joint least-squares refinement of centre and normal, and the
//! arc's two ends from the angular extent of the inliers.
//!
//! Why the ends come from the angular extent and not from the paper's "two most distant
//! inliers": on a circle of known radius the extent is the robust statistic (one outlier
//! moves the farthest pair; it cannot move the extent of points that lie on the circle),
//! and it costs a sort instead of a quadratic search. PERCEPTION-NOTES saw ≈ 3× smaller
//! endpoint errors with it; `stitch bench perception` measures ours.

use nalgebra::{Matrix3, Vector2};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use stitch_robot::{Point, Vector};

/// A plane: unit normal `n` and offset, `n · p = offset`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    /// Unit normal.
    pub normal: Vector,
    /// `n · p` for points on it, m.
    pub offset: f64,
}

impl Plane {
    /// Signed distance of `p`, m.
    pub fn distance(&self, p: &Point) -> f64 {
        self.normal.dot(&p.coords) - self.offset
    }
}

/// How much a point's offset along its own viewing ray counts, against an offset across
/// it. Stereo places a point across the view to a fraction of a pixel, but along the ray
/// only to a fraction of the rig's disparity step (depth² / (focal length × baseline)), which
/// on a narrow-baseline rig is several times coarser: a distance that counts both alike
/// takes the needle's own noisy points for clutter. A distance here is measured with the
/// ray's part scaled by √(1 − `k`) (`k` = 0: as it is).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayDiscount {
    /// Unit direction from the camera to the point.
    pub dir: Vector,
    /// 1 − s², where s (0 < s ≤ 1) scales the offset along `dir`.
    pub k: f64,
}

impl RayDiscount {
    /// The length of the offset `r` from a point, its part along the ray discounted.
    pub fn length(&self, r: &Vector) -> f64 {
        (r.norm_squared() - self.k * r.dot(&self.dir).powi(2))
            .max(0.0)
            .sqrt()
    }

    /// The discounted distance of the point (offset `h` along `normal`) from a plane: the
    /// least discounted length of an offset that reaches the plane.
    pub fn plane_distance(&self, h: f64, normal: &Vector) -> f64 {
        // The least of √(xᵀMx) over x with n·x = h, M = I − k·d dᵀ, is |h| / √(nᵀM⁻¹n), and
        // M⁻¹ = I + k / (1 − k) · d dᵀ.
        let c = normal.dot(&self.dir);
        h.abs() / (1.0 + self.k / (1.0 - self.k) * c * c).sqrt()
    }
}

/// The distance of `points[i]` from the circle, its ray's part discounted where `rays`
/// gives one (`rays` is empty, or one for each point).
fn circle_distance(c: &Circle, points: &[Point], rays: &[RayDiscount], i: usize) -> f64 {
    match rays.get(i) {
        Some(d) => d.length(&c.offset(&points[i])),
        None => c.distance(&points[i]),
    }
}

/// The distance of `points[i]` from the plane, discounted as [`circle_distance`]'s.
fn plane_distance(p: &Plane, points: &[Point], rays: &[RayDiscount], i: usize) -> f64 {
    let h = p.distance(&points[i]);
    match rays.get(i) {
        Some(d) => d.plane_distance(h, &p.normal),
        None => h.abs(),
    }
}

/// RANSAC parameters.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RansacParams {
    /// Most distance of a plane inlier, m.
    pub plane_threshold_m: f64,
    /// Most distance of a circle inlier from the circle, m.
    pub circle_threshold_m: f64,
    /// Hypotheses tried, at most.
    pub iterations: usize,
    /// Stop early when this share of points are inliers.
    pub early_stop_share: f64,
}

impl Default for RansacParams {
    fn default() -> Self {
        Self {
            plane_threshold_m: 0.0006,
            circle_threshold_m: 0.0006,
            iterations: 200,
            early_stop_share: 0.9,
        }
    }
}

/// The least-squares plane through `points` (the smallest eigenvector of their scatter).
pub fn fit_plane(points: &[Point]) -> Option<Plane> {
    if points.len() < 3 {
        return None;
    }
    let n = points.len() as f64;
    let mean = points.iter().fold(Vector::zeros(), |a, p| a + p.coords) / n;
    let mut scatter = Matrix3::zeros();
    for p in points {
        let d = p.coords - mean;
        scatter += d * d.transpose();
    }
    let eig = scatter.symmetric_eigen();
    let (k, _) = eig
        .eigenvalues
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    let normal = eig
        .eigenvectors
        .column(k)
        .into_owned()
        .try_normalize(1e-12)?;
    Some(Plane {
        normal,
        offset: normal.dot(&mean),
    })
}

/// RANSAC plane: the plane through three points with the most inliers, refitted to them.
/// Returns it and the inliers' indices. `rays`: none, or each point's [`RayDiscount`].
pub fn ransac_plane(
    points: &[Point],
    rays: &[RayDiscount],
    params: &RansacParams,
    rng: &mut ChaCha8Rng,
) -> Option<(Plane, Vec<usize>)> {
    if points.len() < 3 {
        return None;
    }
    let t = params.plane_threshold_m;
    let mut best: Option<(usize, Plane)> = None;
    for _ in 0..params.iterations {
        let i = rng.random_range(0..points.len());
        let j = rng.random_range(0..points.len());
        let k = rng.random_range(0..points.len());
        let n = (points[j] - points[i]).cross(&(points[k] - points[i]));
        let Some(n) = n.try_normalize(1e-12) else {
            continue;
        };
        let plane = Plane {
            normal: n,
            offset: n.dot(&points[i].coords),
        };
        let count = (0..points.len())
            .filter(|&i| plane_distance(&plane, points, rays, i) <= t)
            .count();
        if best.is_none_or(|(c, _)| count > c) {
            best = Some((count, plane));
            if count as f64 >= params.early_stop_share * points.len() as f64 {
                break;
            }
        }
    }
    let (_, plane) = best?;
    let inliers: Vec<usize> = (0..points.len())
        .filter(|&i| plane_distance(&plane, points, rays, i) <= t)
        .collect();
    let refit = fit_plane(&inliers.iter().map(|&i| points[i]).collect::<Vec<_>>())?;
    let inliers: Vec<usize> = (0..points.len())
        .filter(|&i| plane_distance(&refit, points, rays, i) <= t)
        .collect();
    Some((refit, inliers))
}

/// Two unit vectors spanning the plane with normal `n`.
pub fn plane_basis(n: &Vector) -> (Vector, Vector) {
    let helper = if n.x.abs() < 0.9 {
        Vector::x()
    } else {
        Vector::y()
    };
    let e1 = n.cross(&helper).normalize();
    let e2 = n.cross(&e1);
    (e1, e2)
}

/// The centres of the circles of radius `r` through 2D points `a` and `b` (none if they
/// are farther apart than `2r`).
fn centers_through(a: Vector2<f64>, b: Vector2<f64>, r: f64) -> Option<[Vector2<f64>; 2]> {
    let m = (a + b) / 2.0;
    let half = (b - a).norm() / 2.0;
    if half < 1e-9 || half > r {
        return None;
    }
    let h = (r * r - half * half).sqrt();
    let perp = Vector2::new(-(b - a).y, (b - a).x) / (2.0 * half);
    Some([m + perp * h, m - perp * h])
}

/// A circle of known radius in 3D.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Circle {
    /// Centre, m.
    pub center: Point,
    /// Unit normal of its plane (sign arbitrary).
    pub normal: Vector,
    /// Radius, m.
    pub radius: f64,
}

impl Circle {
    /// The offset of `p` from the circle's nearest point (for a point on the axis, from the
    /// ring's nearest point along the first of [`plane_basis`]'s directions), m.
    pub fn offset(&self, p: &Point) -> Vector {
        let d = p - self.center;
        let h = d.dot(&self.normal);
        let inplane = d - self.normal * h;
        let along = inplane
            .try_normalize(1e-15)
            .unwrap_or_else(|| plane_basis(&self.normal).0);
        d - along * self.radius
    }

    /// Distance from `p` to the circle (the ring, not the disc), m.
    pub fn distance(&self, p: &Point) -> f64 {
        let d = p - self.center;
        let h = d.dot(&self.normal);
        let inplane = (d - self.normal * h).norm();
        ((inplane - self.radius).powi(2) + h * h).sqrt()
    }
}

/// RANSAC circle of radius `r` in `plane` through (projections of) `points`: hypotheses from
/// pairs of points, the one with the most inliers, then the centre and normal refined by
/// Gauss–Newton on the points' distances to the 3D circle. Returns it and its inliers.
pub fn ransac_circle(
    points: &[Point],
    rays: &[RayDiscount],
    plane: &Plane,
    r: f64,
    params: &RansacParams,
    rng: &mut ChaCha8Rng,
) -> Option<(Circle, Vec<usize>)> {
    if points.len() < 3 {
        return None;
    }
    let (e1, e2) = plane_basis(&plane.normal);
    let origin = plane.normal * plane.offset;
    let flat: Vec<Vector2<f64>> = points
        .iter()
        .map(|p| {
            let d = p.coords - origin;
            Vector2::new(d.dot(&e1), d.dot(&e2))
        })
        .collect();
    // Each ray's direction in the plane's basis and its discount: a point's offset from a
    // circle in the plane is radial.
    let flat_rays: Vec<(Vector2<f64>, f64)> = rays
        .iter()
        .map(|d| (Vector2::new(d.dir.dot(&e1), d.dir.dot(&e2)), d.k))
        .collect();
    let off = |i: usize, c: Vector2<f64>| -> f64 {
        let q = flat[i] - c;
        let n = q.norm();
        let radial = (n - r).abs();
        match flat_rays.get(i) {
            Some((dir, k)) if n > 1e-15 => {
                let along = dir.dot(&q) / n;
                radial * (1.0 - k * along * along).max(0.0).sqrt()
            }
            _ => radial,
        }
    };
    let t = params.circle_threshold_m;
    let mut best: Option<(usize, Vector2<f64>)> = None;
    for _ in 0..params.iterations {
        let i = rng.random_range(0..flat.len());
        let j = rng.random_range(0..flat.len());
        // Pairs too close give poorly placed centres.
        if (flat[i] - flat[j]).norm() < 0.4 * r {
            continue;
        }
        let Some(cs) = centers_through(flat[i], flat[j], r) else {
            continue;
        };
        for c in cs {
            let count = (0..flat.len()).filter(|&i| off(i, c) <= t).count();
            if best.is_none_or(|(n, _)| count > n) {
                best = Some((count, c));
            }
        }
        if best.is_some_and(|(n, _)| n as f64 >= params.early_stop_share * flat.len() as f64) {
            break;
        }
    }
    let (_, c2) = best?;
    let circle = Circle {
        center: Point::from(origin + e1 * c2.x + e2 * c2.y),
        normal: plane.normal,
        radius: r,
    };
    Some(refined_on_inliers(points, rays, circle, t))
}

/// RANSAC circle of radius `r` in space, with no plane first: hypotheses from the circle
/// through three points, kept when its radius is within 15 % of `r`; the best refined as
/// [`ransac_circle`]'s is. For a cloud whose needle points are a minority (wet glare on the
/// tissue beside it, a jaw's metal): the plane with the most points is then the clutter's,
/// and no circle on it holds the needle. A hypothesis scores its inliers times their share
/// of the points within `zone_m` of it: in a dense field of glare any circle has many
/// inliers, and many more points just off it.
pub fn ransac_circle_free(
    points: &[Point],
    rays: &[RayDiscount],
    r: f64,
    zone_m: f64,
    params: &RansacParams,
    iterations: usize,
    rng: &mut ChaCha8Rng,
) -> Option<(Circle, Vec<usize>)> {
    if points.len() < 3 {
        return None;
    }
    let t = params.circle_threshold_m;
    let mut best: Option<((usize, usize), Circle)> = None;
    for _ in 0..iterations {
        let [a, b, c] = [(); 3].map(|_| points[rng.random_range(0..points.len())]);
        let Some(k) = circle_through(&a, &b, &c) else {
            continue;
        };
        // Points close together place the circle poorly; a radius far from the needle's is
        // not the needle.
        if (k.radius - r).abs() > 0.15 * r
            || (b - a).norm().min((c - b).norm()).min((a - c).norm()) < 0.3 * r
        {
            continue;
        }
        let k = Circle { radius: r, ..k };
        let (mut on, mut near) = (0usize, 0usize);
        for i in 0..points.len() {
            let d = circle_distance(&k, points, rays, i);
            on += usize::from(d <= t);
            near += usize::from(d <= zone_m);
        }
        // on × on / near, compared without division.
        let score = (on * on, near.max(1));
        if best.is_none_or(|(b, _)| score.0 * b.1 > b.0 * score.1) {
            best = Some((score, k));
        }
    }
    let (_, circle) = best?;
    Some(refined_on_inliers(points, rays, circle, t))
}

/// A RANSAC circle refined twice on its inliers (the points within `t` of it, m), and the
/// inliers of the refined circle.
fn refined_on_inliers(
    points: &[Point],
    rays: &[RayDiscount],
    mut circle: Circle,
    t: f64,
) -> (Circle, Vec<usize>) {
    let inliers_of = |c: &Circle| -> Vec<usize> {
        (0..points.len())
            .filter(|&i| circle_distance(c, points, rays, i) <= t)
            .collect()
    };
    let mut inliers = inliers_of(&circle);
    for _ in 0..2 {
        let pts: Vec<Point> = inliers.iter().map(|&i| points[i]).collect();
        let pts_rays: Vec<RayDiscount> = inliers
            .iter()
            .filter_map(|&i| rays.get(i).copied())
            .collect();
        circle = refine_circle(&pts, &pts_rays, circle, 8);
        inliers = inliers_of(&circle);
    }
    (circle, inliers)
}

/// The circle through three points (`None` if they are nearly on a line).
pub fn circle_through(a: &Point, b: &Point, c: &Point) -> Option<Circle> {
    let (u, v) = (b - a, c - a);
    let n = u.cross(&v);
    let n2 = n.norm_squared();
    if n2 < 1e-18 {
        return None;
    }
    // The circumcentre: a + (|u|² v × n + |v|² n × u) / (2 |n|²).
    let to_centre = (v.cross(&n) * u.norm_squared() + n.cross(&u) * v.norm_squared()) / (2.0 * n2);
    Some(Circle {
        center: a + to_centre,
        normal: n / n2.sqrt(),
        radius: to_centre.norm(),
    })
}

/// Gauss–Newton on the centre (3) and the normal's tilt (2) of a circle of fixed radius,
/// minimising the points' squared distances to it (discounted along their rays where `rays`,
/// empty or one for each point, says).
pub fn refine_circle(
    points: &[Point],
    rays: &[RayDiscount],
    mut c: Circle,
    iterations: usize,
) -> Circle {
    if points.len() < 5 {
        return c;
    }
    let residuals = |c: &Circle| -> Vec<f64> {
        (0..points.len())
            .map(|i| circle_distance(c, points, rays, i))
            .collect()
    };
    for _ in 0..iterations {
        let (e1, e2) = plane_basis(&c.normal);
        let apply = |c: &Circle, x: &nalgebra::SVector<f64, 5>| Circle {
            center: c.center + Vector::new(x[0], x[1], x[2]),
            normal: (c.normal + e1 * x[3] + e2 * x[4]).normalize(),
            radius: c.radius,
        };
        let r0 = residuals(&c);
        let h = 1e-7;
        let mut jt_j = nalgebra::SMatrix::<f64, 5, 5>::zeros();
        let mut jt_r = nalgebra::SVector::<f64, 5>::zeros();
        let mut cols = Vec::with_capacity(5);
        for k in 0..5 {
            let mut dx = nalgebra::SVector::<f64, 5>::zeros();
            dx[k] = h;
            let rk = residuals(&apply(&c, &dx));
            cols.push(
                rk.iter()
                    .zip(&r0)
                    .map(|(a, b)| (a - b) / h)
                    .collect::<Vec<f64>>(),
            );
        }
        for i in 0..points.len() {
            let row = nalgebra::SVector::<f64, 5>::from_fn(|k, _| cols[k][i]);
            jt_j += row * row.transpose();
            jt_r += row * r0[i];
        }
        let Some(step) = (jt_j + nalgebra::SMatrix::<f64, 5, 5>::identity() * 1e-12)
            .cholesky()
            .map(|ch| ch.solve(&(-jt_r)))
        else {
            break;
        };
        let next = apply(&c, &step);
        let before: f64 = r0.iter().map(|v| v * v).sum();
        let after: f64 = residuals(&next).iter().map(|v| v * v).sum();
        if after.is_nan() || after > before {
            break;
        }
        c = next;
        if step.norm() < 1e-9 {
            break;
        }
    }
    c
}

/// The angular extent of points around a circle: angles in the basis `(e1, e2)` of its
/// plane, and the arc they cover (the complement of the largest empty gap).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ArcExtent {
    /// Angle of the arc's start (going counter-clockwise about the normal), rad.
    pub start: f64,
    /// Angle covered from the start, rad.
    pub extent: f64,
    /// The largest empty gap inside the arc, rad (occlusions).
    pub largest_inner_gap: f64,
}

/// The arc the `points` (near the circle) cover.
pub fn arc_extent(points: &[Point], c: &Circle) -> Option<ArcExtent> {
    if points.len() < 2 {
        return None;
    }
    let (e1, e2) = plane_basis(&c.normal);
    let mut angles: Vec<f64> = points
        .iter()
        .map(|p| {
            let d = p - c.center;
            d.dot(&e2).atan2(d.dot(&e1))
        })
        .collect();
    angles.sort_by(f64::total_cmp);
    let tau = std::f64::consts::TAU;
    let mut gaps: Vec<(f64, usize)> = angles
        .windows(2)
        .enumerate()
        .map(|(i, w)| (w[1] - w[0], i + 1))
        .collect();
    gaps.push((angles[0] + tau - angles[angles.len() - 1], 0));
    let (gap, after) = gaps.iter().copied().max_by(|a, b| a.0.total_cmp(&b.0))?;
    let inner = gaps
        .iter()
        .filter(|(g, a)| *a != after || (*g - gap).abs() > 0.0)
        .map(|g| g.0)
        .fold(0.0, f64::max);
    Some(ArcExtent {
        start: angles[after],
        extent: tau - gap,
        largest_inner_gap: inner.min(tau - gap),
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::UnitQuaternion;
    use rand_chacha::rand_core::SeedableRng;

    fn half_circle(c: Point, n: Vector, r: f64, k: usize) -> Vec<Point> {
        let (e1, e2) = plane_basis(&n);
        (0..k)
            .map(|i| {
                let a = std::f64::consts::PI * i as f64 / (k - 1) as f64;
                c + (e1 * a.cos() + e2 * a.sin()) * r
            })
            .collect()
    }

    #[test]
    fn the_circle_through_three_points_is_their_circumcircle() {
        let c = Point::new(0.01, -0.02, -0.1);
        let n = UnitQuaternion::from_euler_angles(0.3, -0.5, 1.0) * Vector::z();
        let pts = half_circle(c, n, 0.012, 7);
        let k = circle_through(&pts[0], &pts[3], &pts[6]).expect("a circle");
        assert!((k.center - c).norm() < 1e-12, "{:?}", k.center - c);
        assert!((k.radius - 0.012).abs() < 1e-12);
        assert!(k.normal.cross(&n).norm() < 1e-9);
        assert!(circle_through(&pts[0], &pts[0], &pts[6]).is_none());
    }

    #[test]
    fn a_needle_outnumbered_by_clutter_on_a_plane_is_found_with_no_plane_first() {
        // The needle, 100 points within 0.1 mm, held 4 mm above and tilted 50° to a plane of
        // 600 glare points (wet tissue) spread under and round it: the plane with the most
        // points is the glare's, and no circle on it is the needle.
        let mut rng = ChaCha8Rng::seed_from_u64(3);
        let c = Point::new(0.0, 0.0, -0.1);
        let n = Vector::new(0.0, (50f64).to_radians().sin(), (50f64).to_radians().cos());
        let mut pts: Vec<Point> = half_circle(c, n, 0.012, 100)
            .into_iter()
            .map(|p| p + Vector::new(rng.random(), rng.random(), rng.random()) * 0.0001)
            .collect();
        for _ in 0..600 {
            pts.push(Point::new(
                rng.random_range(-0.02..0.02),
                rng.random_range(-0.02..0.02),
                -0.1 - 0.004 - 0.009,
            ));
        }
        let params = RansacParams::default();
        let (plane, _) = ransac_plane(&pts, &[], &params, &mut rng).expect("a plane");
        assert!(plane.normal.z.abs() > 0.99, "the glare's plane: {plane:?}");
        let (circle, inliers) =
            ransac_circle_free(&pts, &[], 0.012, 0.003, &params, 2000, &mut rng).expect("a circle");
        assert!((circle.center - c).norm() < 3e-4, "{:?}", circle.center - c);
        assert!(circle.normal.cross(&n).norm() < 0.03, "{:?}", circle.normal);
        assert!(inliers.len() >= 95, "{}", inliers.len());
    }

    #[test]
    fn an_exact_half_circle_is_fitted_exactly() {
        let c = Point::new(0.01, -0.02, -0.1);
        let n = UnitQuaternion::from_euler_angles(0.3, -0.5, 1.0) * Vector::z();
        let pts = half_circle(c, n, 0.012, 200);
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        let (plane, inl) =
            ransac_plane(&pts, &[], &RansacParams::default(), &mut rng).expect("plane");
        assert_eq!(inl.len(), 200);
        assert!(plane.normal.cross(&n).norm() < 1e-9);
        let (circle, inl) =
            ransac_circle(&pts, &[], &plane, 0.012, &RansacParams::default(), &mut rng).expect("c");
        assert_eq!(inl.len(), 200);
        assert!((circle.center - c).norm() < 1e-9, "{:?}", circle.center - c);
        let arc = arc_extent(&pts, &circle).expect("arc");
        assert!(
            (arc.extent - std::f64::consts::PI).abs() < 1e-6,
            "{}",
            arc.extent
        );
    }

    #[test]
    fn a_noisy_circle_with_outliers_is_fitted_closely() {
        let c = Point::new(0.0, 0.0, -0.1);
        let n = Vector::new(0.2, 0.9, 0.3).normalize();
        let mut rng = ChaCha8Rng::seed_from_u64(7);
        let mut pts: Vec<Point> = half_circle(c, n, 0.012, 300)
            .into_iter()
            .map(|p| {
                p + Vector::new(
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                    rng.random_range(-1.0..1.0),
                ) * 0.0002
            })
            .collect();
        for _ in 0..150 {
            pts.push(
                c + Vector::new(
                    rng.random_range(-0.02..0.02),
                    rng.random_range(-0.02..0.02),
                    rng.random_range(-0.02..0.02),
                ),
            );
        }
        let p = RansacParams::default();
        let (plane, _) = ransac_plane(&pts, &[], &p, &mut rng).expect("plane");
        let (circle, inl) = ransac_circle(&pts, &[], &plane, 0.012, &p, &mut rng).expect("circle");
        assert!(
            (circle.center - c).norm() < 0.0001,
            "{}",
            (circle.center - c).norm()
        );
        assert!(circle.normal.cross(&n).norm() < 1f64.to_radians().sin());
        assert!(inl.len() >= 290, "{}", inl.len());
    }

    #[test]
    fn a_discounted_plane_distance_is_the_least_discounted_offset_to_the_plane() {
        let plane = Plane {
            normal: Vector::new(0.3, -0.2, 0.9).normalize(),
            offset: -0.05,
        };
        let q = Point::new(0.01, 0.02, -0.04);
        let h = plane.distance(&q);
        // Along the ray, a quarter of the step counts (s = 0.25, k = 1 − s²).
        let along = |dir: Vector| RayDiscount {
            dir: dir.normalize(),
            k: 1.0 - 0.25 * 0.25,
        };
        // The ray along the normal: the offset to the plane is all along it.
        let d = along(plane.normal);
        assert!((d.plane_distance(h, &plane.normal) - 0.25 * h.abs()).abs() < 1e-12);
        // Across the normal: none of it is.
        let d = along(plane.normal.cross(&Vector::x()));
        assert!((d.plane_distance(h, &plane.normal) - h.abs()).abs() < 1e-12);
        // Slanted: the least over offsets that reach the plane, searched on a grid of them.
        let d = along(Vector::new(0.5, 0.1, 0.4));
        let (e1, e2) = plane_basis(&plane.normal);
        let foot = q - plane.normal * h;
        let mut least = f64::INFINITY;
        for i in -400..=400 {
            for j in -400..=400 {
                let x = foot + e1 * (f64::from(i) * 2e-5) + e2 * (f64::from(j) * 2e-5) - q;
                least = least.min(d.length(&x));
            }
        }
        let closed = d.plane_distance(h, &plane.normal);
        assert!(closed <= least + 1e-9, "{closed} against {least}");
        assert!(least - closed < 1e-6, "{closed} against {least}");
        assert!(closed < h.abs());
    }

    #[test]
    fn a_needle_whose_depth_is_coarse_holds_its_points_when_the_ray_is_discounted() {
        // A narrow-baseline rig 0.18 m away whose disparity step there is 2 mm: each point
        // of the needle is off along its own viewing ray by up to ±1.5 mm, and across it
        // by 0.1 mm. Counted in full, the depth noise leaves few inliers and a tilted plane;
        // discounted to a 0.5 mm step, the needle holds.
        let mut rng = ChaCha8Rng::seed_from_u64(5);
        let eye = Point::new(0.0, 0.0, 0.0);
        let c = Point::new(0.01, -0.005, -0.18);
        let n = Vector::new(0.1, 0.5, 0.8).normalize();
        let s = 0.0005 / 0.002;
        let (pts, rays): (Vec<Point>, Vec<RayDiscount>) = half_circle(c, n, 0.012, 300)
            .into_iter()
            .map(|p| {
                let dir = (p - eye).normalize();
                let across = Vector::new(rng.random(), rng.random(), rng.random()) * 1e-4;
                let q = p + dir * rng.random_range(-0.0015..0.0015) + across;
                let ray = RayDiscount {
                    dir: (q - eye).normalize(),
                    k: 1.0 - s * s,
                };
                (q, ray)
            })
            .unzip();
        let p = RansacParams::default();
        let fit_with = |rays: &[RayDiscount], rng: &mut ChaCha8Rng| {
            let (plane, on) = ransac_plane(&pts, rays, &p, rng).expect("a plane");
            let on_pts: Vec<Point> = on.iter().map(|&i| pts[i]).collect();
            let on_rays: Vec<RayDiscount> =
                on.iter().filter_map(|&i| rays.get(i).copied()).collect();
            ransac_circle(&on_pts, &on_rays, &plane, 0.012, &p, rng).expect("a circle")
        };
        let (_, full_inliers) = fit_with(&[], &mut rng);
        let (discounted, inliers) = fit_with(&rays, &mut rng);
        assert!(
            inliers.len() >= 270,
            "{} of 300 points on the circle",
            inliers.len()
        );
        assert!(
            full_inliers.len() < 200,
            "{} of 300 points on the circle counted in full",
            full_inliers.len()
        );
        let off = (discounted.center - c).norm();
        assert!(off < 0.0005, "the centre {off} m off");
        assert!(discounted.normal.cross(&n).norm() < 3f64.to_radians().sin());
    }

    #[test]
    fn too_few_points_fit_nothing() {
        let mut rng = ChaCha8Rng::seed_from_u64(1);
        assert!(
            ransac_plane(&[Point::origin()], &[], &RansacParams::default(), &mut rng).is_none()
        );
        assert!(fit_plane(&[Point::origin(), Point::new(1.0, 0.0, 0.0)]).is_none());
    }
}
