//! The primitives' commanded poses, with a known needle pose: the paper's offsets and
//! rotations, checked against what dummy arms were told.

use rand::SeedableRng;
use std::sync::Arc;
use std::time::Duration;
use stitch_perception::{NeedleEstimate, NeedleEstimator, PerceptionError};
use stitch_primitives::{
    CorrectParams, ExtractParams, FailureKind, HANDOVER_INSET_RAD, HandoverParams, Layout,
    Primitives, Rig, RobotPrimitives, StepKind, StepOutcome, StepRequest, rotated_about,
};
use stitch_robot::nalgebra::{Translation3, UnitQuaternion};
use stitch_robot::{ArmCommand, DummyArm, DummyJaw, Needle, Point, Pose, Vector, WoundPoint};

/// Estimates a needle fixed in the world.
struct Fixed(Pose);
impl NeedleEstimator for Fixed {
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError> {
        Ok(NeedleEstimate {
            pose: self.0,
            confidence: 1.0,
            stamp: Duration::ZERO,
        })
    }
}

/// Estimates a needle held by a dummy arm through a fixed grasp.
struct Held(Arc<DummyArm>, Pose);
impl NeedleEstimator for Held {
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError> {
        let tool = *self.0.pose.lock().expect("pose");
        Ok(NeedleEstimate {
            pose: tool * self.1,
            confidence: 1.0,
            stamp: Duration::ZERO,
        })
    }
}

fn at(x: f64, y: f64, z: f64) -> Pose {
    Pose::from_parts(Translation3::new(x, y, z), UnitQuaternion::identity())
}

fn layout() -> Layout {
    Layout {
        correction_point: Point::new(-0.04, -0.03, -0.11),
        left_ready: Point::new(0.04, 0.02, -0.09),
        handover_point: Point::new(-0.015, 0.02, -0.09),
        right_ready: Point::new(-0.03, 0.0, -0.09),
    }
}

fn rig(
    right: Arc<dyn stitch_robot::Arm>,
    left: Arc<dyn stitch_robot::Arm>,
    estimator: Box<dyn NeedleEstimator>,
) -> RobotPrimitives {
    RobotPrimitives::new(Rig {
        right,
        left,
        right_jaw: Arc::new(DummyJaw::new("PSM1/jaw")),
        left_jaw: Arc::new(DummyJaw::new("PSM2/jaw")),
        estimator,
        observer: None,
        needle: Needle::default(),
        layout: layout(),
        rng: rand_chacha::ChaCha8Rng::seed_from_u64(1),
    })
}

fn moves(arm: &DummyArm) -> Vec<Pose> {
    arm.commands()
        .into_iter()
        .filter_map(|c| match c {
            ArmCommand::MoveCp(p) => Some(p),
            _ => None,
        })
        .collect()
}

fn run(p: &mut RobotPrimitives, kind: StepKind) -> StepOutcome {
    let point = WoundPoint {
        index: 0,
        entry: Point::new(-0.005, 0.0, -0.12),
        exit: Point::new(0.005, 0.0, -0.12),
    };
    p.run(
        &StepRequest {
            throw: 0,
            step: 0,
            point: &point,
            kind: &kind,
            attempt: 0,
        },
        &mut stitch_primitives::Uninterrupted,
    )
}

fn same(a: &Pose, b: &Pose) -> bool {
    (a.translation.vector - b.translation.vector).norm() < 1e-9
        && a.rotation.angle_to(&b.rotation) < 1e-9
}

/// A needle lodged after insertion: plane x–z, normal +y, tip out beyond the exit.
fn lodged() -> Pose {
    let r = stitch_robot::nalgebra::Rotation3::from_basis_unchecked(&[
        -Vector::z(),
        -Vector::x(),
        Vector::y(),
    ]);
    let start = Pose::from_parts(
        Translation3::new(0.002, 0.0, -0.108),
        UnitQuaternion::from_rotation_matrix(&r),
    );
    rotated_about(
        &start,
        &Point::new(0.002, 0.0, -0.108),
        &Vector::y(),
        -45f64.to_radians(),
    )
}

