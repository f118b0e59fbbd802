//! The tissue phantom: a raised linear wound along the robot's +y axis, its entry and exit
//! holes, and the scoring of a needle pass the way the Surgical Robotics Challenge scores it.
//!
//! Each wound point has an entry hole on the outer face of one raised edge and an exit hole on
//! the outer face of the other. A hole's frame has its origin at the hole and its normal
//! pointing out of the tissue (entry: against the entry→exit direction; exit: along it). A
//! pass is scored from the needle tip's true path: the tip's lateral offset from the hole at
//! the moment it crosses the hole's plane (within ±2.5 mm to pass), and how far the tip
//! protrudes beyond the exit plane at the end (at least 5 mm). Between the two planes the tip
//! must stay inside the raised edge's height: above it, it left through the top; below, the
//! bottom.

use crate::SimError;
use serde::{Deserialize, Serialize};
use stitch_robot::{Point, Vector, Wound, WoundPoint};

/// Pass tolerance on the lateral offset at each hole (the Surgical Robotics Challenge's
/// ±2.5 mm), m.
pub const HOLE_TOLERANCE_M: f64 = 0.0025;
/// Least protrusion of the tip beyond the exit plane for a pass (the SRC's 5 mm), m.
pub const MIN_PROTRUSION_M: f64 = 0.005;

/// The raised edges' extent around the holes (modelling choices: a 3-Dmed-like pad).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PhantomGeometry {
    /// Height of the edge's top above the holes, m.
    pub top_above_hole_m: f64,
    /// Depth of the tissue's bottom below the holes, m.
    pub bottom_below_hole_m: f64,
}

impl Default for PhantomGeometry {
    /// The edges rise 4 mm above the holes and the tissue goes 6 mm below them: modelling
    /// choices for a raised wound a 12 mm needle passes under.
    fn default() -> Self {
        Self {
            top_above_hole_m: 0.004,
            bottom_below_hole_m: 0.006,
        }
    }
}

impl PhantomGeometry {
    /// Refuse geometry no phantom has.
    pub fn validate(&self) -> Result<(), SimError> {
        for (name, v) in [
            ("top_above_hole_m", self.top_above_hole_m),
            ("bottom_below_hole_m", self.bottom_below_hole_m),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 0.05) {
                return Err(SimError::Config {
                    what: format!("phantom.{name}"),
                    why: format!("{v} m; expected more than 0 and at most 0.05 m"),
                });
            }
        }
        Ok(())
    }
}

/// A hole in the phantom: its centre and its outward normal.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hole {
    /// The hole's centre, m.
    pub center: Point,
    /// Unit normal pointing out of the tissue.
    pub normal: Vector,
}

impl Hole {
    /// Signed distance of `p` from the hole's plane, positive outside the tissue, m.
    pub fn distance(&self, p: &Point) -> f64 {
        (p - self.center).dot(&self.normal)
    }

    /// The offset of `p` from the hole's centre within the hole's plane, m.
    pub fn lateral(&self, p: &Point) -> Vector {
        let d = p - self.center;
        d - self.normal * d.dot(&self.normal)
    }
}

/// The tissue phantom.
#[derive(Clone, Debug, PartialEq)]
pub struct Phantom {
    /// The wound's points, in suturing order.
    pub wound: Wound,
    /// The raised edges' extent.
    pub geometry: PhantomGeometry,
}

/// Where a tip left the tissue between the holes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Breach {
    /// Through the top of the raised edge.
    Top,
    /// Through the bottom of the phantom.
    Bottom,
}

/// How one needle pass went, scored on the true tip path.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassScore {
    /// Lateral offset from the entry hole where the tip crossed its plane; `None` if it never
    /// went in, m.
    pub entry_error_m: Option<f64>,
    /// Lateral offset from the exit hole where the tip crossed its plane; `None` if it never
    /// came out, m.
    pub exit_error_m: Option<f64>,
    /// How far the tip ends beyond the exit plane, m (negative: short of it).
    pub protrusion_m: f64,
    /// Where the tip left the tissue between the holes, if it did.
    pub breach: Option<Breach>,
}

