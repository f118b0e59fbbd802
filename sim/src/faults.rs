//! Injected faults: constant calibration errors, seeded random faults, and scheduled ones.
//!
//! - **Joint offset errors**, as the Surgical Robotics Challenge injects them: an error on
//!   each PSM's first two joints (yaw and pitch about its remote centre of motion, up to ±5°)
//!   and its insertion axis (up to ±5 mm). The arm's kinematics do not see them: it reports
//!   the pose it was told to reach, but the tool tip, and the needle it holds, end where the
//!   erroneous joints put them.
//! - **Hand-eye calibration error**: every needle estimate is off by a fixed transform.
//! - **Perception dropout**, **missed grasp** (a closing jaw catches nothing), **needle
//!   slip** (the needle turns in the jaw during a move), **stale measurement** (`measured_cp`
//!   would report the pose from before the last move; the arm refuses it with
//!   `RobotError::Stale`, as the dVRK backend refuses old data), **arm fault** (a motion
//!   command fails):
//!   each with a chance per event from the seed's `Faults` stream, and each schedulable at
//!   the n-th event of its kind.

use crate::SimError;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use serde::{Deserialize, Serialize};
use stitch_robot::nalgebra::{Translation3, UnitQuaternion};
use stitch_robot::{Point, Pose, Vector};

/// A kind of event-triggered fault.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum FaultKind {
    /// A needle estimate drops out.
    PerceptionDropout,
    /// A closing jaw catches nothing.
    MissedGrasp,
    /// The needle turns in the jaw during a move.
    NeedleSlip,
    /// `measured_cp` has only the pose from before the last move, and refuses it as stale.
    StaleMeasurement,
    /// A motion command fails with an arm fault.
    ArmFault,
}

const KINDS: usize = 5;

impl FaultKind {
    /// Every kind, in the order of [`Faults::events`].
    pub const ALL: [FaultKind; KINDS] = [
        FaultKind::PerceptionDropout,
        FaultKind::MissedGrasp,
        FaultKind::NeedleSlip,
        FaultKind::StaleMeasurement,
        FaultKind::ArmFault,
    ];

    fn index(self) -> usize {
        self as usize
    }
}

/// A fault at the n-th event of its kind (1-based: `nth = 1` is the first).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ScheduledFault {
    /// What goes wrong.
    pub kind: FaultKind,
    /// At which event of that kind (estimates, grasps, carrying moves, measurements, motion
    /// commands), 1-based.
    pub nth: u32,
}

/// What to inject. Everything defaults to no fault.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct FaultConfig {
    /// Joint offset errors of [PSM1, PSM2]: [yaw rad, pitch rad, insertion m].
    pub joint_offsets: [[f64; 3]; 2],
    /// Hand-eye calibration error: translation, m.
    pub hand_eye_translation_m: [f64; 3],
    /// Hand-eye calibration error: rotation vector, rad.
    pub hand_eye_rotation_rad: [f64; 3],
    /// Chance per estimate of a dropout.
    pub p_perception_dropout: f64,
    /// Chance per closing jaw of a missed grasp.
    pub p_missed_grasp: f64,
    /// Chance per move carrying the needle that it slips.
    pub p_needle_slip: f64,
    /// How far a slip turns the needle in the jaw, about its normal, rad (0 means 15°).
    pub slip_rad: f64,
    /// Chance per `measured_cp` of a stale measurement.
    pub p_stale_measurement: f64,
    /// Chance per motion command of an arm fault.
    pub p_arm_fault: f64,
    /// Faults at given events.
    pub schedule: Vec<ScheduledFault>,
}

/// The largest joint offsets the SRC injects: ±5° on the first two joints, ±5 mm insertion.
pub const MAX_JOINT_OFFSET: [f64; 3] = [
    5.0 * std::f64::consts::PI / 180.0,
    5.0 * std::f64::consts::PI / 180.0,
    0.005,
];