#[test]
fn extraction_goes_one_centimetre_off_the_nearer_end_then_in_turns_eighty_degrees_and_pulls() {
    let needle = lodged();
    let tip = needle * Needle::default().tip();
    let left = Arc::new(DummyArm::new("PSM2"));
    *left.pose.lock().expect("pose") = at(0.04, 0.02, -0.09);
    let right = Arc::new(DummyArm::new("PSM1"));
    let mut p = rig(right, left.clone(), Box::new(Fixed(needle)));
    let params = ExtractParams::default();
    let out = run(&mut p, StepKind::Extract(params));
    // The needle never moved (a fixed estimate): no progress, retryable.
    match out {
        StepOutcome::Failed(f) => {
            assert_eq!(f.kind, FailureKind::NoProgress);
            assert_eq!(f.measured.endpoint_travel_m, Some(0.0));
        }
        other => panic!("{other:?}"),
    }
    let m = moves(&left);
    let h = {
        let d = Point::new(0.04, 0.02, -0.09) - tip;
        Vector::new(d.x, d.y, 0.0).normalize()
    };
    // Stand-off 1 cm horizontally from the tip (the end nearer the left driver), then 1.5 cm
    // towards it.
    assert!((m[0].translation.vector - (tip.coords + h * 0.01)).norm() < 1e-9);
    assert!((m[1].translation.vector - (tip.coords - h * 0.005)).norm() < 1e-9);
    // Sixteen 5° steps: the last is the grasp pose turned 80° about the needle's axis.
    let c = needle * Point::origin();
    let n = needle * Vector::z();
    let turned = rotated_about(&m[1], &c, &n, -80f64.to_radians());
    assert!(same(&m[17], &turned));
    // Then a 3 cm pull away and up; then, no progress, back to the stand-off.
    let pull = (h + Vector::z()).normalize() * 0.03;
    assert!((m[18].translation.vector - (turned.translation.vector + pull)).norm() < 1e-9);
    assert!(same(&m[19], &m[0]));
}

#[test]
fn handover_goes_one_centimetre_off_the_farther_end_across_the_needle_then_onto_it() {
    let left = Arc::new(DummyArm::new("PSM2"));
    *left.pose.lock().expect("pose") = at(0.01, 0.02, -0.09);
    // The left holds the needle near its tip; the swage is farther from it.
    let needle = Pose::from_parts(
        Translation3::new(0.0, 0.02, -0.09),
        UnitQuaternion::identity(),
    ) * Pose::from_parts(
        Translation3::identity(),
        UnitQuaternion::from_axis_angle(&Vector::x_axis(), std::f64::consts::FRAC_PI_2),
    );
    let right = Arc::new(DummyArm::new("PSM1"));
    *right.pose.lock().expect("pose") = at(-0.03, 0.05, -0.09);
    let mut p = rig(right.clone(), left, Box::new(Fixed(needle)));
    let out = run(&mut p, StepKind::Handover(HandoverParams::default()));
    // The estimate never changes: the normal did not change, so the grasp "did not take".
    match out {
        StepOutcome::Failed(f) => assert_eq!(
            (f.kind, f.measured.normal_change_rad),
            (FailureKind::NoProgress, Some(0.0))
        ),
        other => panic!("{other:?}"),
    }
    let target = needle * Needle::default().point_at(std::f64::consts::PI - HANDOVER_INSET_RAD);
    // The approach runs across the needle's plane, along its normal, from the right
    // driver's side.
    let n = needle * Vector::z();
    let h = if n.dot(&(Point::new(-0.03, 0.05, -0.09) - target)) >= 0.0 {
        n
    } else {
        -n
    };
    let m = moves(&right);
    assert!(
        (m[0].translation.vector - (target.coords + h * 0.01)).norm() < 1e-9,
        "1 cm off"
    );
    assert!(
        (m[1].translation.vector - target.coords).norm() < 1e-9,
        "onto the re-grasp point"
    );
    // The tug turns 20° about the horizontal axis across the approach; then back off.
    assert!((m[2].rotation.angle_to(&m[1].rotation) - 20f64.to_radians()).abs() < 1e-9);
    assert!(same(&m[3], &m[0]));
}

