//! The fault matrix, in process: every fault the mock dVRK injects at an event (perception
//! dropout, missed grasp, needle slip, stale measurement, arm fault), scheduled at the start,
//! the middle and the end of every phase of STITCH + Human's first throw (insert, sweep,
//! extract, cinch, handover, correct, and the step re-run after an intervention), and the
//! constant calibration faults (joint offsets, hand-eye). Each cell's run must end —
//! completed, failed with the class its failing step's phase gives, or aborted — without a
//! panic or a hang; no primitive may run after the failure that ended it; the arms must be
//! held at the end of every run (completed ones too); the journal must be complete (numbered
//! without a gap, ending with the outcome) and must say what the primitives reported.
//!
//! The matrix is written to `docs/reliability.md` (between its generated-table markers);
//! `STITCH_UPDATE_DOCS=1` rewrites it, else a stale table fails the test.

use std::sync::Arc;
use std::sync::mpsc;
use std::time::Duration;
use stitch_engine::{
    Entry, FailureClass, Plan, PlanLoader, Report, RunOutcome, Runner, ScriptLimits,
    ScriptedSupervisor, load_plan,
};
use stitch_primitives::{
    FailureKind, Observation, ObserveRequest, PrimitiveError, Primitives, RobotPrimitives,
    StepControl, StepOutcome, StepRequest, mock_primitives,
};
use stitch_robot::{SimClock, Wound};
use stitch_sim::{
    FaultConfig, FaultKind, MAX_JOINT_OFFSET, MockDvrk, SceneConfig, ScheduledFault, SensingConfig,
    ThreadConfig,
};

const SEED: u64 = 1;
const PLAN: &str = "stitch_human.rhai";
/// The longest a cell's run may take before it counts as a hang, s (they take milliseconds).
const HANG_S: u64 = 60;
const BEGIN: &str = "<!-- BEGIN GENERATED FAULT MATRIX -->";
const END: &str = "<!-- END GENERATED FAULT MATRIX -->";

/// The phases, as columns: a primitive's first attempt in throw 1, and the step re-run after
/// an intervention.
const PHASES: [&str; 7] = [
    "insert",
    "sweep",
    "extract",
    "cinch",
    "handover",
    "correct",
    "intervention",
];

/// One call the engine made on the primitives, with the mock's fault event counters around
/// it and what the primitives really reported.
#[derive(Clone, Debug)]
enum Call {
    Run {
        primitive: &'static str,
        before: [u32; 5],
        after: [u32; 5],
        outcome: Box<StepOutcome>,
    },
    Hold,
    Observe,
}

/// The mock's primitives, recording every call. `ignore_arm_faults` makes it the broken
/// robot layer the matrix must catch: it reports an arm fault to the engine as a success.
struct Probe {
    inner: RobotPrimitives,
    world: MockDvrk,
    calls: Vec<Call>,
    ignore_arm_faults: bool,
}

fn counters(world: &MockDvrk) -> [u32; 5] {
    FaultKind::ALL.map(|k| world.fault_events(k))
}

impl Primitives for Probe {
    fn run(&mut self, req: &StepRequest<'_>, control: &mut dyn StepControl) -> StepOutcome {
        let before = counters(&self.world);
        let outcome = self.inner.run(req, control);
        self.calls.push(Call::Run {
            primitive: req.kind.name(),
            before,
            after: counters(&self.world),
            outcome: Box::new(outcome.clone()),
        });
        match outcome {
            StepOutcome::Failed(f)
                if self.ignore_arm_faults && matches!(f.kind, FailureKind::ArmFault { .. }) =>
            {
                StepOutcome::Succeeded {
                    measured: f.measured,
                }
            }
            other => other,
        }
    }

    fn observe(&mut self, req: &ObserveRequest<'_>) -> Observation {
        self.calls.push(Call::Observe);
        self.inner.observe(req)
    }

    fn hold_all(&mut self) -> Result<(), PrimitiveError> {
        self.calls.push(Call::Hold);
        self.inner.hold_all()
    }
}

fn plan() -> Plan {
    let scene = SceneConfig::default();
    let wound = Wound::linear(&scene.wound).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scripts")
        .join(PLAN);
    load_plan(&loader, &path)
        .unwrap_or_else(|e| panic!("{e}"))
        .plan
}

/// A scene in which only the injected faults go wrong: exact perception is set by the caller,
/// the thread neither hides the needle nor catches.
fn scene(faults: FaultConfig) -> SceneConfig {
    SceneConfig {
        thread: ThreadConfig {
            catch_radius_m: 0.0,
            occlusion_radius_m: 0.0,
            ..ThreadConfig::default()
        },
        faults,
        ..SceneConfig::default()
    }
}

