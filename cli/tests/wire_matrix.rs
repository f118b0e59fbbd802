//! The fault matrix's wire cells, over real DDS on loopback: every misbehaviour `stitch
//! sim-node --wire-fault` can put on the CRTK topics (an `error` and FAULT, busy that never
//! clears, stale or zero stamps, a lost motion command, a dVRK that takes no more motions, a
//! silent side channel) at a motion command in each phase of STITCH + Human's first throw.
//! By default (and in CI) it runs the diagonal: each wire fault once, at the middle of one
//! phase, the phases taken in turn (7 cells, about 2 minutes). `STITCH_WIRE_MATRIX=middle`
//! runs each fault at the middle of each phase (42 cells, about 10 minutes);
//! `STITCH_WIRE_MATRIX=full` at the start, the middle and the end, as the in-process matrix
//! does (`tests/matrix.rs`).
//!
//! Each cell must end (exit 0, 4 or 5, within its deadline; never a panic), and its journal
//! must be complete (the last record the outcome), fail (if it fails) with its failing
//! step's phase's class, and hold both arms after a failure (journal and sim-node both say
//! so). The phases' motion commands are counted on the in-process twin of the fault-free run
//! (arm and jaw motions, as the sim-node numbers them).
#![cfg(feature = "ros2")]

mod support;

use std::sync::Arc;
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::Duration;
use stitch_engine::{
    Entry, PlanLoader, Record, RunOutcome, Runner, ScriptLimits, ScriptedSupervisor, load_plan,
};
use stitch_primitives::{
    Observation, ObserveRequest, PrimitiveError, Primitives, RobotPrimitives, StepControl,
    StepOutcome, StepRequest, mock_primitives,
};
use stitch_robot::{Arm, Jaw, MoveHandle, Pose, RobotError, SimClock, SpeedLimits, Wound};
use stitch_sim::{SceneConfig, SensingConfig};
use support::{SimNode, run, serial, tmp};

const PLAN: &str = "stitch_human.rhai";
const SEED: u64 = 1;
const PHASES: [&str; 6] = ["insert", "sweep", "extract", "cinch", "handover", "correct"];
const FAULTS: [&str; 7] = [
    "arm-error",
    "busy-stuck",
    "stale-stamps",
    "zero-stamps",
    "drop-command",
    "deaf",
    "oracle-silent",
];

/// An arm whose motion commands are counted.
struct CountedArm(Arc<dyn Arm>, Arc<AtomicU32>);
impl Arm for CountedArm {
    fn name(&self) -> &str {
        self.0.name()
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        self.0.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        self.0.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        self.1.fetch_add(1, Ordering::SeqCst);
        self.0.move_cp(goal)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        self.1.fetch_add(1, Ordering::SeqCst);
        self.0.servo_cp(goal)
    }
    fn hold(&self) -> Result<(), RobotError> {
        self.0.hold()
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        self.0.set_max_speed(limits)
    }
}

/// A jaw whose motion commands are counted.
struct CountedJaw(Arc<dyn Jaw>, Arc<AtomicU32>);
impl Jaw for CountedJaw {
    fn name(&self) -> &str {
        self.0.name()
    }
    fn measured_jp(&self) -> Result<f64, RobotError> {
        self.0.measured_jp()
    }
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        self.1.fetch_add(1, Ordering::SeqCst);
        self.0.move_jp(angle_rad)
    }
    fn open(&self) -> Result<MoveHandle, RobotError> {
        self.1.fetch_add(1, Ordering::SeqCst);
        self.0.open()
    }
    fn close(&self) -> Result<MoveHandle, RobotError> {
        self.1.fetch_add(1, Ordering::SeqCst);
        self.0.close()
    }
}

