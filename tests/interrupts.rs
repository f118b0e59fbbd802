//! Supervisor commands that land in the middle of a step, on the mock dVRK: abort, e-stop,
//! pause/resume and take-over/hand-back in each of the six primitives, while an arm moves.
//! The arms hold at the command's instant, nothing moves after an abort or while paused or
//! taken over, the journal says what became of the interrupted step, and the same seed and
//! command schedule give the same journal.

use std::sync::{Arc, Mutex, PoisonError};
use stitch_engine::{
    AbortCause, Entry, PlanLoader, Report, RunOutcome, Runner, ScriptLimits, ScriptedSupervisor,
    SupervisorCommand, TimedCommand, load_plan,
};
use stitch_primitives::{Rig, StepOutcome, mock_primitives};
use stitch_robot::{Arm, Clock, Jaw, MoveHandle, Pose, RobotError, SimClock, SpeedLimits, Wound};
use stitch_sim::{SceneConfig, SensingConfig, ThreadConfig};

/// What an arm or jaw was told, when (simulated s), and for a move how far it had to go (m).
#[derive(Clone, Debug, PartialEq)]
struct Told {
    t_s: f64,
    what: &'static str,
    who: String,
    distance_m: f64,
}

type Log = Arc<Mutex<Vec<Told>>>;

fn note(log: &Log, clock: &SimClock, what: &'static str, who: &str, distance_m: f64) {
    log.lock()
        .unwrap_or_else(PoisonError::into_inner)
        .push(Told {
            t_s: clock.now().as_secs_f64(),
            what,
            who: who.to_string(),
            distance_m,
        });
}

struct Watched {
    arm: Arc<dyn Arm>,
    log: Log,
    clock: SimClock,
}

impl Arm for Watched {
    fn name(&self) -> &str {
        self.arm.name()
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        self.arm.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        self.arm.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        let from = self.arm.setpoint_cp()?;
        let d = (goal.translation.vector - from.translation.vector).norm();
        note(&self.log, &self.clock, "move", self.arm.name(), d);
        self.arm.move_cp(goal)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        note(&self.log, &self.clock, "move", self.arm.name(), 0.0);
        self.arm.servo_cp(goal)
    }
    fn hold(&self) -> Result<(), RobotError> {
        note(&self.log, &self.clock, "hold", self.arm.name(), 0.0);
        self.arm.hold()
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        self.arm.set_max_speed(limits)
    }
}

struct WatchedJaw {
    jaw: Arc<dyn Jaw>,
    log: Log,
    clock: SimClock,
}

impl Jaw for WatchedJaw {
    fn name(&self) -> &str {
        self.jaw.name()
    }
    fn measured_jp(&self) -> Result<f64, RobotError> {
        self.jaw.measured_jp()
    }
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        note(&self.log, &self.clock, "jaw", self.jaw.name(), 0.0);
        self.jaw.move_jp(angle_rad)
    }
}

struct Ran {
    report: Report,
    told: Vec<Told>,
    journal: String,
}

