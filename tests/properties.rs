//! Properties of the engine for arbitrary plans (budgets up to beyond the caps; plain and
//! conditional: arbitrary conditions in when, repeat and checkpoints) and arbitrary outcome
//! schedules and condition values. Each property runs `STITCH_PROPTEST_CASES` cases (default
//! 4,000; the model-checking property a tenth of that).
//!
//! Counts are taken from what the scripted primitives and supervisor saw, not from the
//! engine's own bookkeeping, so a bug in the engine's counters cannot hide itself.

use proptest::prelude::*;
use std::collections::BTreeMap;
use stitch_engine::{
    AbortCause, During, Entry, FailureClass, InterventionResult, Plan, Rebuilt, RunOutcome,
    SupervisorCommand,
};
use stitch_primitives::{Scripted, StepKind, StepOutcome};
use stitch_tests::{
    Run, cases, commands, conditional_plans, conditional_plans_with, interventions, plans,
    run_scripted, run_scripted_deciding, timed_commands, token,
};

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
        if run.plan.throws[c.throw]
            .step(c.step)
            .is_some_and(|s| pick(&s.kind))
        {
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
    let program = &plan.throws[throw].program;
    let Some(this) = program[step].step() else {
        return FailureClass::Insertion;
    };
    match this.kind {
        StepKind::Insert(_) | StepKind::Correct(_) => FailureClass::Insertion,
        StepKind::Extract(_) => FailureClass::Extraction,
        StepKind::Handover(_) => FailureClass::Handover,
        StepKind::Sweep(_) | StepKind::Cinch(_) | StepKind::TrackThread(_) => FailureClass::Thread,
        StepKind::EstimateNeedle(_) => {
            let before: Vec<&str> = program[..step]
                .iter()
                .filter_map(|o| Some(o.step()?.kind.name()))
                .collect();
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
        let asked = plan.throws.iter().flat_map(|t| t.steps()).find_map(|(_, s)| match s.kind {
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
        let asked = plan.throws.iter().flat_map(|t| t.steps()).find_map(|(_, s)| match s.kind {
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
        let steps: Vec<usize> = run.plan.throws.iter().map(|t| t.program.len()).collect();
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
                    Entry::Supervisor { command: SupervisorCommand::Abort | SupervisorCommand::EStop, acted: true, .. }));
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
            Entry::Supervisor { command: SupervisorCommand::Abort | SupervisorCommand::EStop, acted: true, .. }));
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
        let steps: Vec<usize> = run.plan.throws.iter().map(|t| t.program.len()).collect();
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

/// Checkpoint answers, `go` mostly.
fn answers() -> impl Strategy<Value = Vec<SupervisorCommand>> {
    prop::collection::vec(
        prop_oneof![
            6 => Just(SupervisorCommand::Go),
            1 => Just(SupervisorCommand::Abort),
            1 => Just(SupervisorCommand::EStop),
            1 => Just(SupervisorCommand::TakeOver),
        ],
        0..4,
    )
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn conditional_plans_keep_every_bound_end_and_journal_their_decisions(
        plan in conditional_plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in commands(3),
        ivs in interventions(),
        values in prop::collection::vec(any::<bool>(), 0..40),
        checkpoints in answers(),
    ) {
        let budget = usize::from(plan.interventions);
        let run = run_scripted_deciding(plan, outcomes, cmds, ivs, values.clone(), checkpoints);
        let records = run.report.journal.records();
        // Retries and interventions stay within the plan's asks and the caps, on every path.
        for (at, retries) in retries_seen(&run, |k| k.retries().is_some()) {
            let step = run.plan.throws[at.0].step(at.1).expect("a step");
            let asked = usize::from(step.kind.retries().unwrap_or(0));
            prop_assert!(retries <= 5 && retries <= asked, "{retries} retries at {at:?}, asked {asked}");
        }
        let requests = run.supervisor.requests.len();
        prop_assert!(requests <= 2 && requests <= budget, "{requests} interventions, budget {budget}");
        // Conditions took the scheduled values, in order (true past the schedule), and the
        // journal says so; a repeat never runs past its cap.
        let decided: Vec<bool> = records.iter().filter_map(|r| match &r.entry {
            Entry::Condition { value, role, .. } => {
                if let stitch_engine::BranchRole::Until { run } = role {
                    assert!(*run <= stitch_engine::caps::REPEAT);
                }
                Some(*value)
            }
            _ => None,
        }).collect();
        for (i, v) in decided.iter().enumerate() {
            prop_assert_eq!(*v, values.get(i).copied().unwrap_or(true), "condition {}", i);
        }
        prop_assert_eq!(&decided, &run.primitives.decided);
        // The run ends, and a completed run finished every throw.
        let last = records.last().map(|r| r.entry.clone());
        prop_assert_eq!(last, Some(Entry::Finished { outcome: run.report.outcome.clone() }));
        if run.report.outcome == RunOutcome::Completed {
            prop_assert!(run.report.throws.iter().all(|t| t.completed));
            for (ti, _) in run.plan.throws.iter().enumerate() {
                prop_assert!(run.primitives.calls.iter().any(|c| c.throw == ti), "throw {} ran no step", ti);
            }
            let mut last_call = BTreeMap::new();
            for c in &run.primitives.calls {
                last_call.insert((c.throw, c.step), c.token);
            }
            prop_assert!(last_call.values().all(|t| *t == Scripted::Ok));
        }
        // Nothing moves after an abort or e-stop, and the arms hold at the end of a stop.
        let stop = records.iter().position(|r| matches!(r.entry,
            Entry::Supervisor { command: SupervisorCommand::Abort | SupervisorCommand::EStop, acted: true, .. }));
        if let Some(stop) = stop {
            let aborted = matches!(run.report.outcome, RunOutcome::Aborted { .. });
            prop_assert!(aborted, "{:?}", run.report.outcome);
            let moved = records[stop..].iter().any(|r| matches!(r.entry, Entry::StepStart { .. } | Entry::Condition { .. }));
            prop_assert!(!moved, "a step or a condition after the stop");
        }
        if matches!(run.report.outcome, RunOutcome::Aborted { .. } | RunOutcome::Failed { .. }) {
            prop_assert_eq!(run.primitives.holds.last().copied(), Some(run.primitives.calls.len()));
        }
        // The journal rebuilds the runner's own report.
        let steps: Vec<usize> = run.plan.throws.iter().map(|t| t.program.len()).collect();
        let whole = Rebuilt::from_journal(records, Some(&steps)).expect("its own journal");
        prop_assert_eq!(&whole.throws, &run.report.throws);
        prop_assert_eq!(whole.outcome.as_ref(), Some(&run.report.outcome));
    }
}

proptest! {
    #![proptest_config(ProptestConfig { cases: cases(DEFAULT_CASES) / 10, ..config() })]

    #[test]
    fn the_model_checker_finds_every_property_holding_on_valid_conditional_plans(
        plan in conditional_plans_with(5, 2),
    ) {
        let mut plan = plan;
        plan.throws.truncate(2);
        plan.thread_length_m.get_or_insert(0.3);
        stitch_engine::validate(&plan).map_err(|e| TestCaseError::fail(e.to_string()))?;
        let found = stitch_engine::explore(std::sync::Arc::new(plan), stitch_engine::ExploreOptions::default());
        for v in &found.verdicts {
            prop_assert!(v.holds, "{} fails: {:?}", v.says, v.path);
        }
    }
}

proptest! {
    #![proptest_config(config())]

    /// Commands at arbitrary times on the run's clock, most of them in the middle of a step.
    #[test]
    fn commands_mid_step_spend_no_budget_and_the_journal_says_what_they_interrupted(
        plan in plans(),
        outcomes in prop::collection::vec(token(), 0..150),
        cmds in timed_commands(4),
        ivs in interventions(),
    ) {
        let run = run_scripted(plan.clone(), outcomes.clone(), cmds.clone(), ivs.clone());
        let records = run.report.journal.records();
        let finished = matches!(records.last().map(|r| &r.entry), Some(Entry::Finished { .. }));
        prop_assert!(finished, "the journal ends with the run's end");
        // A retry or an intervention follows a failure of that very step, never an
        // interruption: the last attempt's end (or an unobserved condition) before it says so.
        let mut last_end: Option<(usize, usize, bool)> = None;
        let mut last_mid: Option<During> = None;
        for r in records {
            match &r.entry {
                Entry::StepEnd { throw, step, attempt, outcome, .. } => {
                    let failed = matches!(outcome, StepOutcome::Failed(_));
                    if let StepOutcome::Interrupted { committed, .. } = outcome {
                        // The command that ended it landed in it (mid-step), or, after a
                        // mid-step pause, while it was paused.
                        let d = last_mid.expect("a command landed in the interrupted attempt");
                        prop_assert_eq!((d.throw, d.step, d.attempt), (*throw, *step, *attempt));
                        prop_assert!(*committed || !d.committed);
                    }
                    last_end = Some((*throw, *step, failed));
                }
                Entry::Unobserved { throw, step, .. } => last_end = Some((*throw, *step, true)),
                Entry::Retry { throw, step, .. } | Entry::InterventionRequested { throw, step, .. } => {
                    prop_assert_eq!(last_end, Some((*throw, *step, true)), "{:?} after {:?}", r.entry, last_end);
                }
                Entry::Supervisor { during: Some(d), .. } => last_mid = Some(*d),
                _ => {}
            }
        }
        prop_assert!(run.report.interventions <= 2);
        // Nothing moves after an abort or e-stop; the arms hold.
        let stop = records.iter().position(|r| matches!(r.entry,
            Entry::Supervisor { command: SupervisorCommand::Abort | SupervisorCommand::EStop, acted: true, .. }));
        if let Some(stop) = stop {
            prop_assert!(matches!(run.report.outcome, RunOutcome::Aborted { .. }), "{:?}", run.report.outcome);
            let moved = records[stop..].iter().any(|r| matches!(r.entry, Entry::StepStart { .. } | Entry::Condition { .. }));
            prop_assert!(!moved, "a step or a condition after the stop");
            prop_assert_eq!(run.primitives.holds.last().copied(), Some(run.primitives.calls.len()));
        }
        // The journal rebuilds the runner's report, and the same schedule gives the same
        // journal.
        let steps: Vec<usize> = run.plan.throws.iter().map(|t| t.program.len()).collect();
        let whole = Rebuilt::from_journal(records, Some(&steps)).expect("its own journal");
        // (Times at a command's instant are not whole seconds: the journal keeps them to the
        // nanosecond, so attempts are compared without their times.)
        let seen = |t: &[stitch_engine::ThrowSummary]| -> Vec<Vec<(usize, u32, StepOutcome)>> {
            t.iter()
                .map(|t| t.attempts.iter().map(|a| (a.step, a.attempt, a.outcome.clone())).collect())
                .collect()
        };
        prop_assert_eq!(seen(&whole.throws), seen(&run.report.throws));
        let again = run_scripted(plan, outcomes, cmds, ivs);
        prop_assert_eq!(again.report.journal.records(), records);
    }
}
