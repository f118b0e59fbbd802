//! The needle model: a half circle of known radius, with a tip and a swage.

use crate::{Point, Pose, RobotError, Vector};
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;

/// Radius of the paper's GS-21 half-circle needle ("Experimental Setup"), m.
pub const NEEDLE_RADIUS_M: f64 = 0.012;
/// Wire diameter of a GS-21-like needle; modelling choice, m.
pub const NEEDLE_WIRE_DIAMETER_M: f64 = 0.0007;

/// A half-circle needle. In its own frame the centre is the origin, the circle lies in the
/// x–y plane with normal +z, the tip is at angle 0, `(r, 0, 0)`, the swage (where the thread
/// leaves) at angle π, `(−r, 0, 0)`, and the arc passes through `(0, r, 0)`.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct Needle {
    /// Radius, m.
    pub radius_m: f64,
    /// Wire diameter, m.
    pub wire_diameter_m: f64,
}

impl Default for Needle {
    fn default() -> Self {
        Self {
            radius_m: NEEDLE_RADIUS_M,
            wire_diameter_m: NEEDLE_WIRE_DIAMETER_M,
        }
    }
}

/// A needle's features in the world (robot) frame.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct NeedleGeometry {
    /// Circle centre, m.
    pub center: Point,
    /// Unit normal of the circle's plane.
    pub normal: Vector,
    /// The sharp end, m.
    pub tip: Point,
    /// The thread end, m.
    pub swage: Point,
}

impl Needle {
    /// A needle of radius `radius_m` (1 mm to 50 mm) and the default wire.
    pub fn new(radius_m: f64) -> Result<Self, RobotError> {
        if !(radius_m.is_finite() && (0.001..=0.05).contains(&radius_m)) {
            return Err(RobotError::InvalidConfig {
                what: "needle radius".into(),
                why: format!("{radius_m} m; expected 0.001 to 0.05 m"),
            });
        }
        Ok(Self {
            radius_m,
            ..Self::default()
        })
    }

    /// The point of the arc at `angle_rad` from the tip (0) towards the swage (π), needle frame.
    pub fn point_at(&self, angle_rad: f64) -> Point {
        Point::new(
            self.radius_m * angle_rad.cos(),
            self.radius_m * angle_rad.sin(),
            0.0,
        )
    }

    /// The tip, needle frame.
    pub fn tip(&self) -> Point {
        self.point_at(0.0)
    }

    /// The swage, needle frame.
    pub fn swage(&self) -> Point {
        self.point_at(PI)
    }

    /// The circle's normal, needle frame (+z).
    pub fn normal(&self) -> Vector {
        Vector::z()
    }

    /// Length of the half-circle arc, m.
    pub fn arc_length_m(&self) -> f64 {
        PI * self.radius_m
    }

    /// Centre, normal, tip and swage in the world, for a needle frame at `needle_pose`.
    pub fn in_world(&self, needle_pose: &Pose) -> NeedleGeometry {
        NeedleGeometry {
            center: needle_pose * Point::origin(),
            normal: needle_pose * self.normal(),
            tip: needle_pose * self.tip(),
            swage: needle_pose * self.swage(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Translation3, UnitQuaternion};

    #[test]
    fn tip_swage_and_normal_follow_the_needle_frame() {
        let n = Needle::default();
        // Rotate 90° about +x, then move to (0.1, 0.2, 0.3): +y → +z, +z → −y.
        let pose = Pose::from_parts(
            Translation3::new(0.1, 0.2, 0.3),
            UnitQuaternion::from_axis_angle(&Vector::x_axis(), PI / 2.0),
        );
        let g = n.in_world(&pose);
        assert!((g.center - Point::new(0.1, 0.2, 0.3)).norm() < 1e-12);
        assert!((g.tip - Point::new(0.112, 0.2, 0.3)).norm() < 1e-12);
        assert!((g.swage - Point::new(0.088, 0.2, 0.3)).norm() < 1e-12);
        assert!((g.normal - Vector::new(0.0, -1.0, 0.0)).norm() < 1e-12);
        // The arc's midpoint goes to +z.
        let mid = pose * n.point_at(PI / 2.0);
        assert!((mid - Point::new(0.1, 0.2, 0.312)).norm() < 1e-12);
        assert!((n.arc_length_m() - PI * 0.012).abs() < 1e-15);
    }

    #[test]
    fn radii_outside_1_to_50_mm_are_refused() {
        assert!(Needle::new(0.012).is_ok());
        assert!(Needle::new(0.0005).is_err());
        assert!(Needle::new(f64::NAN).is_err());
    }
}