#[test]
fn correction_takes_the_needle_to_the_corner_aligns_its_normal_with_y_and_turns_ninety_degrees() {
    let right = Arc::new(DummyArm::new("PSM1"));
    let start = Pose::from_parts(
        Translation3::new(-0.02, 0.01, -0.1),
        UnitQuaternion::from_euler_angles(0.4, -0.3, 1.1),
    );
    *right.pose.lock().expect("pose") = start;
    let grasp = Pose::from_parts(
        Translation3::new(0.01, 0.006, 0.0),
        UnitQuaternion::from_euler_angles(0.1, 0.2, -0.5),
    );
    let left = Arc::new(DummyArm::new("PSM2"));
    let mut p = rig(right.clone(), left, Box::new(Held(right.clone(), grasp)));
    let out = run(&mut p, StepKind::Correct(CorrectParams::default()));
    assert!(matches!(out, StepOutcome::Succeeded { .. }), "{out:?}");
    let m = moves(&right);
    assert_eq!(m.len(), 3);
    // 1. The needle's centre to the corner, orientation unchanged.
    let centre = |t: &Pose| (t * grasp) * Point::origin();
    assert!((centre(&m[0]) - layout().correction_point).norm() < 1e-9);
    assert!(m[0].rotation.angle_to(&start.rotation) < 1e-9);
    // 2. Its normal along +y, centre still at the corner.
    assert!(((m[1] * grasp) * Vector::z() - Vector::y()).norm() < 1e-9);
    assert!((centre(&m[1]) - layout().correction_point).norm() < 1e-9);
    // 3. A 90° turn about +y through the centre: the normal stays +y.
    let turned = rotated_about(
        &m[1],
        &layout().correction_point,
        &Vector::y(),
        90f64.to_radians(),
    );
    assert!(same(&m[2], &turned));
}

/// A motion that never finishes: its tracker reports a timeout at once.
#[derive(Debug)]
struct Stuck;
impl stitch_robot::MotionTracker for Stuck {
    fn is_busy(&self) -> bool {
        true
    }
    fn wait(&self, timeout: Duration) -> Result<(), stitch_robot::RobotError> {
        Err(stitch_robot::RobotError::Timeout {
            arm: "PSM1".into(),
            after_s: timeout.as_secs_f64(),
        })
    }
    fn stop(&self) -> Result<(), stitch_robot::RobotError> {
        Ok(())
    }
}

