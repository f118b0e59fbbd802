//! Properties of the engine for arbitrary plans (budgets up to beyond the caps) and arbitrary
//! outcome schedules. Each property runs `STITCH_PROPTEST_CASES` cases (default 4,000; seven
//! properties make 28,000 cases per `cargo test`).
//!
//! Counts are taken from what the scripted primitives and supervisor saw, not from the
//! engine's own bookkeeping, so a bug in the engine's counters cannot hide itself.

use proptest::prelude::*;
use std::collections::BTreeMap;
use stitch_engine::{
    AbortCause, Entry, FailureClass, InterventionResult, Plan, Rebuilt, RunOutcome,
    SupervisorCommand,
};
use stitch_primitives::{Scripted, StepKind};
use stitch_tests::{Run, cases, commands, interventions, plans, run_scripted, token};

const DEFAULT_CASES: u32 = 4_000;

fn config() -> ProptestConfig {
    ProptestConfig {
        cases: cases(DEFAULT_CASES),
        ..ProptestConfig::default()
    }
}

/// Retries of each step of kind `pick`, as the primitives saw them: attempts at the step, less
/// the first, less each re-run that followed a recovered intervention on it (an intervention
/// whose re-run never came, because the run was aborted first, re-ran nothing).
fn retries_seen(run: &Run, pick: fn(&StepKind) -> bool) -> Vec<((usize, usize), usize)> {
    let calls = &run.primitives.calls;
    let mut attempts: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for c in calls {
        if pick(&run.plan.throws[c.throw].steps[c.step].kind) {
            *attempts.entry((c.throw, c.step)).or_default() += 1;
        }
    }
    let mut reruns: BTreeMap<(usize, usize), usize> = BTreeMap::new();
    for (n, r) in run.supervisor.requests.iter().enumerate() {
        let after = run.intervention_after_calls[n];
        let rerun = calls
            .get(after)
            .is_some_and(|c| (c.throw, c.step) == (r.throw, r.step));
        if run.intervention_result(n) == InterventionResult::Recovered && rerun {
            *reruns.entry((r.throw, r.step)).or_default() += 1;
        }
    }
    attempts
        .into_iter()
        .map(|(k, n)| (k, n - 1 - reruns.get(&k).copied().unwrap_or(0)))
        .collect()
}