/// STITCH (all six primitives in every throw) on the mock with perfect perception and a tame
/// thread, the supervisor following `commands`.
fn run(commands: Vec<TimedCommand>, seed: u64) -> Ran {
    let scene = SceneConfig {
        thread: ThreadConfig {
            catch_radius_m: 0.0,
            occlusion_radius_m: 0.0,
            ..ThreadConfig::default()
        },
        ..SceneConfig::default()
    };
    let wound = Wound::linear(&scene.wound).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/stitch.rhai");
    let plan = load_plan(&loader, &path).expect("plan").plan;
    let clock = SimClock::new();
    let log: Log = Arc::default();
    let (primitives, _world) =
        mock_primitives(&scene, SensingConfig::perfect(), seed, clock.clone()).expect("mock");
    let arm = |a: Arc<dyn Arm>| -> Arc<dyn Arm> {
        Arc::new(Watched {
            arm: a,
            log: Arc::clone(&log),
            clock: clock.clone(),
        })
    };
    let jaw = |j: Arc<dyn Jaw>| -> Arc<dyn Jaw> {
        Arc::new(WatchedJaw {
            jaw: j,
            log: Arc::clone(&log),
            clock: clock.clone(),
        })
    };
    let mut primitives = primitives.map_rig(|rig| Rig {
        right: arm(rig.right),
        left: arm(rig.left),
        right_jaw: jaw(rig.right_jaw),
        left_jaw: jaw(rig.left_jaw),
        ..rig
    });
    let mut supervisor = ScriptedSupervisor::new(commands, []);
    let report = Runner::new(
        Arc::new(plan),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        Some(seed),
    )
    .run();
    let mut journal = Vec::new();
    report.journal.write_jsonl(&mut journal).expect("jsonl");
    let told = log.lock().unwrap_or_else(PoisonError::into_inner).clone();
    Ran {
        report,
        told,
        journal: String::from_utf8(journal).expect("utf-8"),
    }
}

/// For each primitive, a moment in the middle of its first attempt while an arm moves: 50 ms
/// into the longest move it commands (more than 5 mm at at most 2 cm/s: at least 0.25 s
/// long) at least 0.1 s before the attempt ends. Also the attempt's step index.
fn moments(base: &Ran) -> Vec<(&'static str, usize, f64)> {
    moments_by(base, |x, y| x.distance_m.total_cmp(&y.distance_m))
}

/// As [`moments`], 50 ms into the first move of more than 5 mm each primitive commands
/// (for most, before their commit point; [`moments`] finds most past it).
fn first_moments(base: &Ran) -> Vec<(&'static str, usize, f64)> {
    moments_by(base, |x, y| y.t_s.total_cmp(&x.t_s))
}

/// As [`moments`], 50 ms into the last move of more than 5 mm each primitive commands (for
/// those with a commit point, past it).
fn last_moments(base: &Ran) -> Vec<(&'static str, usize, f64)> {
    moments_by(base, |x, y| x.t_s.total_cmp(&y.t_s))
}

fn moments_by(
    base: &Ran,
    pick: impl Fn(&&Told, &&Told) -> std::cmp::Ordering,
) -> Vec<(&'static str, usize, f64)> {
    let throw = &base.report.throws[0];
    ["insert", "sweep", "extract", "cinch", "handover", "correct"]
        .into_iter()
        .map(|name| {
            let a = throw
                .attempts
                .iter()
                .find(|a| a.primitive == name)
                .unwrap_or_else(|| panic!("{name} ran"));
            let (t0, t1) = (a.start_s, a.start_s + a.duration_s);
            let longest = base
                .told
                .iter()
                .filter(|e| {
                    e.what == "move"
                        && e.distance_m > 0.005
                        && us(e.t_s) >= us(t0)
                        && us(e.t_s) < us(t1) - 100_000
                })
                .max_by(&pick)
                .unwrap_or_else(|| panic!("{name} moves an arm"));
            assert!(
                longest.distance_m > 0.005,
                "{name}: its longest move is {} m",
                longest.distance_m
            );
            (name, a.step, longest.t_s + 0.05)
        })
        .collect()
}

fn commands(list: &[(f64, SupervisorCommand)]) -> Vec<TimedCommand> {
    list.iter()
        .map(|(t, c)| TimedCommand::at_time(*t, *c))
        .collect()
}

/// Both arms were told to hold at `t` (the command's instant on the simulated clock).
fn held_at(r: &Ran, t: f64, context: &str) {
    for arm in ["PSM1", "PSM2"] {
        assert!(
            r.told
                .iter()
                .any(|e| e.what == "hold" && e.who == arm && us(e.t_s) == us(t)),
            "{context}: {arm} was not told to hold at {t} s: {:?}",
            r.told
                .iter()
                .filter(|e| e.what == "hold")
                .collect::<Vec<_>>()
        );
    }
}