/// The primitives, noting the motion count around each step attempt.
struct Windows {
    inner: RobotPrimitives,
    motions: Arc<AtomicU32>,
    steps: Vec<(&'static str, u32, u32)>,
}
impl Primitives for Windows {
    fn run(&mut self, req: &StepRequest<'_>, control: &mut dyn StepControl) -> StepOutcome {
        let before = self.motions.load(Ordering::SeqCst);
        let out = self.inner.run(req, control);
        let after = self.motions.load(Ordering::SeqCst);
        self.steps.push((req.kind.name(), before, after));
        out
    }
    fn observe(&mut self, req: &ObserveRequest<'_>) -> Observation {
        self.inner.observe(req)
    }
    fn hold_all(&mut self) -> Result<(), PrimitiveError> {
        self.inner.hold_all()
    }
}

/// Each phase's motion commands in the fault-free run (its first attempt in throw 1): the
/// first and the last, numbered from 1 as the sim-node numbers them.
fn windows() -> Vec<(&'static str, u32, u32)> {
    let scene = SceneConfig::default();
    let wound = Wound::linear(&scene.wound).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let plan = load_plan(&loader, &support::root().join("scripts").join(PLAN))
        .unwrap_or_else(|e| panic!("{e}"))
        .plan;
    let clock = SimClock::new();
    let (inner, _world) =
        mock_primitives(&scene, SensingConfig::default(), SEED, clock.clone()).expect("mock");
    let motions = Arc::new(AtomicU32::new(0));
    let m = Arc::clone(&motions);
    let inner = inner.map_rig(move |mut rig| {
        rig.right = Arc::new(CountedArm(rig.right, Arc::clone(&m)));
        rig.left = Arc::new(CountedArm(rig.left, Arc::clone(&m)));
        rig.right_jaw = Arc::new(CountedJaw(rig.right_jaw, Arc::clone(&m)));
        rig.left_jaw = Arc::new(CountedJaw(rig.left_jaw, Arc::clone(&m)));
        rig
    });
    let mut p = Windows {
        inner,
        motions,
        steps: Vec::new(),
    };
    let mut supervisor = ScriptedSupervisor::default();
    let _ = Runner::new(
        Arc::new(plan),
        &mut p,
        &mut supervisor,
        Arc::new(clock),
        Some(SEED),
    )
    .run();
    PHASES
        .iter()
        .map(|phase| {
            let (_, before, after) = p
                .steps
                .iter()
                .find(|(name, ..)| name == phase)
                .copied()
                .unwrap_or_else(|| panic!("the fault-free run has no {phase}"));
            assert!(after > before, "{phase} commands no motion");
            (*phase, before + 1, after)
        })
        .collect()
}

fn domain() -> String {
    (40 + (std::process::id() % 20) * 10).to_string()
}

fn records(journal: &str) -> Result<Vec<Record>, String> {
    journal
        .lines()
        .map(|l| serde_json::from_str::<Record>(l).map_err(|e| format!("{e}: {l}")))
        .collect()
}

/// One cell's checks; its code (`C`, a class letter, `A`) or what is wrong.
fn cell(fault: &str, nth: u32) -> Result<String, String> {
    let d = domain();
    let wire = format!("{fault}@{nth}");
    let node = SimNode::start(&d, &["--wire-fault", &wire]);
    let config = tmp("wire-matrix.toml");
    std::fs::write(&config, "move_timeout_s = 2.0\n").expect("config");
    let journal = tmp("wire-matrix.jsonl");
    let plan = format!("scripts/{PLAN}");
    let seed = SEED.to_string();
    let ran = run(
        &[
            &plan,
            "--seed",
            &seed,
            "--robot",
            "ros2",
            "--domain-id",
            &d,
            "--dvrk-config",
            config.to_str().expect("utf-8"),
        ],
        &journal,
        Duration::from_secs(180),
    );
    if !matches!(ran.code, Some(0 | 4 | 5)) {
        return Err(format!("exit {:?}: {}", ran.code, ran.out));
    }
    let records = records(&ran.journal)?;
    let outcome = match records.last().map(|r| &r.entry) {
        Some(Entry::Finished { outcome }) => outcome.clone(),
        other => return Err(format!("the journal ends with {other:?}, not the outcome")),
    };
    for (i, r) in records.iter().enumerate() {
        if r.seq != i as u64 {
            return Err(format!("journal record {i} is numbered {}", r.seq));
        }
    }
    let code = match &outcome {
        RunOutcome::Completed => return Ok("C".into()),
        RunOutcome::Failed { class, .. } => class.code().to_string(),
        RunOutcome::Aborted { .. } => "A".into(),
    };
    if let RunOutcome::Failed {
        class,
        step,
        reason,
        ..
    } = &outcome
    {
        let primitive = records.iter().rev().find_map(|r| match &r.entry {
            Entry::StepEnd {
                primitive, step: s, ..
            } if s == step => Some(primitive.clone()),
            _ => None,
        });
        let expected = match (reason, primitive.as_deref()) {
            (Some(r), _) if r.is_thread() => 'T',
            (_, Some("insert" | "correct")) => 'I',
            (_, Some("extract")) => 'E',
            (_, Some("handover")) => 'H',
            (_, Some("sweep" | "cinch")) => 'T',
            _ => class.code(),
        };
        if class.code() != expected {
            return Err(format!(
                "failed as class {}, its step's phase is {expected}",
                class.code()
            ));
        }
    }
    let last_step = records
        .iter()
        .rposition(|r| matches!(r.entry, Entry::StepEnd { .. } | Entry::Unobserved { .. }));
    let held = records[last_step.map_or(0, |i| i + 1)..]
        .iter()
        .any(|r| matches!(r.entry, Entry::Hold { .. }));
    if !held {
        return Err("failed or aborted without a hold journaled after the end".into());
    }
    node.held_both()
        .map_err(|log| format!("the sim-node was not told to hold both arms:\n{log}"))?;
    Ok(code)
}

#[test]
fn every_wire_fault_in_every_phase_ends_safe() {
    // The whole matrix takes 10 minutes or more on 2 cores: by default only its diagonal.
    let mode = std::env::var("STITCH_WIRE_MATRIX").unwrap_or_else(|_| "diagonal".into());
    let (full, diagonal) = match mode.as_str() {
        "diagonal" => (false, true),
        "middle" => (false, false),
        "full" => (true, false),
        other => panic!("STITCH_WIRE_MATRIX={other:?}: expected diagonal, middle or full"),
    };
    let _one = serial();
    let windows = windows();
    let mut broken = Vec::new();
    let mut table = format!(
        "| wire fault | {} |\n|---|{}\n",
        PHASES.join(" | "),
        "---|".repeat(PHASES.len())
    );
    for (k, fault) in FAULTS.iter().enumerate() {
        let mut row = Vec::new();
        for (p, (phase, first, last)) in windows.iter().enumerate() {
            if diagonal && p != k % windows.len() {
                row.push("·".to_string());
                continue;
            }
            let at: Vec<u32> = if full {
                vec![*first, (first + last) / 2, *last]
            } else {
                vec![(first + last) / 2]
            };
            let mut codes = Vec::new();
            for nth in at {
                match cell(fault, nth) {
                    Ok(c) => codes.push(c),
                    Err(e) => {
                        broken.push(format!("{fault}@{nth} ({phase}): {e}"));
                        codes.push("✗".into());
                    }
                }
            }
            row.push(codes.join(" "));
        }
        table.push_str(&format!("| {fault} | {} |\n", row.join(" | ")));
    }
    eprintln!(
        "wire matrix ({}), motions per phase {windows:?}:\n{table}",
        if full {
            "start, middle, end"
        } else if diagonal {
            "diagonal, middle"
        } else {
            "middle"
        }
    );
    assert!(
        broken.is_empty(),
        "{} cells broke a rule:\n{}",
        broken.len(),
        broken.join("\n")
    );
}