impl PassScore {
    /// Whether the pass meets every criterion.
    pub fn passed(&self) -> bool {
        self.entry_error_m.is_some_and(|e| e <= HOLE_TOLERANCE_M)
            && self.exit_error_m.is_some_and(|e| e <= HOLE_TOLERANCE_M)
            && self.protrusion_m >= MIN_PROTRUSION_M
            && self.breach.is_none()
    }
}

impl Phantom {
    /// A phantom around `wound`.
    pub fn new(wound: Wound, geometry: PhantomGeometry) -> Result<Self, SimError> {
        geometry.validate()?;
        Ok(Self { wound, geometry })
    }

    /// The entry and exit holes of a wound point.
    pub fn holes(&self, wp: &WoundPoint) -> (Hole, Hole) {
        let mut u = wp.exit - wp.entry;
        u.z = 0.0; // the holes face horizontally: the wound is raised, the pad is level
        let u = u.try_normalize(1e-12).unwrap_or_else(Vector::x);
        (
            Hole {
                center: wp.entry,
                normal: -u,
            },
            Hole {
                center: wp.exit,
                normal: u,
            },
        )
    }

    /// Score the tip's path (in order, m) against wound point `wp`.
    pub fn score(&self, wp: &WoundPoint, tip_path: &[Point]) -> PassScore {
        let (entry, exit) = self.holes(wp);
        let top = wp.entry.z.max(wp.exit.z) + self.geometry.top_above_hole_m;
        let bottom = wp.entry.z.min(wp.exit.z) - self.geometry.bottom_below_hole_m;
        let mut score = PassScore {
            entry_error_m: None,
            exit_error_m: None,
            protrusion_m: tip_path
                .last()
                .map_or(f64::NEG_INFINITY, |p| exit.distance(p)),
            breach: None,
        };
        let mut inside = false;
        for pair in tip_path.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            if score.entry_error_m.is_none() {
                // Going in: from outside (or on) the entry plane to inside it.
                let (da, db) = (entry.distance(&a), entry.distance(&b));
                if da >= 0.0 && db < 0.0 {
                    let p = a + (b - a) * (da / (da - db));
                    score.entry_error_m = Some(entry.lateral(&p).norm());
                    inside = true;
                    self.check_breach(&mut score, &p, &b, top, bottom);
                }
                continue;
            }
            if inside {
                let (da, db) = (exit.distance(&a), exit.distance(&b));
                if da < 0.0 && db >= 0.0 {
                    let p = a + (b - a) * (da / (da - db));
                    score.exit_error_m = Some(exit.lateral(&p).norm());
                    inside = false;
                    self.check_breach(&mut score, &a, &p, top, bottom);
                } else {
                    self.check_breach(&mut score, &a, &b, top, bottom);
                }
            }
        }
        score
    }

    fn check_breach(&self, score: &mut PassScore, a: &Point, b: &Point, top: f64, bottom: f64) {
        if score.breach.is_some() {
            return;
        }
        let z = a.z.max(b.z);
        let zmin = a.z.min(b.z);
        if z > top {
            score.breach = Some(Breach::Top);
        } else if zmin < bottom {
            score.breach = Some(Breach::Bottom);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn phantom() -> Phantom {
        // Entry at (-5, 0, 0) mm, exit at (5, 0, 0) mm: the needle travels along +x.
        let wound = Wound {
            points: vec![WoundPoint {
                index: 0,
                entry: Point::new(-0.005, 0.0, 0.0),
                exit: Point::new(0.005, 0.0, 0.0),
            }],
        };
        Phantom::new(wound, PhantomGeometry::default()).expect("phantom")
    }

    fn line(from: Point, to: Point, n: usize) -> Vec<Point> {
        (0..=n)
            .map(|i| from + (to - from) * (i as f64 / n as f64))
            .collect()
    }

    const MM: f64 = 1e-3;

    #[test]
    fn a_straight_pass_one_millimetre_high_passes_with_one_millimetre_errors() {
        let p = phantom();
        let path = line(
            Point::new(-8.0 * MM, 0.0, MM),
            Point::new(11.0 * MM, 0.0, MM),
            19,
        );
        let s = p.score(&p.wound.points[0], &path);
        assert!((s.entry_error_m.expect("in") - MM).abs() < 1e-9);
        assert!((s.exit_error_m.expect("out") - MM).abs() < 1e-9);
        assert!((s.protrusion_m - 6.0 * MM).abs() < 1e-9);
        assert_eq!(s.breach, None);
        assert!(s.passed());
    }

    #[test]
    fn a_pass_three_millimetres_off_misses_both_holes() {
        let p = phantom();
        let path = line(
            Point::new(-8.0 * MM, 3.0 * MM, 0.0),
            Point::new(11.0 * MM, 3.0 * MM, 0.0),
            19,
        );
        let s = p.score(&p.wound.points[0], &path);
        assert!((s.entry_error_m.expect("in") - 3.0 * MM).abs() < 1e-9);
        assert!(!s.passed());
    }

    #[test]
    fn a_tip_that_stops_short_has_no_exit_and_fails() {
        let p = phantom();
        let path = line(
            Point::new(-8.0 * MM, 0.0, 0.0),
            Point::new(2.0 * MM, 0.0, 0.0),
            10,
        );
        let s = p.score(&p.wound.points[0], &path);
        assert_eq!(s.exit_error_m, None);
        assert!((s.protrusion_m + 3.0 * MM).abs() < 1e-9);
        assert!(!s.passed());
    }

    #[test]
    fn a_tip_that_dives_below_the_phantom_breaches_the_bottom() {
        let p = phantom();
        let mut path = line(
            Point::new(-8.0 * MM, 0.0, 0.0),
            Point::new(0.0, 0.0, -8.0 * MM),
            8,
        );
        path.extend(line(
            Point::new(0.0, 0.0, -8.0 * MM),
            Point::new(11.0 * MM, 0.0, 0.0),
            11,
        ));
        let s = p.score(&p.wound.points[0], &path);
        assert_eq!(s.breach, Some(Breach::Bottom));
        assert!(!s.passed());
    }

    #[test]
    fn the_papers_insertion_arc_passes_with_the_hand_computed_errors() {
        // Tip at the entry, tangent along +x, centre 12 mm above it; push 7 mm along +x, then
        // rotate 45° about the normal: the tip crosses the exit plane (x = 5 mm) where the arc
        // is 3 mm past the bottom: height 12 − √(144 − 9) = 0.381 mm; it ends
        // 7 + 12·sin 45° − 10 = 5.485 mm beyond the exit plane.
        let p = phantom();
        let r = 12.0 * MM;
        let mut path = line(
            Point::new(-5.0 * MM, 0.0, 0.0),
            Point::new(2.0 * MM, 0.0, 0.0),
            14,
        );
        let c = Point::new(2.0 * MM, 0.0, r);
        path.extend((1..=90).map(|i| {
            let a = (45.0f64).to_radians() * f64::from(i) / 90.0;
            Point::new(c.x + r * a.sin(), 0.0, c.z - r * a.cos())
        }));
        let s = p.score(&p.wound.points[0], &path);
        assert!(s.entry_error_m.expect("in") < 1e-9);
        let exit = s.exit_error_m.expect("out");
        assert!((exit - (12.0 - 135f64.sqrt()) * MM).abs() < 1e-5, "{exit}");
        assert!((s.protrusion_m - (7.0 + 12.0 * (0.5f64).sqrt() - 10.0) * MM).abs() < 1e-9);
        assert!(s.passed());
    }

    #[test]
    fn bad_geometry_is_refused() {
        let g = PhantomGeometry {
            top_above_hole_m: -1.0,
            ..PhantomGeometry::default()
        };
        assert!(g.validate().is_err());
    }
}