/// Where the needle is before step `step` of throw `throw`, worked out here from the step
/// names, independently of the engine's own rule.
fn expected_class(plan: &Plan, throw: usize, step: usize, token: Scripted) -> FailureClass {
    if token == Scripted::Thread {
        return FailureClass::Thread;
    }
    let steps = &plan.throws[throw].steps;
    match steps[step].kind {
        StepKind::Insert(_) | StepKind::Correct(_) => FailureClass::Insertion,
        StepKind::Extract(_) => FailureClass::Extraction,
        StepKind::Handover(_) => FailureClass::Handover,
        StepKind::Sweep(_) | StepKind::Cinch(_) | StepKind::TrackThread(_) => FailureClass::Thread,
        StepKind::EstimateNeedle(_) => {
            let before: Vec<&str> = steps[..step].iter().map(|s| s.kind.name()).collect();
            let pos = |n: &str| before.iter().rposition(|b| *b == n);
            match (pos("insert"), pos("extract"), pos("handover")) {
                (_, _, Some(_)) => FailureClass::Insertion,
                (_, Some(_), None) => FailureClass::Handover,
                (Some(_), None, None) => FailureClass::Extraction,
                (None, None, None) => FailureClass::Insertion,
            }
        }
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn extraction_never_exceeds_five_retries(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(3),
        ivs in interventions(),
    ) {
        let asked = plan.throws.iter().flat_map(|t| &t.steps).find_map(|s| match s.kind {
            StepKind::Extract(p) => Some(p.retries),
            _ => None,
        }).unwrap_or(0);
        let run = run_scripted(plan, outcomes, cmds, ivs);
        for (at, retries) in retries_seen(&run, |k| matches!(k, StepKind::Extract(_))) {
            prop_assert!(retries <= 5, "{retries} extraction retries at {at:?}");
            prop_assert!(retries <= usize::from(asked), "{retries} retries but the plan asked for {asked}");
        }
    }

    #[test]
    fn handover_never_exceeds_five_reattempts(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(3),
        ivs in interventions(),
    ) {
        let asked = plan.throws.iter().flat_map(|t| &t.steps).find_map(|s| match s.kind {
            StepKind::Handover(p) => Some(p.retries),
            _ => None,
        }).unwrap_or(0);
        let run = run_scripted(plan, outcomes, cmds, ivs);
        for (at, retries) in retries_seen(&run, |k| matches!(k, StepKind::Handover(_))) {
            prop_assert!(retries <= 5, "{retries} handover re-attempts at {at:?}");
            prop_assert!(retries <= usize::from(asked), "{retries} re-attempts but the plan asked for {asked}");
        }
    }

    #[test]
    fn interventions_never_exceed_the_plans_budget_or_two(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(3),
        ivs in interventions(),
    ) {
        let budget = usize::from(plan.interventions);
        let run = run_scripted(plan, outcomes, cmds, ivs);
        let requests = run.supervisor.requests.len();
        prop_assert!(requests <= 2, "{requests} interventions");
        prop_assert!(requests <= budget, "{requests} interventions with a budget of {budget}");
        prop_assert_eq!(usize::from(run.report.interventions), requests);
    }

    #[test]
    fn every_run_ends_completed_failed_or_aborted(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(4),
        ivs in interventions(),
    ) {
        let run = run_scripted(plan, outcomes, cmds, ivs);
        let last = run.report.journal.records().last().map(|r| r.entry.clone());
        prop_assert_eq!(last, Some(Entry::Finished { outcome: run.report.outcome.clone() }));
        let steps: Vec<usize> = run.plan.throws.iter().map(|t| t.steps.len()).collect();
        match &run.report.outcome {
            RunOutcome::Completed => {
                // Every step of every throw succeeded on its last attempt.
                for (ti, n) in steps.iter().enumerate() {
                    for si in 0..*n {
                        let last = run.primitives.calls.iter().rev().find(|c| c.throw == ti && c.step == si);
                        prop_assert_eq!(last.map(|c| c.token), Some(Scripted::Ok), "throw {} step {}", ti, si);
                    }
                }
            }
            RunOutcome::Failed { throw, step, .. } => {
                let last = run.primitives.calls.last();
                prop_assert!(last.is_some_and(|c| c.throw == *throw && c.step == *step && c.token != Scripted::Ok), "{:?}", last);
            }
            RunOutcome::Aborted { by, .. } => {
                let asked = run.report.journal.records().iter().any(|r| matches!(r.entry,
                    Entry::Supervisor { command: SupervisorCommand::Abort | SupervisorCommand::EStop, acted: true }));
                prop_assert!(asked || *by == AbortCause::SupervisorSilent);
            }
        }
    }

    #[test]
    fn after_abort_or_estop_no_motion_is_commanded_and_the_arms_hold(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(4),
        ivs in interventions(),
    ) {
        let run = run_scripted(plan, outcomes, cmds, ivs);
        let records = run.report.journal.records();
        let stop = records.iter().position(|r| matches!(r.entry,
            Entry::Supervisor { command: SupervisorCommand::Abort | SupervisorCommand::EStop, acted: true }));
        if let Some(stop) = stop {
            prop_assert!(matches!(run.report.outcome, RunOutcome::Aborted { .. }), "{:?}", run.report.outcome);
            let started_before = records[..stop].iter().filter(|r| matches!(r.entry, Entry::StepStart { .. })).count();
            let started_after = records[stop..].iter().filter(|r| matches!(r.entry, Entry::StepStart { .. })).count();
            prop_assert_eq!(started_after, 0);
            // The primitives saw exactly the attempts started before the stop, and the last
            // thing they were told was to hold.
            prop_assert_eq!(run.primitives.calls.len(), started_before);
            prop_assert_eq!(run.primitives.holds.last().copied(), Some(started_before));
        }
        if matches!(run.report.outcome, RunOutcome::Aborted { .. } | RunOutcome::Failed { .. }) {
            prop_assert_eq!(run.primitives.holds.last().copied(), Some(run.primitives.calls.len()));
        }
    }

    #[test]
    fn the_failure_class_matches_the_phase_that_failed(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(2),
        ivs in interventions(),
    ) {
        let run = run_scripted(plan, outcomes, cmds, ivs);
        if let RunOutcome::Failed { class, throw, step, .. } = run.report.outcome {
            let token = run.primitives.calls.iter().rev()
                .find(|c| c.throw == throw && c.step == step)
                .map(|c| c.token)
                .expect("a failed step was attempted");
            prop_assert_eq!(class, expected_class(&run.plan, throw, step, token));
        }
    }

    #[test]
    fn a_journal_rebuilds_the_runners_own_report_and_any_prefix_of_it_rebuilds(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(3),
        ivs in interventions(),
        cut in 0.0f64..1.0,
    ) {
        let run = run_scripted(plan, outcomes, cmds, ivs);
        let records = run.report.journal.records();
        let steps: Vec<usize> = run.plan.throws.iter().map(|t| t.steps.len()).collect();
        // The whole journal: exactly what the runner kept (`stitch journal show` prints what
        // `stitch run` printed).
        let whole = Rebuilt::from_journal(records, Some(&steps)).expect("its own journal");
        prop_assert_eq!(&whole.throws, &run.report.throws);
        prop_assert_eq!(whole.interventions, run.report.interventions);
        prop_assert_eq!(whole.outcome.as_ref(), Some(&run.report.outcome));
        prop_assert!(whole.under_way.is_none());
        // A journal cut short (a crash): still rebuilt, no outcome, its attempts a prefix of
        // the whole run's, throw by throw.
        let n = ((records.len() as f64 * cut) as usize).max(1);
        if n < records.len() {
            let part = Rebuilt::from_journal(&records[..n], Some(&steps)).expect("a prefix");
            prop_assert!(part.outcome.is_none());
            for (p, w) in part.throws.iter().zip(&whole.throws) {
                prop_assert!(p.attempts.len() <= w.attempts.len());
                for (a, b) in p.attempts.iter().zip(&w.attempts) {
                    prop_assert_eq!((a.step, a.attempt, &a.outcome), (b.step, b.attempt, &b.outcome));
                }
            }
        }
    }
}