/// Nothing was told to move in (`from`, `to`) s.
fn still_between(r: &Ran, from: f64, to: f64, context: &str) {
    let moved: Vec<_> = r
        .told
        .iter()
        .filter(|e| e.what != "hold" && us(e.t_s) > us(from) && us(e.t_s) < us(to))
        .collect();
    assert!(
        moved.is_empty(),
        "{context}: motion while it should hold: {moved:?}"
    );
}

/// The journal's supervisor records, with their times in µs (the journal keeps ns).
fn commands_journaled(r: &Ran) -> Vec<(i64, SupervisorCommand, Option<usize>)> {
    r.report
        .journal
        .records()
        .iter()
        .filter_map(|rec| match &rec.entry {
            Entry::Supervisor {
                command, during, ..
            } => Some((us(rec.t_s), *command, during.map(|d| d.step))),
            _ => None,
        })
        .collect()
}

fn us(t_s: f64) -> i64 {
    (t_s * 1e6).round() as i64
}

/// The outcome of the first attempt at `step` of throw 1.
fn first_outcome(r: &Ran, step: usize) -> StepOutcome {
    r.report.throws[0]
        .attempts
        .iter()
        .find(|a| a.step == step)
        .map(|a| a.outcome.clone())
        .expect("attempted")
}

#[test]
fn abort_and_e_stop_mid_motion_hold_the_arms_at_once_and_nothing_moves_after() {
    let base = run(Vec::new(), 3);
    assert_eq!(base.report.outcome, RunOutcome::Completed);
    let all = [moments(&base), first_moments(&base), last_moments(&base)];
    for (name, step, t) in all.into_iter().flatten() {
        for (command, cause) in [
            (SupervisorCommand::Abort, AbortCause::Abort),
            (SupervisorCommand::EStop, AbortCause::EStop),
        ] {
            let context = format!("{command} in {name} at {t:.2} s");
            let r = run(commands(&[(t, command)]), 3);
            assert!(
                matches!(r.report.outcome, RunOutcome::Aborted { by, throw: 0, step: s } if by == cause && s == step),
                "{context}: {:?}",
                r.report.outcome
            );
            held_at(&r, t, &context);
            still_between(&r, t, f64::INFINITY, &context);
            assert_eq!(
                commands_journaled(&r),
                vec![(us(t), command, Some(step))],
                "{context}"
            );
            assert!(
                matches!(first_outcome(&r, step), StepOutcome::Interrupted { .. }),
                "{context}: {:?}",
                first_outcome(&r, step)
            );
            assert_eq!(
                us(r.report.duration_s),
                us(t),
                "{context}: the run ends at the command"
            );
        }
    }
}

#[test]
fn a_pause_mid_motion_holds_until_resumed_and_the_step_goes_on_where_it_stopped() {
    let base = run(Vec::new(), 3);
    let all = [moments(&base), first_moments(&base), last_moments(&base)];
    for (name, step, t) in all.into_iter().flatten() {
        let context = format!("pause in {name} at {t:.2} s, resume 3 s later");
        let r = run(
            commands(&[
                (t, SupervisorCommand::Pause),
                (t + 3.0, SupervisorCommand::Resume),
            ]),
            3,
        );
        held_at(&r, t, &context);
        still_between(&r, t, t + 3.0, &context);
        assert_eq!(
            commands_journaled(&r),
            vec![
                (us(t), SupervisorCommand::Pause, Some(step)),
                (us(t + 3.0), SupervisorCommand::Resume, None)
            ],
            "{context}"
        );
        // The attempt was not ended: it went on and finished as without the pause.
        assert!(
            matches!(first_outcome(&r, step), StepOutcome::Succeeded { .. }),
            "{context}: {:?}",
            first_outcome(&r, step)
        );
        let attempts = |x: &Ran| {
            x.report.throws[0]
                .attempts
                .iter()
                .filter(|a| a.step == step)
                .count()
        };
        assert_eq!(attempts(&r), attempts(&base), "{context}: no attempt added");
        assert_eq!(r.report.outcome, RunOutcome::Completed, "{context}");
        assert_eq!(r.report.interventions, 0, "{context}");
        let retries = |x: &Ran| x.report.throws.iter().map(|t| t.retries).sum::<u32>();
        assert_eq!(retries(&r), retries(&base), "{context}: no retry spent");
    }
}