impl FaultConfig {
    /// Refuse faults outside what the models mean.
    pub fn validate(&self) -> Result<(), SimError> {
        let bad = |what: &str, why: String| {
            Err(SimError::Config {
                what: format!("faults.{what}"),
                why,
            })
        };
        for (arm, offsets) in self.joint_offsets.iter().enumerate() {
            for (j, (v, max)) in offsets.iter().zip(MAX_JOINT_OFFSET).enumerate() {
                if !(v.is_finite() && v.abs() <= max) {
                    return bad(
                        &format!("joint_offsets[{arm}][{j}]"),
                        format!("{v}; expected within ±{max} (the SRC's ±5°, ±5°, ±5 mm)"),
                    );
                }
            }
        }
        let t = self.hand_eye_translation_m;
        let r = self.hand_eye_rotation_rad;
        if !t.iter().all(|v| v.is_finite() && v.abs() <= 0.05)
            || !r.iter().all(|v| v.is_finite() && v.abs() <= 0.5)
        {
            return bad("hand_eye", "expected within ±5 cm and ±0.5 rad".into());
        }
        for (name, p) in [
            ("p_perception_dropout", self.p_perception_dropout),
            ("p_missed_grasp", self.p_missed_grasp),
            ("p_needle_slip", self.p_needle_slip),
            ("p_stale_measurement", self.p_stale_measurement),
            ("p_arm_fault", self.p_arm_fault),
        ] {
            if !(0.0..=1.0).contains(&p) {
                return bad(name, format!("{p}; expected a probability, 0 to 1"));
            }
        }
        if !(self.slip_rad.is_finite() && self.slip_rad.abs() <= 1.5) {
            return bad(
                "slip_rad",
                format!("{}; expected within ±1.5 rad", self.slip_rad),
            );
        }
        if let Some(s) = self.schedule.iter().find(|s| s.nth == 0) {
            return bad(
                "schedule",
                format!("{:?} at nth = 0; events count from 1", s.kind),
            );
        }
        Ok(())
    }
}

/// The faults of one run, with their counters and stream.
#[derive(Debug)]
pub struct Faults {
    config: FaultConfig,
    counts: [u32; KINDS],
    rng: ChaCha8Rng,
}