/// One run of the plan with `faults`, on its own thread: the report and the calls, or why it
/// did not end (a panic, or no end within [`HANG_S`]).
fn run(faults: FaultConfig, ignore_arm_faults: bool) -> Result<(Report, Vec<Call>), String> {
    let (tx, rx) = mpsc::channel();
    let worker = std::thread::spawn(move || {
        let clock = SimClock::new();
        let (inner, world) = mock_primitives(
            &scene(faults),
            SensingConfig::perfect(),
            SEED,
            clock.clone(),
        )
        .expect("mock");
        let mut probe = Probe {
            inner,
            world,
            calls: Vec::new(),
            ignore_arm_faults,
        };
        let mut supervisor = ScriptedSupervisor::default();
        let report = Runner::new(
            Arc::new(plan()),
            &mut probe,
            &mut supervisor,
            Arc::new(clock),
            Some(SEED),
        )
        .run();
        let _ = tx.send((report, probe.calls));
    });
    match rx.recv_timeout(Duration::from_secs(HANG_S)) {
        Ok(r) => {
            let _ = worker.join();
            Ok(r)
        }
        Err(mpsc::RecvTimeoutError::Timeout) => Err(format!("no end within {HANG_S} s")),
        Err(mpsc::RecvTimeoutError::Disconnected) => match worker.join() {
            Err(p) => Err(format!(
                "panicked: {}",
                p.downcast_ref::<String>()
                    .cloned()
                    .or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()))
                    .unwrap_or_default()
            )),
            Ok(()) => Err("the run's thread ended without a report".into()),
        },
    }
}

/// What a cell shows: `C` completed, the class letter of a failure, `A` aborted.
fn code(outcome: &RunOutcome) -> String {
    match outcome {
        RunOutcome::Completed => "C".into(),
        RunOutcome::Failed { class, .. } => class.code().to_string(),
        RunOutcome::Aborted { .. } => "A".into(),
    }
}

/// The matrix's checks on one run; the cell's code, or what is wrong.
fn check(plan: &Plan, report: &Report, calls: &[Call]) -> Result<String, String> {
    let records = report.journal.records();
    // The journal is complete: numbered from 0 without a gap, ending with the outcome.
    for (i, r) in records.iter().enumerate() {
        if r.seq != i as u64 {
            return Err(format!("journal record {i} is numbered {}", r.seq));
        }
    }
    match records.last().map(|r| &r.entry) {
        Some(Entry::Finished { outcome }) if *outcome == report.outcome => {}
        other => return Err(format!("the journal ends with {other:?}, not the outcome")),
    }
    // It says what the primitives reported, attempt by attempt.
    let journaled: Vec<(&str, &StepOutcome)> = records
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::StepEnd {
                primitive, outcome, ..
            } => Some((primitive.as_str(), outcome)),
            _ => None,
        })
        .collect();
    let reported: Vec<(&str, &StepOutcome)> = calls
        .iter()
        .filter_map(|c| match c {
            Call::Run {
                primitive, outcome, ..
            } => Some((*primitive, outcome.as_ref())),
            _ => None,
        })
        .collect();
    if journaled.len() != reported.len() {
        return Err(format!(
            "{} step attempts journaled, {} run",
            journaled.len(),
            reported.len()
        ));
    }
    for (k, (j, r)) in journaled.iter().zip(&reported).enumerate() {
        if j != r {
            return Err(format!(
                "attempt {} ({}): the journal says {:?}, the primitives reported {:?}: a \
                 failure was not acted on",
                k + 1,
                r.0,
                j.1,
                r.1
            ));
        }
    }
    let last_run = calls.iter().rposition(|c| matches!(c, Call::Run { .. }));
    match &report.outcome {
        RunOutcome::Completed => held_at_the_end(calls, last_run).map(|()| code(&report.outcome)),
        RunOutcome::Failed {
            class,
            throw,
            step,
            reason,
            ..
        } => {
            // The class is the failing step's phase's, or T for the thread's failures.
            let expected = match reason {
                Some(r) if r.is_thread() => FailureClass::Thread,
                _ => plan.phase_class(*throw, *step),
            };
            if *class != expected {
                return Err(format!(
                    "failed as class {class}, but its step's phase is class {expected}"
                ));
            }
            held_after_the_end(calls, last_run)
        }
        RunOutcome::Aborted { .. } => held_after_the_end(calls, last_run),
    }
}

/// Every run: both arms were held after the last step it ran.
fn held_at_the_end(calls: &[Call], last_run: Option<usize>) -> Result<(), String> {
    let from = last_run.map_or(0, |i| i + 1);
    if calls[from..].iter().any(|c| matches!(c, Call::Hold)) {
        Ok(())
    } else {
        Err("the run ended without holding the arms".into())
    }
}

