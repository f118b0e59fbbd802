//! The jaw (gripper) of a needle driver, CRTK-named.

use crate::{MoveHandle, RobotError};
use std::sync::{Mutex, PoisonError};

/// Jaw angle for "open": dVRK large needle drivers open to about 80°; 60° leaves margin.
pub const JAW_OPEN_RAD: f64 = 60.0 * std::f64::consts::PI / 180.0;
/// Jaw angle for "closed" (a grasp closes onto the needle and stops there).
pub const JAW_CLOSED_RAD: f64 = 0.0;

/// A jaw. Angles are the opening between the two blades, rad.
pub trait Jaw: Send + Sync {
    /// The jaw's name, e.g. `PSM1/jaw`.
    fn name(&self) -> &str;
    /// Measured opening, rad.
    fn measured_jp(&self) -> Result<f64, RobotError>;
    /// Move to an opening, rad; returns at once.
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError>;
    /// Open to [`JAW_OPEN_RAD`].
    fn open(&self) -> Result<MoveHandle, RobotError> {
        self.move_jp(JAW_OPEN_RAD)
    }
    /// Close to [`JAW_CLOSED_RAD`].
    fn close(&self) -> Result<MoveHandle, RobotError> {
        self.move_jp(JAW_CLOSED_RAD)
    }
}

/// Forwards every call, so `Arc<dyn Jaw>` (and `Box`, `&`) is a [`Jaw`] too.
macro_rules! forward_jaw {
    ($($ptr:ty),*) => {$(
        impl<T: Jaw + ?Sized> Jaw for $ptr {
            fn name(&self) -> &str {
                (**self).name()
            }
            fn measured_jp(&self) -> Result<f64, RobotError> {
                (**self).measured_jp()
            }
            fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
                (**self).move_jp(angle_rad)
            }
            fn open(&self) -> Result<MoveHandle, RobotError> {
                (**self).open()
            }
            fn close(&self) -> Result<MoveHandle, RobotError> {
                (**self).close()
            }
        }
    )*};
}
forward_jaw!(std::sync::Arc<T>, Box<T>, &T);

/// A jaw that records what it is told and is wherever it was last told to be.
#[derive(Debug)]
pub struct DummyJaw {
    /// The jaw's name.
    pub name: String,
    /// Every commanded opening, rad, in order.
    pub commands: Mutex<Vec<f64>>,
    /// The current opening, rad.
    pub angle_rad: Mutex<f64>,
}

impl DummyJaw {
    /// A closed dummy jaw.
    pub fn new(name: &str) -> Self {
        Self {
            name: name.into(),
            commands: Mutex::new(Vec::new()),
            angle_rad: Mutex::new(0.0),
        }
    }
}

impl Jaw for DummyJaw {
    fn name(&self) -> &str {
        &self.name
    }
    fn measured_jp(&self) -> Result<f64, RobotError> {
        Ok(*self
            .angle_rad
            .lock()
            .unwrap_or_else(PoisonError::into_inner))
    }
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        if !angle_rad.is_finite() {
            return Err(RobotError::NonFinite {
                arm: self.name.clone(),
                what: "jaw angle".into(),
            });
        }
        self.commands
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(angle_rad);
        *self
            .angle_rad
            .lock()
            .unwrap_or_else(PoisonError::into_inner) = angle_rad;
        Ok(MoveHandle::done())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn open_and_close_move_to_the_named_angles() {
        let j = DummyJaw::new("PSM1/jaw");
        let _ = j.open().expect("opens");
        assert!((j.measured_jp().expect("measured") - JAW_OPEN_RAD).abs() < 1e-12);
        let _ = j.close().expect("closes");
        assert_eq!(
            *j.commands.lock().expect("lock"),
            vec![JAW_OPEN_RAD, JAW_CLOSED_RAD]
        );
        assert!(j.move_jp(f64::NAN).is_err());
    }
}
