//! Nearest points on segments and polylines: what the thread's physics, tracer, conditions
//! and evaluation all ask of a curve given as points.

use crate::Point;

/// The point of the segment `a`–`b` nearest `p`, and how far along it it lies (0 at `a`, 1
/// at `b`; 0 for a segment of no length).
pub fn nearest_on_segment(p: &Point, a: &Point, b: &Point) -> (Point, f64) {
    let ab = b - a;
    let l2 = ab.norm_squared();
    let t = if l2 > 0.0 {
        ((p - a).dot(&ab) / l2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (a + ab * t, t)
}

/// The point of the polyline `line` nearest `p`: the point, the index of its segment (of its
/// only point, for one point) and how far along that segment; `None` for no points. The
/// first of equally near segments wins.
pub fn nearest_on_polyline(p: &Point, line: &[Point]) -> Option<(Point, usize, f64)> {
    if let [only] = line {
        return Some((*only, 0, 0.0));
    }
    let mut best: Option<(Point, usize, f64, f64)> = None;
    for (i, w) in line.windows(2).enumerate() {
        let (q, t) = nearest_on_segment(p, &w[0], &w[1]);
        let d = (p - q).norm();
        if best.is_none_or(|(.., bd)| d < bd) {
            best = Some((q, i, t, d));
        }
    }
    best.map(|(q, i, t, _)| (q, i, t))
}

/// The distance from `p` to the polyline `line`, m (infinite for no points).
pub fn distance_to_polyline(p: &Point, line: &[Point]) -> f64 {
    nearest_on_polyline(p, line).map_or(f64::INFINITY, |(q, ..)| (p - q).norm())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn close(a: f64, b: f64) -> bool {
        (a - b).abs() < 1e-12
    }

    #[test]
    fn nearest_points_on_segments_and_polylines() {
        let (a, b) = (Point::new(0.0, 0.0, 0.0), Point::new(2.0, 0.0, 0.0));
        let (q, t) = nearest_on_segment(&Point::new(0.5, 1.0, 0.0), &a, &b);
        assert!((q - Point::new(0.5, 0.0, 0.0)).norm() < 1e-12 && close(t, 0.25));
        assert!(close(
            nearest_on_segment(&Point::new(-1.0, 1.0, 0.0), &a, &b).1,
            0.0
        ));
        assert!(close(
            nearest_on_segment(&Point::new(3.0, 0.0, 0.0), &a, &b).1,
            1.0
        ));
        let (q, t) = nearest_on_segment(&Point::new(3.0, 0.0, 0.0), &a, &a);
        assert!(q == a && close(t, 0.0), "a segment of no length");
        let line = [a, b, Point::new(2.0, 2.0, 0.0)];
        let (q, i, t) = nearest_on_polyline(&Point::new(3.0, 1.5, 0.0), &line).expect("points");
        assert!((q - Point::new(2.0, 1.5, 0.0)).norm() < 1e-12 && i == 1 && close(t, 0.75));
        assert!(close(
            distance_to_polyline(&Point::new(1.0, -2.0, 0.0), &line),
            2.0
        ));
        let (q, i, _) = nearest_on_polyline(&a, &[b]).expect("one point");
        assert!(q == b && i == 0);
        assert!(nearest_on_polyline(&a, &[]).is_none());
        assert!(distance_to_polyline(&a, &[]).is_infinite());
    }
}