#[test]
fn a_take_over_mid_motion_ends_the_attempt_and_the_hand_back_reruns_it_or_goes_past_it() {
    let base = run(Vec::new(), 3);
    let mut committed_seen = std::collections::BTreeSet::new();
    let all = [moments(&base), first_moments(&base), last_moments(&base)];
    for (name, step, t) in all.into_iter().flatten() {
        let context = format!("take-over in {name} at {t:.2} s, hand-back 5 s later");
        let r = run(
            commands(&[
                (t, SupervisorCommand::TakeOver),
                (t + 5.0, SupervisorCommand::HandBack),
            ]),
            3,
        );
        held_at(&r, t, &context);
        still_between(&r, t, t + 5.0, &context);
        let StepOutcome::Interrupted { committed, .. } = first_outcome(&r, step) else {
            panic!("{context}: {:?}", first_outcome(&r, step));
        };
        let during = r
            .report
            .journal
            .records()
            .iter()
            .find_map(|rec| match &rec.entry {
                Entry::Supervisor {
                    command: SupervisorCommand::TakeOver,
                    during: Some(d),
                    ..
                } => Some(*d),
                _ => None,
            });
        assert_eq!(
            during.map(|d| (d.step, d.committed)),
            Some((step, committed)),
            "{context}"
        );
        // What runs after the hand-back: the step again from its start, or, past its commit
        // point, the step after it.
        let next = r
            .report
            .journal
            .records()
            .iter()
            .find_map(|rec| match &rec.entry {
                Entry::StepStart {
                    throw,
                    step,
                    attempt,
                    ..
                } if us(rec.t_s) >= us(t + 5.0) => Some((*throw, *step, *attempt)),
                _ => None,
            });
        let expect = if committed {
            (0, step + 1, 0)
        } else {
            (0, step, 1)
        };
        assert_eq!(next, Some(expect), "{context} (committed: {committed})");
        committed_seen.insert((name, committed));
        assert_eq!(
            r.report.interventions, 0,
            "{context}: no intervention spent"
        );
        let retried = r.report.journal.records().iter().any(|rec| {
            matches!(&rec.entry, Entry::Retry { step: s, .. } if *s == step)
                && us(rec.t_s) < us(t + 5.0)
        });
        assert!(!retried, "{context}: the interruption spent a retry");
    }
    // Both branches are taken: the steps with a commit point were taken over before it and
    // past it, the others only before.
    for name in ["insert", "extract", "handover"] {
        assert!(
            committed_seen.contains(&(name, false)),
            "{name} before its commit point: {committed_seen:?}"
        );
        assert!(
            committed_seen.contains(&(name, true)),
            "{name} past its commit point: {committed_seen:?}"
        );
    }
    for name in ["sweep", "correct"] {
        assert!(
            !committed_seen.contains(&(name, true)),
            "{name} has no commit point"
        );
    }
}

#[test]
fn the_same_seed_and_command_schedule_give_the_same_journal() {
    let base = run(Vec::new(), 4);
    let m = moments(&base);
    let (_, _, t_insert) = m[0];
    let (_, _, t_cinch) = m[3];
    let schedule = commands(&[
        (t_insert, SupervisorCommand::Pause),
        (t_insert + 2.0, SupervisorCommand::Resume),
        (t_cinch, SupervisorCommand::TakeOver),
        (t_cinch + 4.0, SupervisorCommand::HandBack),
    ]);
    let a = run(schedule.clone(), 4);
    let b = run(schedule, 4);
    assert_eq!(a.journal, b.journal);
    assert_ne!(a.journal, base.journal, "the commands changed the run");
    assert!(a.journal.contains("\"during\""));
}