/// A failed or aborted run: nothing ran after the failure that ended it, and both arms were
/// held after it.
fn held_after_the_end(calls: &[Call], last_run: Option<usize>) -> Result<String, String> {
    held_at_the_end(calls, last_run)?;
    if let Some(Call::Run { outcome, .. }) = last_run.map(|i| &calls[i])
        && matches!(**outcome, StepOutcome::Succeeded { .. })
    {
        return Err("the last step run succeeded, yet the run did not complete".into());
    }
    Ok(String::new())
}

/// The baseline's calls for a column: the step attempt whose events the column's faults are
/// scheduled among, and the faults that make the baseline reach it.
/// Which step attempt of a baseline run (its index among the attempts) a column is about.
type Pick = Box<dyn Fn(&Report, &[Call]) -> Option<usize>>;

fn window(phase: &str) -> (FaultConfig, Pick) {
    if phase == "intervention" {
        // Missed grasps at the first extraction's first six grasps spend its five retries:
        // the surgeon is asked, recovers, and the extraction runs again; the column is that
        // re-run. Its grasps are counted on a fault-free run.
        let (_, calls) = run(FaultConfig::default(), false).expect("a fault-free run");
        let grasps = calls
            .iter()
            .find_map(|c| match c {
                Call::Run {
                    primitive: "extract",
                    before,
                    ..
                } => Some(before[1]),
                _ => None,
            })
            .expect("an extraction");
        let faults = FaultConfig {
            schedule: (grasps + 1..=grasps + 6)
                .map(|nth| ScheduledFault {
                    kind: FaultKind::MissedGrasp,
                    nth,
                })
                .collect(),
            ..FaultConfig::default()
        };
        let pick = |report: &Report, _: &[Call]| {
            let mut attempts = 0;
            let mut after_intervention = false;
            for r in report.journal.records() {
                match &r.entry {
                    Entry::InterventionEnded { .. } => after_intervention = true,
                    Entry::StepEnd { .. } if after_intervention => return Some(attempts),
                    Entry::StepEnd { .. } => attempts += 1,
                    _ => {}
                }
            }
            None
        };
        (faults, Box::new(pick))
    } else {
        let name = phase.to_string();
        let pick = move |_: &Report, calls: &[Call]| {
            calls
                .iter()
                .filter(|c| matches!(c, Call::Run { .. }))
                .position(|c| matches!(c, Call::Run { primitive, .. } if *primitive == name))
        };
        (FaultConfig::default(), Box::new(pick))
    }
}

fn kind_name(k: FaultKind) -> &'static str {
    match k {
        FaultKind::PerceptionDropout => "perception dropout",
        FaultKind::MissedGrasp => "missed grasp",
        FaultKind::NeedleSlip => "needle slip",
        FaultKind::StaleMeasurement => "stale measurement",
        FaultKind::ArmFault => "arm fault",
    }
}

fn with(mut base: FaultConfig, kind: FaultKind, nth: u32) -> FaultConfig {
    base.schedule.push(ScheduledFault { kind, nth });
    base
}

