//! Scenarios: hand-written outcome schedules with the exact path the engine must take.

use stitch_engine::{
    AbortCause, Entry, FailureClass, InterventionResult, RunOutcome, SupervisorCommand,
    TimedCommand,
};
use stitch_primitives::{FailureKind, Scripted};
use stitch_tests::{Budgets, plan_from, run_scripted};

const STITCH: usize = 2;
const SENSING_ONLY: usize = 0;

fn budgets(extract: u8, handover: u8, interventions: u8) -> Budgets {
    Budgets {
        extract,
        handover,
        perception: 2,
        interventions,
    }
}

fn cmd(at: usize, command: SupervisorCommand) -> TimedCommand {
    TimedCommand::before(at, command)
}

#[test]
fn all_successes_complete_every_throw() {
    let run = run_scripted(
        plan_from(&[STITCH; 6], budgets(5, 5, 0)),
        vec![],
        vec![],
        vec![],
    );
    assert_eq!(run.report.outcome, RunOutcome::Completed);
    assert_eq!(run.primitives.calls.len(), 36);
    assert!(run.report.throws.iter().all(|t| t.completed));
    assert_eq!(run.primitives.holds, vec![36], "held once, at the end");
}

#[test]
fn a_plan_asking_for_nine_extraction_retries_gets_five() {
    // Built in Rust, never validated: the machine's guard alone bounds it.
    let plan = plan_from(&[SENSING_ONLY], budgets(9, 5, 0));
    let outcomes = [vec![Scripted::Ok], vec![Scripted::NoProgress; 20]].concat();
    let run = run_scripted(plan, outcomes, vec![], vec![]);
    let extracts = run
        .primitives
        .calls
        .iter()
        .filter(|c| c.primitive == "extract")
        .count();
    assert_eq!(extracts, 6, "one attempt and five retries");
    match run.report.outcome {
        RunOutcome::Failed {
            class,
            throw: 0,
            step: 1,
            reason,
            ..
        } => {
            assert_eq!(class, FailureClass::Extraction);
            assert_eq!(reason, Some(FailureKind::NoProgress));
        }
        other => panic!("{other:?}"),
    }
    let retries: Vec<_> = run
        .report
        .journal
        .records()
        .iter()
        .filter_map(|r| match r.entry {
            Entry::Retry { retry, cap, .. } => Some((retry, cap)),
            _ => None,
        })
        .collect();
    assert_eq!(retries, vec![(1, 5), (2, 5), (3, 5), (4, 5), (5, 5)]);
}

#[test]
fn a_handover_whose_normal_did_not_change_is_reattempted_then_succeeds() {
    let plan = plan_from(&[SENSING_ONLY], budgets(5, 5, 0));
    let outcomes = vec![
        Scripted::Ok,
        Scripted::Ok,
        Scripted::NoProgress,
        Scripted::NoProgress,
    ];
    let run = run_scripted(plan, outcomes, vec![], vec![]);
    assert_eq!(run.report.outcome, RunOutcome::Completed);
    assert_eq!(run.report.throws[0].retries, 2);
    let attempts: Vec<u32> = run
        .primitives
        .calls
        .iter()
        .filter(|c| c.primitive == "handover")
        .map(|c| c.attempt)
        .collect();
    assert_eq!(attempts, vec![0, 1, 2]);
}

#[test]
fn a_missed_insertion_is_not_retried_and_fails_as_insertion() {
    let run = run_scripted(
        plan_from(&[STITCH], budgets(5, 5, 0)),
        vec![Scripted::Fail],
        vec![],
        vec![],
    );
    assert_eq!(run.primitives.calls.len(), 1);
    assert!(matches!(
        run.report.outcome,
        RunOutcome::Failed {
            class: FailureClass::Insertion,
            ..
        }
    ));
    assert_eq!(
        run.primitives.holds,
        vec![1],
        "the arms hold once the run fails"
    );
}