impl Faults {
    /// The faults `config` describes, drawing from `rng` (the seed's `Faults` stream).
    pub fn new(config: FaultConfig, rng: ChaCha8Rng) -> Result<Self, SimError> {
        config.validate()?;
        Ok(Self {
            config,
            counts: [0; KINDS],
            rng,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &FaultConfig {
        &self.config
    }

    /// How many events of `kind` have happened so far (the `nth` the next one would be,
    /// less one): what a schedule counts.
    pub fn events(&self, kind: FaultKind) -> u32 {
        self.counts[kind.index()]
    }

    /// Count one event of `kind` and say whether it faults (scheduled, or drawn). The draw is
    /// made only when its chance is above zero, so a run without that fault draws nothing.
    pub fn fires(&mut self, kind: FaultKind) -> bool {
        let n = &mut self.counts[kind.index()];
        *n += 1;
        let scheduled = self
            .config
            .schedule
            .iter()
            .any(|s| s.kind == kind && s.nth == *n);
        let p = match kind {
            FaultKind::PerceptionDropout => self.config.p_perception_dropout,
            FaultKind::MissedGrasp => self.config.p_missed_grasp,
            FaultKind::NeedleSlip => self.config.p_needle_slip,
            FaultKind::StaleMeasurement => self.config.p_stale_measurement,
            FaultKind::ArmFault => self.config.p_arm_fault,
        };
        scheduled || (p > 0.0 && self.rng.random_bool(p))
    }

    /// Where a commanded tool pose really ends, for the arm `arm` (0 = PSM1) whose remote
    /// centre of motion is `rcm`: its direction from the RCM turned by the yaw (about +z) and
    /// pitch (about the horizontal axis across it) offsets, its distance from the RCM
    /// lengthened by the insertion offset.
    pub fn actual_pose(&self, arm: usize, rcm: &Point, commanded: &Pose) -> Pose {
        let [yaw, pitch, insertion] = self
            .config
            .joint_offsets
            .get(arm)
            .copied()
            .unwrap_or_default();
        if yaw == 0.0 && pitch == 0.0 && insertion == 0.0 {
            return *commanded;
        }
        let d = commanded.translation.vector - rcm.coords;
        let length = d.norm();
        let Some(dir) = d.try_normalize(1e-9) else {
            return *commanded;
        };
        let across = Vector::z()
            .cross(&dir)
            .try_normalize(1e-9)
            .unwrap_or_else(Vector::x);
        let r = UnitQuaternion::from_scaled_axis(Vector::z() * yaw)
            * UnitQuaternion::from_scaled_axis(across * pitch);
        let p = rcm.coords + r * (dir * (length + insertion));
        Pose::from_parts(Translation3::from(p), r * commanded.rotation)
    }

    /// The hand-eye error transform applied to estimates.
    pub fn hand_eye(&self) -> Pose {
        let t = self.config.hand_eye_translation_m;
        let r = self.config.hand_eye_rotation_rad;
        Pose::from_parts(
            Translation3::new(t[0], t[1], t[2]),
            UnitQuaternion::from_scaled_axis(Vector::new(r[0], r[1], r[2])),
        )
    }

    /// How a slip turns the needle in the jaw (about the needle's normal).
    pub fn slip(&self) -> Pose {
        let angle = if self.config.slip_rad == 0.0 {
            15f64.to_radians()
        } else {
            self.config.slip_rad
        };
        Pose::from_parts(
            Translation3::identity(),
            UnitQuaternion::from_scaled_axis(Vector::z() * angle),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Streams, Subsystem};

    fn faults(config: FaultConfig) -> Faults {
        Faults::new(config, Streams::new(1).rng(Subsystem::Faults)).expect("faults")
    }

    #[test]
    fn a_scheduled_fault_fires_at_its_event_only() {
        let mut f = faults(FaultConfig {
            schedule: vec![ScheduledFault {
                kind: FaultKind::MissedGrasp,
                nth: 2,
            }],
            ..FaultConfig::default()
        });
        let fired: Vec<bool> = (0..4).map(|_| f.fires(FaultKind::MissedGrasp)).collect();
        assert_eq!(fired, vec![false, true, false, false]);
        assert!(!f.fires(FaultKind::ArmFault));
    }

    #[test]
    fn joint_offsets_move_the_tool_tip_as_hand_computed() {
        // PSM1 with 5 mm of insertion error, 10 cm straight below its RCM.
        let f = faults(FaultConfig {
            joint_offsets: [[0.0, 0.0, 0.005], [0.0; 3]],
            ..FaultConfig::default()
        });
        let rcm = Point::new(0.0, 0.0, 0.0);
        let cmd = Pose::from_parts(
            Translation3::new(0.0, 0.0, -0.1),
            UnitQuaternion::identity(),
        );
        let p = f.actual_pose(0, &rcm, &cmd);
        assert!((p.translation.vector - Vector::new(0.0, 0.0, -0.105)).norm() < 1e-12);
        // 5° of yaw swings a tip 10 cm out from the RCM along +x by 10·sin 5° mm sideways.
        let f = faults(FaultConfig {
            joint_offsets: [[5f64.to_radians(), 0.0, 0.0], [0.0; 3]],
            ..FaultConfig::default()
        });
        let cmd = Pose::from_parts(Translation3::new(0.1, 0.0, 0.0), UnitQuaternion::identity());
        let p = f.actual_pose(0, &rcm, &cmd);
        assert!((p.translation.vector.y - 0.1 * 5f64.to_radians().sin()).abs() < 1e-12);
        // The other arm is untouched.
        assert_eq!(f.actual_pose(1, &rcm, &cmd), cmd);
    }

    #[test]
    fn offsets_beyond_the_srcs_range_are_refused() {
        let c = FaultConfig {
            joint_offsets: [[0.0, 0.0, 0.006], [0.0; 3]],
            ..FaultConfig::default()
        };
        assert!(c.validate().is_err());
        let c = FaultConfig {
            schedule: vec![ScheduledFault {
                kind: FaultKind::ArmFault,
                nth: 0,
            }],
            ..FaultConfig::default()
        };
        assert!(c.validate().is_err());
    }
}
