//! The wound model: ordered entry/exit point pairs.

use crate::{Point, RobotError};
use serde::{Deserialize, Serialize};

/// One suture site: where the needle enters and where it should exit, robot frame, m.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WoundPoint {
    /// Position in suturing order, 0-based.
    pub index: usize,
    /// Entry point on one wound edge, m.
    pub entry: Point,
    /// Exit point on the other edge, m.
    pub exit: Point,
}

/// A wound: its suture sites in suturing order.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Wound {
    /// The sites, in order.
    pub points: Vec<WoundPoint>,
}

/// A straight raised wound along the robot's +y axis (the paper's "Assumptions": raised and
/// orthogonal to the camera).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct WoundSpec {
    /// The first site's midpoint between entry and exit, robot frame, m.
    pub origin: Point,
    /// Number of sites (the paper closes a wound with 6).
    pub count: usize,
    /// Distance between consecutive sites along +y, m.
    pub spacing_m: f64,
    /// Distance from the wound's centre line to the entry (−x: the right needle driver's side,
    /// the camera's right when it looks along −y) and to the exit (+x, the left driver's
    /// side), m.
    pub half_bite_m: f64,
}

impl Default for WoundSpec {
    /// 6 sites, as the paper's full wound. The rest are modelling choices: 8 mm spacing and a
    /// 5 mm half bite (a 10 mm bite, inside the 24 mm chord of the 12 mm needle), centred at
    /// a point in a dVRK PSM's reach below its remote centre of motion.
    fn default() -> Self {
        Self {
            origin: Point::new(0.0, 0.0, -0.12),
            count: 6,
            spacing_m: 0.008,
            half_bite_m: 0.005,
        }
    }
}

impl Wound {
    /// The sites of a straight wound; entry at −x, exit at +x of the centre line (the right
    /// driver inserts towards the left, which extracts), the i-th at `origin.y + i · spacing`.
    pub fn linear(spec: &WoundSpec) -> Result<Wound, RobotError> {
        let bad = |why: String| {
            Err(RobotError::InvalidConfig {
                what: "wound".into(),
                why,
            })
        };
        if !(1..=20).contains(&spec.count) {
            return bad(format!("{} points; expected 1 to 20", spec.count));
        }
        if !(spec.spacing_m.is_finite() && spec.spacing_m > 0.0 && spec.spacing_m <= 0.05) {
            return bad(format!(
                "spacing {} m; expected more than 0 and at most 0.05 m",
                spec.spacing_m
            ));
        }
        if !(spec.half_bite_m.is_finite() && spec.half_bite_m > 0.0 && spec.half_bite_m <= 0.02) {
            return bad(format!(
                "half bite {} m; expected more than 0 and at most 0.02 m",
                spec.half_bite_m
            ));
        }
        if !spec.origin.iter().all(|v| v.is_finite()) {
            return bad("origin is not finite".into());
        }
        let points = (0..spec.count)
            .map(|i| {
                let y = spec.origin.y + i as f64 * spec.spacing_m;
                WoundPoint {
                    index: i,
                    entry: Point::new(spec.origin.x - spec.half_bite_m, y, spec.origin.z),
                    exit: Point::new(spec.origin.x + spec.half_bite_m, y, spec.origin.z),
                }
            })
            .collect();
        Ok(Wound { points })
    }

    /// Number of sites.
    pub fn len(&self) -> usize {
        self.points.len()
    }

    /// Whether there are no sites.
    pub fn is_empty(&self) -> bool {
        self.points.is_empty()
    }

    /// The sites in order.
    pub fn iter(&self) -> impl Iterator<Item = &WoundPoint> {
        self.points.iter()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_linear_wound_puts_entries_and_exits_on_either_edge() {
        let spec = WoundSpec {
            origin: Point::new(0.01, 0.02, -0.1),
            count: 3,
            spacing_m: 0.008,
            half_bite_m: 0.005,
        };
        let w = Wound::linear(&spec).expect("valid");
        assert_eq!(w.len(), 3);
        assert_eq!(w.points[2].index, 2);
        assert!((w.points[2].entry - Point::new(0.005, 0.036, -0.1)).norm() < 1e-12);
        assert!((w.points[2].exit - Point::new(0.015, 0.036, -0.1)).norm() < 1e-12);
    }

    #[test]
    fn bad_specs_are_refused_with_the_reason() {
        let e = Wound::linear(&WoundSpec {
            count: 0,
            ..WoundSpec::default()
        })
        .expect_err("0 points");
        assert_eq!(e.to_string(), "invalid wound: 0 points; expected 1 to 20");
        assert!(
            Wound::linear(&WoundSpec {
                spacing_m: f64::NAN,
                ..WoundSpec::default()
            })
            .is_err()
        );
        assert!(
            Wound::linear(&WoundSpec {
                half_bite_m: -1.0,
                ..WoundSpec::default()
            })
            .is_err()
        );
    }

    #[test]
    fn the_default_wound_is_six_sites_8_mm_apart_with_a_10_mm_bite() {
        let spec = WoundSpec::default();
        let w = Wound::linear(&spec).expect("valid");
        assert_eq!(w.len(), 6);
        assert!(!w.is_empty());
        let last = w.iter().last().expect("six");
        assert_eq!(last.index, 5);
        let o = spec.origin;
        assert!((last.entry - Point::new(o.x - 0.005, o.y + 0.040, o.z)).norm() < 1e-12);
        assert!((last.exit - last.entry).norm() - 0.010 < 1e-12);
        assert!(
            Wound::linear(&WoundSpec {
                count: 21,
                ..spec.clone()
            })
            .is_err()
        );
        assert!(
            Wound::linear(&WoundSpec {
                spacing_m: 0.2,
                ..spec
            })
            .is_err()
        );
    }
}