#[test]
fn a_thread_caught_during_extraction_is_class_t() {
    let outcomes = vec![Scripted::Ok, Scripted::Ok, Scripted::Thread];
    let run = run_scripted(
        plan_from(&[STITCH], budgets(5, 5, 0)),
        outcomes,
        vec![],
        vec![],
    );
    match run.report.outcome {
        RunOutcome::Failed {
            class,
            primitive,
            reason,
            ..
        } => {
            assert_eq!(class, FailureClass::Thread);
            assert_eq!(primitive, "extract");
            assert_eq!(reason, Some(FailureKind::ThreadCaught));
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn two_interventions_then_the_third_failure_ends_the_run() {
    let plan = plan_from(&[STITCH; 6], budgets(5, 5, 2));
    let outcomes = vec![
        Scripted::Fail, // insert 1 → intervention 1 → re-run
        Scripted::Ok,
        Scripted::Ok,
        Scripted::Ok,
        Scripted::Ok,
        Scripted::Dropped, // handover 1 → intervention 2 → re-run
        Scripted::Ok,
        Scripted::Ok,
        Scripted::Fail, // insert 2 → budget spent → failed
    ];
    let run = run_scripted(plan, outcomes, vec![], vec![]);
    assert_eq!(run.supervisor.requests.len(), 2);
    assert_eq!(run.supervisor.requests[1].class, FailureClass::Handover);
    assert!(matches!(
        run.report.outcome,
        RunOutcome::Failed {
            class: FailureClass::Insertion,
            throw: 1,
            step: 0,
            ..
        }
    ));
    assert_eq!(run.report.interventions, 2);
    assert!(run.report.throws[0].completed);
}

#[test]
fn a_failed_intervention_ends_the_run_with_the_steps_class() {
    let plan = plan_from(&[STITCH], budgets(5, 5, 2));
    let run = run_scripted(
        plan,
        vec![Scripted::Ok, Scripted::Thread],
        vec![],
        vec![InterventionResult::Failed],
    );
    assert_eq!(run.supervisor.requests.len(), 1);
    assert!(matches!(
        run.report.outcome,
        RunOutcome::Failed {
            class: FailureClass::Thread,
            step: 1,
            ..
        }
    ));
}

#[test]
fn pause_holds_the_arms_and_resume_runs_the_next_step() {
    let plan = plan_from(&[STITCH], budgets(5, 5, 0));
    let cmds = vec![
        cmd(2, SupervisorCommand::Pause),
        cmd(2, SupervisorCommand::Resume),
    ];
    let run = run_scripted(plan, vec![], cmds, vec![]);
    assert_eq!(run.report.outcome, RunOutcome::Completed);
    assert_eq!(
        run.primitives.calls.len(),
        6,
        "no step skipped, none repeated"
    );
    assert_eq!(
        run.primitives.holds,
        vec![2, 6],
        "held at the pause, after two steps, and at the end"
    );
}

#[test]
fn take_over_and_hand_back_resume_where_the_surgeon_took_over() {
    let plan = plan_from(&[STITCH], budgets(5, 5, 0));
    let cmds = vec![
        cmd(3, SupervisorCommand::TakeOver),
        cmd(3, SupervisorCommand::Resume), // ignored while taken over
        cmd(3, SupervisorCommand::HandBack),
    ];
    let run = run_scripted(plan, vec![], cmds, vec![]);
    assert_eq!(run.report.outcome, RunOutcome::Completed);
    let ignored = run.report.journal.records().iter().any(|r| {
        matches!(
            r.entry,
            Entry::Supervisor {
                command: SupervisorCommand::Resume,
                acted: false,
                ..
            }
        )
    });
    assert!(ignored);
    assert_eq!(run.primitives.calls[3].primitive, "cinch");
}

#[test]
fn e_stop_ends_the_run_with_the_arms_held_and_nothing_after() {
    let plan = plan_from(&[STITCH; 2], budgets(5, 5, 2));
    let run = run_scripted(plan, vec![], vec![cmd(4, SupervisorCommand::EStop)], vec![]);
    assert_eq!(
        run.report.outcome,
        RunOutcome::Aborted {
            by: AbortCause::EStop,
            throw: 0,
            step: 4
        }
    );
    assert_eq!(run.primitives.calls.len(), 4);
    assert_eq!(run.primitives.holds, vec![4]);
}

#[test]
fn a_paused_run_whose_supervisor_is_gone_aborts_safely() {
    let plan = plan_from(&[STITCH], budgets(5, 5, 0));
    let run = run_scripted(plan, vec![], vec![cmd(1, SupervisorCommand::Pause)], vec![]);
    assert_eq!(
        run.report.outcome,
        RunOutcome::Aborted {
            by: AbortCause::SupervisorSilent,
            throw: 0,
            step: 1
        }
    );
    assert_eq!(run.primitives.calls.len(), 1);
    assert_eq!(run.primitives.holds.last(), Some(&1));
}

#[test]
fn the_journal_records_transitions_with_simulated_time() {
    let run = run_scripted(
        plan_from(&[SENSING_ONLY], budgets(5, 5, 0)),
        vec![],
        vec![],
        vec![],
    );
    let text = run.report.journal.to_jsonl();
    let first: Vec<&str> = text.lines().take(3).collect();
    assert!(
        first[0].starts_with(r#"{"seq":0,"t_s":0.0,"event":"plan","name":"generated""#),
        "{}",
        first[0]
    );
    assert_eq!(
        first[1],
        r#"{"seq":1,"t_s":0.0,"event":"transition","from":"ready","to":"inserting(t1 s1 r0)"}"#
    );
    assert!(
        text.lines()
            .last()
            .is_some_and(|l| l.contains(r#""event":"finished","outcome":{"result":"completed"}"#))
    );
    // insert 25 s + extract 30 s + handover 25 s of simulated time.
    assert!((run.report.duration_s - 80.0).abs() < 1e-9);
}

#[test]
fn an_unvalidated_plan_with_an_empty_throw_still_runs_the_throws_after_it() {
    let mut plan = plan_from(&[SENSING_ONLY; 3], budgets(5, 5, 0));
    plan.throws[1].program.clear();
    plan.throws[1].body.clear();
    let run = run_scripted(plan, vec![], vec![], vec![]);
    assert_eq!(run.report.outcome, RunOutcome::Completed);
    let throws: Vec<usize> = run.primitives.calls.iter().map(|c| c.throw).collect();
    assert_eq!(throws, vec![0, 0, 0, 2, 2, 2]);
}