/// An arm whose every motion gets stuck.
struct StuckArm(DummyArm);
impl stitch_robot::Arm for StuckArm {
    fn name(&self) -> &str {
        "PSM1"
    }
    fn measured_cp(&self) -> Result<Pose, stitch_robot::RobotError> {
        self.0.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, stitch_robot::RobotError> {
        self.0.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<stitch_robot::MoveHandle, stitch_robot::RobotError> {
        let _ = self.0.move_cp(goal)?;
        Ok(stitch_robot::MoveHandle::new(Arc::new(Stuck)))
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), stitch_robot::RobotError> {
        self.0.servo_cp(goal)
    }
    fn hold(&self) -> Result<(), stitch_robot::RobotError> {
        self.0.hold()
    }
}

#[test]
fn a_motion_that_never_finishes_stops_the_step_as_an_arm_fault() {
    let right = Arc::new(StuckArm(DummyArm::new("PSM1")));
    let left = Arc::new(DummyArm::new("PSM2"));
    let estimator = Box::new(Fixed(at(0.0, 0.0, -0.1)));
    let mut p = rig(right.clone(), left, estimator);
    match run(&mut p, StepKind::default_for("insert").expect("insert")) {
        StepOutcome::Failed(f) => match f.kind {
            FailureKind::ArmFault { message } => {
                assert!(message.contains("did not finish within 30"), "{message}")
            }
            other => panic!("{other:?}"),
        },
        other => panic!("{other:?}"),
    }
    // It gave up after the first move: no further motion was sent.
    assert_eq!(right.0.commands().len(), 1);
}

/// An arm whose `measured_cp` answers `good` times, then only stale (as a dVRK link whose
/// measurements stopped arriving).
struct StaleAfter {
    arm: Arc<DummyArm>,
    good: usize,
    reads: std::sync::atomic::AtomicUsize,
}
impl stitch_robot::Arm for StaleAfter {
    fn name(&self) -> &str {
        "PSM1"
    }
    fn measured_cp(&self) -> Result<Pose, stitch_robot::RobotError> {
        let n = self.reads.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        if n < self.good {
            self.arm.measured_cp()
        } else {
            Err(stitch_robot::RobotError::Stale {
                arm: "PSM1".into(),
                age_s: 0.3,
            })
        }
    }
    fn setpoint_cp(&self) -> Result<Pose, stitch_robot::RobotError> {
        self.arm.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<stitch_robot::MoveHandle, stitch_robot::RobotError> {
        self.arm.move_cp(goal)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), stitch_robot::RobotError> {
        self.arm.servo_cp(goal)
    }
    fn hold(&self) -> Result<(), stitch_robot::RobotError> {
        self.arm.hold()
    }
}

/// Sees the needle only when told which jaw holds it (as the pipeline, that searches near
/// the jaw): without the hint, nothing.
struct NeedsJaw(Arc<DummyArm>, Pose);
impl NeedleEstimator for NeedsJaw {
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError> {
        Err(PerceptionError::NotFound)
    }
    fn estimate_needle_with(
        &mut self,
        hint: Option<&stitch_perception::NeedleHint>,
    ) -> Result<NeedleEstimate, PerceptionError> {
        match hint {
            Some(stitch_perception::NeedleHint::Held(_)) => {
                Held(self.0.clone(), self.1).estimate_needle()
            }
            _ => Err(PerceptionError::NotFound),
        }
    }
}

#[test]
fn an_arm_that_cannot_say_where_its_jaw_is_stops_the_step_as_an_arm_fault_not_a_dropout() {
    // The correction reads the right arm three times: its pose, the jaw for the first
    // estimate, the jaw for the samples at the corner. The third read is stale: the samples
    // must not be taken without the jaw (they would see nothing: a dropout that hides the
    // arm's fault, as one ROS 2 mission once diverged from its in-process twin).
    let inner = Arc::new(DummyArm::new("PSM1"));
    *inner.pose.lock().expect("pose") = at(-0.02, 0.01, -0.1);
    let right = Arc::new(StaleAfter {
        arm: inner.clone(),
        good: 2,
        reads: Default::default(),
    });
    let grasp = at(0.01, 0.006, 0.0);
    let estimator = Box::new(NeedsJaw(inner.clone(), grasp));
    let mut p = rig(right, Arc::new(DummyArm::new("PSM2")), estimator);
    match run(&mut p, StepKind::Correct(CorrectParams::default())) {
        StepOutcome::Failed(f) => match f.kind {
            FailureKind::ArmFault { message } => {
                assert!(
                    message.contains("PSM1: measurement is 0.300 s old"),
                    "{message}"
                )
            }
            other => panic!("expected an arm fault, got {other:?}"),
        },
        other => panic!("{other:?}"),
    }
    // It went to the corner and no further: nothing moved after the failed read.
    assert_eq!(moves(&inner).len(), 1);
}

/// An arm that refuses to hold.
struct NoHold(DummyArm);
impl stitch_robot::Arm for NoHold {
    fn name(&self) -> &str {
        self.0.name()
    }
    fn measured_cp(&self) -> Result<Pose, stitch_robot::RobotError> {
        self.0.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, stitch_robot::RobotError> {
        self.0.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<stitch_robot::MoveHandle, stitch_robot::RobotError> {
        self.0.move_cp(goal)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), stitch_robot::RobotError> {
        self.0.servo_cp(goal)
    }
    fn hold(&self) -> Result<(), stitch_robot::RobotError> {
        Err(stitch_robot::RobotError::Fault {
            arm: self.0.name().into(),
            message: "hold refused".into(),
        })
    }
}

#[test]
fn a_hold_both_arms_refuse_says_both() {
    let estimator = Box::new(Fixed(at(0.0, 0.0, -0.1)));
    let mut p = rig(
        Arc::new(NoHold(DummyArm::new("PSM1"))),
        Arc::new(NoHold(DummyArm::new("PSM2"))),
        estimator,
    );
    let e = p.hold_all().expect_err("refused").to_string();
    assert!(e.contains("PSM1: fault: hold refused"), "{e}");
    assert!(e.contains("PSM2: fault: hold refused"), "{e}");
}
