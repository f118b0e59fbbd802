//! Every metric of Table I checked by hand on a hand-made set of trials.

use stitch_engine::trials::{TrialRecord, metrics, t95, wilson};

fn trial(
    sutures: usize,
    failure: Option<&str>,
    errors: [u32; 4],
    before: &[u32],
    s: f64,
) -> TrialRecord {
    TrialRecord {
        policy: "hand".into(),
        seed: 0,
        throws: 6,
        sutures,
        outcome: if failure.is_some() {
            "failed"
        } else {
            "completed"
        }
        .into(),
        failure: failure.map(str::to_string),
        errors,
        interventions: before.len() as u32,
        sutures_before_interventions: before.to_vec(),
        duration_s: s,
        entry_error_mm: None,
        exit_error_mm: None,
    }
}

#[test]
fn every_metric_matches_its_definition() {
    // Four trials:
    //   A: 1 suture, then an insertion error ends it                 (attempts 2)
    //   B: 3 sutures, an extraction error asks for help after the 2nd, then a thread error
    //      ends it                                                    (attempts 3 + 2 = 5)
    //   C: 6 sutures, the wound closed; help asked after the 4th (handover)  (attempts 7)
    //   D: 0 sutures, an insertion error                              (attempts 1)
    let set = [
        trial(1, Some("I"), [1, 0, 0, 0], &[], 100.0),
        trial(3, Some("T"), [0, 1, 0, 1], &[2], 450.0),
        trial(6, None, [0, 0, 1, 0], &[4], 900.0),
        trial(0, Some("I"), [1, 0, 0, 0], &[], 50.0),
    ];
    let m = metrics("hand", &set);
    assert_eq!(m.trials, 4);
    // Mean sutures to failure: (1 + 3 + 6 + 0) / 4 = 2.5; s² = (2.25 + 0.25 + 12.25 + 6.25) / 3
    // = 7; half-width t(3) · √(7/4) = 3.182 × 1.3229 = 4.209.
    assert!((m.mean_sutures_to_failure.value - 2.5).abs() < 1e-12);
    let h = 3.182 * (7.0f64 / 4.0).sqrt();
    assert!((m.mean_sutures_to_failure.high - (2.5 + h)).abs() < 1e-9);
    assert!((m.mean_sutures_to_failure.low - (2.5 - h)).abs() < 1e-9);
    // Single-suture success: 10 sutures of 10 + 5 errors = 15 attempts.
    assert!((m.single_suture_success.value - 10.0 / 15.0).abs() < 1e-12);
    // Three throw: B and C of 4; full wound: C of 4.
    assert!((m.three_throw_success.value - 0.5).abs() < 1e-12);
    assert!((m.full_wound_success.value - 0.25).abs() < 1e-12);
    // Time per suture: 1,500 s over 10 sutures.
    assert_eq!(m.mean_time_per_suture_s, Some(150.0));
    // Errors I, E, H, T.
    assert_eq!(m.errors, [2, 1, 1, 1]);
    // Sutures to intervention: requests after 2 and after 4 sutures → 3.
    assert_eq!(m.mean_sutures_to_intervention, Some(3.0));
    // Without interventions or sutures, no such numbers.
    let none = metrics("none", &[trial(0, Some("E"), [0, 1, 0, 0], &[], 30.0)]);
    assert_eq!(none.mean_sutures_to_intervention, None);
    assert_eq!(none.mean_time_per_suture_s, None);
    assert!((none.single_suture_success.value).abs() < 1e-12);
}

#[test]
fn wilson_and_t_intervals_match_published_values() {
    // Wilson, 95 %: 7 of 10 → [0.3968, 0.8922] (Newcombe 1998, Table I).
    let w = wilson(7, 10);
    assert!(
        (w.low - 0.3968).abs() < 1e-3 && (w.high - 0.8922).abs() < 1e-3,
        "{w:?}"
    );
    // 0 of 15 → [0, 0.2039].
    let w = wilson(0, 15);
    assert!(
        w.low.abs() < 1e-12 && (w.high - 0.2039).abs() < 1e-3,
        "{w:?}"
    );
    assert!((t95(14) - 2.145).abs() < 1e-9);
    assert!((t95(1000) - 1.962).abs() < 1e-3);
}

/// Runs a two-throw, insert-only plan (validation skipped: only the record's arithmetic is
/// under test) against scripted outcomes and interventions.
fn record_of(
    outcomes: Vec<stitch_primitives::Scripted>,
    interventions: Vec<stitch_engine::InterventionResult>,
) -> TrialRecord {
    use std::sync::Arc;
    let wound = stitch_robot::Wound::linear(&stitch_robot::WoundSpec::default()).expect("wound");
    let loader = stitch_engine::PlanLoader::new(&wound, stitch_engine::ScriptLimits::default());
    let loaded = loader
        .eval_str(
            "t.rhai",
            "let w = wound(); mission(#{ name: \"t\", interventions: 2, throws: [suture(w[0], [insert()]), suture(w[1], [insert()])] })",
        )
        .expect("plan");
    let clock = stitch_robot::SimClock::new();
    let mut primitives =
        stitch_primitives::ScriptedPrimitives::from_schedule(outcomes, clock.clone());
    let mut supervisor = stitch_engine::ScriptedSupervisor::new([], interventions);
    let plan = Arc::new(loaded.plan.clone());
    let report = stitch_engine::Runner::new(
        Arc::clone(&plan),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        None,
    )
    .run();
    TrialRecord::from_report("t", 0, &plan, &report)
}

#[test]
fn records_count_each_error_once_and_every_intervention_request() {
    use stitch_engine::InterventionResult::{Failed, Recovered};
    use stitch_primitives::Scripted::{Fail, Ok};
    // Throw 1 succeeds; throw 2's insertion fails, an intervention recovers, it fails
    // again, the second intervention fails: the trial ends with I.
    let r = record_of(vec![Ok, Fail, Fail], vec![Recovered, Failed]);
    assert_eq!((r.sutures, r.outcome.as_str()), (1, "failed"));
    assert_eq!(r.failure.as_deref(), Some("I"));
    // One error the trial went on after, one that ended it: two, not three.
    assert_eq!(r.errors, [2, 0, 0, 0]);
    assert_eq!(r.attempts(), 3);
    // Two requests, both after one suture and none since.
    assert_eq!(r.sutures_before_interventions, vec![1, 0]);
    // Every throw done after one recovered intervention.
    let r = record_of(vec![Fail, Ok, Ok], vec![Recovered]);
    assert_eq!(
        (r.sutures, r.outcome.as_str(), r.errors),
        (2, "completed", [1, 0, 0, 0])
    );
    assert_eq!(r.sutures_before_interventions, vec![0]);
}