/// The matrix as markdown, or every cell that broke a rule.
fn matrix() -> Result<String, Vec<String>> {
    let plan = plan();
    let mut broken = Vec::new();
    let mut rows: Vec<Vec<String>> = FaultKind::ALL.iter().map(|_| Vec::new()).collect();
    for phase in PHASES {
        let (base, pick) = window(phase);
        let (report, calls) = match run(base.clone(), false) {
            Ok(r) => r,
            Err(e) => {
                broken.push(format!("{phase} baseline: {e}"));
                continue;
            }
        };
        let runs: Vec<&Call> = calls
            .iter()
            .filter(|c| matches!(c, Call::Run { .. }))
            .collect();
        let Some(Call::Run { before, after, .. }) = pick(&report, &calls).map(|i| runs[i]) else {
            broken.push(format!("{phase}: the baseline never reached it"));
            continue;
        };
        for (k, kind) in FaultKind::ALL.into_iter().enumerate() {
            let (first, last) = (before[k] + 1, after[k]);
            if last < first {
                rows[k].push("–".into());
                continue;
            }
            let mut cell = Vec::new();
            for (at, nth) in [
                ("start", first),
                ("middle", (first + last) / 2),
                ("end", last),
            ] {
                let name = format!("{} at the {at} of {phase} (event {nth})", kind_name(kind));
                match run(with(base.clone(), kind, nth), false)
                    .and_then(|(r, c)| check(&plan, &r, &c).map(|_| code(&r.outcome)))
                {
                    Ok(c) => cell.push(c),
                    Err(e) => {
                        broken.push(format!("{name}: {e}"));
                        cell.push("✗".into());
                    }
                }
            }
            rows[k].push(cell.join(" "));
        }
    }
    // The constant calibration faults: present from the start, in every phase.
    let constant = [
        (
            "joint offsets (the SRC's largest, both arms)",
            FaultConfig {
                joint_offsets: [MAX_JOINT_OFFSET, MAX_JOINT_OFFSET],
                ..FaultConfig::default()
            },
        ),
        (
            "hand-eye error (4 mm along y)",
            FaultConfig {
                hand_eye_translation_m: [0.0, 0.004, 0.0],
                ..FaultConfig::default()
            },
        ),
    ];
    let mut constant_rows = Vec::new();
    for (name, faults) in constant {
        match run(faults, false).and_then(|(r, c)| check(&plan, &r, &c).map(|_| r)) {
            Ok(r) => constant_rows.push(format!("| {name} | {} |", describe(&r.outcome))),
            Err(e) => broken.push(format!("{name}: {e}")),
        }
    }
    if !broken.is_empty() {
        return Err(broken);
    }
    let mut md = String::new();
    md.push_str(&format!("{BEGIN}\n"));
    md.push_str(&format!(
        "`{PLAN}`, seed {SEED}, exact perception, a thread that never catches; each cell: \
         the fault at the start, middle and end of the phase in throw 1 (`C` completed; `I`, \
         `E`, `H`, `T` failed with that class; `A` aborted; `–` no such event in that \
         phase). Every cell passed every check.\n\n"
    ));
    md.push_str(&format!("| fault | {} |\n", PHASES.join(" | ")));
    md.push_str(&format!("|---|{}\n", "---|".repeat(PHASES.len())));
    for (k, kind) in FaultKind::ALL.into_iter().enumerate() {
        md.push_str(&format!(
            "| {} | {} |\n",
            kind_name(kind),
            rows[k].join(" | ")
        ));
    }
    md.push_str("\n| constant fault | outcome |\n|---|---|\n");
    for r in constant_rows {
        md.push_str(&format!("{r}\n"));
    }
    md.push_str(END);
    Ok(md)
}

fn describe(outcome: &RunOutcome) -> String {
    match outcome {
        RunOutcome::Completed => "completed".into(),
        RunOutcome::Failed {
            class,
            throw,
            primitive,
            reason,
            ..
        } => format!(
            "failed, class {}, throw {} at {primitive}{}",
            class.code(),
            throw + 1,
            reason
                .as_ref()
                .map(|r| format!(" ({})", r.label()))
                .unwrap_or_default()
        ),
        RunOutcome::Aborted { by, .. } => format!("aborted ({by:?})"),
    }
}

#[test]
fn every_fault_in_every_phase_ends_safe_and_the_docs_show_the_matrix() {
    let md = match matrix() {
        Ok(md) => md,
        Err(broken) => panic!(
            "{} cells broke a rule:\n{}",
            broken.len(),
            broken.join("\n")
        ),
    };
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/reliability.md");
    let doc = std::fs::read_to_string(&path).expect("docs/reliability.md");
    let (Some(a), Some(b)) = (doc.find(BEGIN), doc.find(END)) else {
        panic!("docs/reliability.md lacks the {BEGIN} / {END} lines");
    };
    let current = &doc[a..b + END.len()];
    if current != md {
        if std::env::var_os("STITCH_UPDATE_DOCS").is_some() {
            std::fs::write(&path, doc.replacen(current, &md, 1)).expect("write");
        } else {
            panic!(
                "docs/reliability.md's fault matrix is stale; rerun with STITCH_UPDATE_DOCS=1:\n{md}"
            );
        }
    }
}

#[test]
fn a_robot_layer_that_ignores_an_arm_fault_breaks_the_matrix() {
    // An arm fault at the first motion command of the extraction, reported to the engine
    // as a success: the run goes on as if nothing happened, and the check must say so.
    let plan = plan();
    let (_, calls) = run(FaultConfig::default(), false).expect("baseline");
    let extract = calls
        .iter()
        .find_map(|c| match c {
            Call::Run {
                primitive: "extract",
                before,
                ..
            } => Some(before[4] + 1),
            _ => None,
        })
        .expect("an extraction");
    let faults = with(FaultConfig::default(), FaultKind::ArmFault, extract);
    let (report, calls) = run(faults.clone(), false).expect("ends");
    check(&plan, &report, &calls).expect("acted on: the matrix's rules hold");
    let (report, calls) = run(faults, true).expect("ends");
    let e = check(&plan, &report, &calls).expect_err("ignored: a rule must break");
    assert!(e.contains("a failure was not acted on"), "{e}");
}
