//! Plans that look before they act: conditions decided on the mock dVRK's observations and the
//! engine's bookkeeping, loops bounded by their cap or stopped by their condition, validation
//! through every branch, and surgeon checkpoints.

use std::sync::Arc;
use stitch_engine::{
    BranchRole, Entry, OutcomeSchedule, Plan, PlanLoader, Report, RunOutcome, Runner, ScriptLimits,
    ScriptedSupervisor, SupervisorCommand, load_plan_str,
};
use stitch_primitives::{MockPerception, mock_primitives_with};
use stitch_robot::{SimClock, Wound};
use stitch_sim::{SceneConfig, SensingConfig, ThreadConfig};

fn scene() -> SceneConfig {
    SceneConfig {
        thread: ThreadConfig {
            catch_radius_m: 0.0,
            occlusion_radius_m: 0.0,
            ..ThreadConfig::default()
        },
        ..SceneConfig::default()
    }
}

fn load(source: &str) -> Plan {
    let wound = Wound::linear(&scene().wound).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    load_plan_str(&loader, "reactive.rhai", source)
        .unwrap_or_else(|e| panic!("{e}"))
        .plan
}

/// Run `plan` on the mock dVRK (perfect sensing unless said), answering checkpoints with
/// `answers`.
fn on_mock(plan: &Plan, sensing: SensingConfig, answers: Vec<SupervisorCommand>) -> Report {
    on_mock_with(plan, &scene(), MockPerception::Model(sensing), answers).0
}

/// Run `plan` on a mock dVRK of `scene` seeing through `perception`; the report and the world
/// as the run left it.
fn on_mock_with(
    plan: &Plan,
    scene: &SceneConfig,
    perception: MockPerception,
    answers: Vec<SupervisorCommand>,
) -> (Report, stitch_sim::MockDvrk) {
    let clock = SimClock::new();
    let (mut primitives, world) =
        mock_primitives_with(scene, perception, 1, clock.clone()).expect("mock");
    let mut supervisor = ScriptedSupervisor::default().with_checkpoints(answers);
    let report = Runner::new(
        Arc::new(plan.clone()),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        Some(1),
    )
    .run();
    (report, world)
}

/// The conditions a run decided: (condition, value).
fn decided(report: &Report) -> Vec<(String, bool)> {
    report
        .journal
        .records()
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::Condition {
                condition, value, ..
            } => Some((condition.clone(), *value)),
            _ => None,
        })
        .collect()
}

/// The steps a run attempted, in order.
fn attempted(report: &Report) -> Vec<String> {
    report
        .journal
        .records()
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::StepStart { primitive, .. } => Some(primitive.clone()),
            _ => None,
        })
        .collect()
}

/// One throw that first decides `cond`: a needle query if it holds, a thread query if not;
/// then the paper's throw.
fn branching_on(cond: &str) -> String {
    format!(
        "let t = suture(wound()[0], [\n\
           when({cond}, [estimate_needle()]).otherwise([track_thread()]),\n\
           insert(), sweep(), extract(), cinch(), handover(),\n\
         ]);\n\
         mission(#{{ name: \"when\", interventions: 1, thread_length: cm(30), throws: [t] }})"
    )
}

#[test]
fn a_when_on_each_kind_of_condition_takes_both_branches_on_the_mock() {
    // Each condition with a bound it meets and one it does not, on the mock's first throw:
    // the needle in the right jaw near its swage, seen by perfect sensing.
    let cases = [
        ("needle_seen()", "not(needle_seen())"),
        ("needle_confidence() >= 0.5", "needle_confidence() > 1.0"),
        (
            "needle_normal_angle(direction(0, 1, 0)) <= deg(180)",
            "needle_normal_angle(direction(0, 1, 0)) < deg(0)",
        ),
        (
            "needle_swage_distance(right_jaw()) < mm(10)",
            "needle_swage_distance(right_jaw()) > mm(10)",
        ),
        (
            "needle_tip_distance(right_jaw()) > mm(10)",
            "needle_tip_distance(wound()[0].entry) < mm(1)",
        ),
        ("needle_age() < s(1)", "needle_age() > s(1)"),
        ("thread_left() > cm(29)", "thread_left() < cm(29)"),
        ("throw_number() == 1", "throw_number() != 1"),
        ("interventions_left() == 1", "interventions_left() == 0"),
        ("retries_used() == 0", "retries_used() > 0"),
        (
            "all([needle_seen(), throw_number() == 1])",
            "any([not(needle_seen()), throw_number() > 1])",
        ),
        // The thread, traced now: before the first stitch it runs from its tail to the
        // swage, held in the right jaw; the left jaw is at its home, centimetres away.
        ("thread_free() > cm(5)", "thread_free() > m(5)"),
        (
            "thread_clearance(left_jaw()) > mm(5)",
            "thread_clearance(left_jaw()) > m(1)",
        ),
        (
            "thread_wrap(left_jaw()) < deg(360)",
            "thread_wrap(left_jaw()) >= deg(360)",
        ),
        // A point on the estimated arc: its swage is on it, its tip 24 mm away.
        (
            "needle_swage_distance(needle_point(deg(180))) < mm(1)",
            "needle_swage_distance(needle_point(deg(0))) < mm(1)",
        ),
    ];
    // The tip is a half circle (24 mm across for the 12 mm needle) from the swage the jaw
    // holds: more than a centimetre from the jaw.
    for (holds, fails) in cases {
        for (cond, expect) in [(holds, true), (fails, false)] {
            let report = on_mock(&load(&branching_on(cond)), SensingConfig::perfect(), vec![]);
            let values = decided(&report);
            assert_eq!(values.len(), 1, "{cond}: {values:?}");
            assert_eq!(values[0].1, expect, "{cond} decided {values:?}");
            let first = attempted(&report).first().cloned();
            let branch = if expect {
                "estimate_needle"
            } else {
                "track_thread"
            };
            assert_eq!(first.as_deref(), Some(branch), "{cond}");
            assert_eq!(report.outcome, RunOutcome::Completed, "{cond}");
            // The journal keeps what it was decided on: a needle query's estimate where one
            // was needed.
            let needle = report
                .journal
                .records()
                .iter()
                .find_map(|r| match &r.entry {
                    Entry::Condition { observation, .. } => Some(observation.needle.is_some()),
                    _ => None,
                });
            let traced = cond.contains("thread_") && !cond.contains("thread_left");
            let needs = cond.contains("needle") || traced;
            assert_eq!(needle, Some(needs), "{cond}");
            // ...and the trace where the thread was read, the free length a thread's.
            let thread = report
                .journal
                .records()
                .iter()
                .find_map(|r| match &r.entry {
                    Entry::Condition { observation, .. } => Some(observation.thread.clone()),
                    _ => None,
                })
                .flatten();
            assert_eq!(thread.is_some(), traced, "{cond}: {thread:?}");
            if let Some(t) = thread {
                assert!(
                    t.points.len() >= 2 && t.points.len() == t.sigma_m.len(),
                    "{t:?}"
                );
                assert!((0.05..1.0).contains(&t.length_m), "{t:?}");
            }
        }
    }
}

#[test]
fn a_needle_out_of_sight_makes_needle_comparisons_false_and_needle_seen_false() {
    let mut blind = SensingConfig::perfect();
    blind.in_corner.p_dropout = 1.0;
    blind.elsewhere.p_dropout = 1.0;
    for cond in [
        "needle_seen()",
        "needle_confidence() >= 0.0",
        "needle_age() < s(1000)",
    ] {
        let report = on_mock(&load(&branching_on(cond)), blind, vec![]);
        assert!(!decided(&report)[0].1, "{cond}");
        assert_eq!(attempted(&report)[0], "track_thread", "{cond}");
    }
}

/// A throw whose insertion is preceded by `repeat(params, [estimate_needle()])`.
fn repeating(params: &str) -> String {
    format!(
        "let t = suture(wound()[0], [\n\
           repeat(#{{ {params} }}, [estimate_needle()]),\n\
           insert(), sweep(), extract(), cinch(), handover(),\n\
         ]);\n\
         mission(#{{ name: \"repeat\", throws: [t] }})"
    )
}

fn scripted(plan: &Plan, conditions: Vec<bool>, checkpoints: Vec<SupervisorCommand>) -> Report {
    let schedule = OutcomeSchedule {
        conditions: conditions.into_iter().map(Some).collect(),
        checkpoints,
        ..OutcomeSchedule::default()
    };
    let clock = SimClock::new();
    let (mut primitives, mut supervisor) = schedule.into_parts(clock.clone());
    Runner::new(
        Arc::new(plan.clone()),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        None,
    )
    .run()
}

fn count(report: &Report, name: &str) -> usize {
    attempted(report).iter().filter(|p| *p == name).count()
}

#[test]
fn a_repeat_stops_at_its_bound() {
    // On the mock: a condition no estimate meets, checked before each of the 3 runs.
    let plan = load(&repeating("max: 3, stop_when: needle_confidence() > 1.0"));
    let report = on_mock(&plan, SensingConfig::perfect(), vec![]);
    assert_eq!(count(&report, "estimate_needle"), 3);
    let values = decided(&report);
    assert_eq!(values.len(), 3, "{values:?}");
    assert!(values.iter().all(|(_, v)| !v));
    assert_eq!(report.outcome, RunOutcome::Completed);
    // Without `stop_when`: exactly `max` runs, nothing decided.
    let plan = load(&repeating("max: 2"));
    let report = scripted(&plan, vec![], vec![]);
    assert_eq!(count(&report, "estimate_needle"), 2);
    assert!(decided(&report).is_empty());
}

#[test]
fn a_repeat_stops_on_its_condition() {
    // On the mock: the first check already sees the needle.
    let plan = load(&repeating("max: 3, stop_when: needle_seen()"));
    let report = on_mock(&plan, SensingConfig::perfect(), vec![]);
    assert_eq!(count(&report, "estimate_needle"), 0);
    assert_eq!(decided(&report), vec![("needle_seen()".to_string(), true)]);
    // Scripted values: false, false, then true: two runs.
    let plan = load(&repeating("max: 5, stop_when: needle_seen()"));
    let report = scripted(&plan, vec![false, false, true], vec![]);
    assert_eq!(count(&report, "estimate_needle"), 2);
    let roles: Vec<BranchRole> = report
        .journal
        .records()
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::Condition { role, .. } => Some(*role),
            _ => None,
        })
        .collect();
    assert_eq!(
        roles,
        [1, 2, 3].map(|run| BranchRole::Until { run }).to_vec(),
        "the stop_when before runs 1, 2 and 3"
    );
}

#[test]
fn a_branch_that_leaves_the_needle_in_the_wrong_jaw_is_refused_at_its_position() {
    let wound = Wound::linear(&scene().wound).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let source = "let a = suture(wound()[0], [\n\
                    insert(), sweep(), extract(), cinch(),\n\
                    when(needle_confidence() >= 0.8, [handover()]),\n\
                  ]);\n\
                  let b = suture(wound()[1], [insert(), sweep(), extract(), cinch(), handover()]);\n\
                  mission(#{ name: \"unsafe when\", throws: [a, b] })";
    let e = load_plan_str(&loader, "unsafe.rhai", source).expect_err("refused");
    let first = &e.0[0];
    assert_eq!((first.pos.line, first.pos.col), (3, 1), "{e}");
    assert!(
        first.message.contains(
            "when: the needle ends in the right jaw if `needle_confidence() >= 0.8` holds and \
             in the left jaw if not"
        ),
        "{e}"
    );
    // A repeated block that moves the needle is refused too, at the repeat.
    let source = "let a = suture(wound()[0], [\n\
                    repeat(#{ max: 2, stop_when: needle_seen() }, [insert(), sweep(), extract()]),\n\
                    cinch(), handover(),\n\
                  ]);\n\
                  mission(#{ name: \"unsafe repeat\", throws: [a] })";
    let e = load_plan_str(&loader, "unsafe.rhai", source).expect_err("refused");
    let text = e.to_string();
    assert!(
        text.contains("unsafe.rhai:2:1: throw 1: repeat: its steps take the needle from in the right jaw to in the left jaw"),
        "{text}"
    );
    assert!(
        text.contains("insert() must run exactly once on every path; here it runs 0 to 2 times"),
        "{text}"
    );
}

/// A throw that waits for the surgeon before inserting.
fn with_checkpoint() -> Plan {
    load(
        "let t = suture(wound()[0], [\n\
           checkpoint(\"first insertion\"),\n\
           insert(), sweep(), extract(), cinch(), handover(),\n\
         ]);\n\
         mission(#{ name: \"checkpoint\", throws: [t] })",
    )
}

#[test]
fn a_checkpoint_holds_the_run_until_the_supervisors_go() {
    let report = on_mock(
        &with_checkpoint(),
        SensingConfig::perfect(),
        vec![SupervisorCommand::Go],
    );
    let entries: Vec<&Entry> = report.journal.records().iter().map(|r| &r.entry).collect();
    let at = entries
        .iter()
        .position(|e| matches!(e, Entry::Checkpoint { label, .. } if label == "first insertion"))
        .expect("the checkpoint is journaled");
    let go = entries
        .iter()
        .position(|e| {
            matches!(
                e,
                Entry::Supervisor {
                    command: SupervisorCommand::Go,
                    acted: true,
                    ..
                }
            )
        })
        .expect("the go acted on");
    let first_step = entries
        .iter()
        .position(|e| matches!(e, Entry::StepStart { .. }))
        .expect("steps ran");
    let hold = entries
        .iter()
        .position(|e| matches!(e, Entry::Hold { state, .. } if state.starts_with("at_checkpoint")))
        .expect("the arms held at the checkpoint");
    assert!(hold < at && at < go && go < first_step, "{entries:?}");
    assert_eq!(report.outcome, RunOutcome::Completed);
    // The throw's summary (what timelines print) says the surgeon confirmed it.
    let seen = &report.throws[0].checkpoints;
    assert_eq!(seen.len(), 1);
    assert_eq!(
        (seen[0].label.as_str(), seen[0].answer),
        ("first insertion", Some(SupervisorCommand::Go))
    );
}

#[test]
fn an_abort_at_a_checkpoint_ends_the_run_safely_with_nothing_moved() {
    for stop in [SupervisorCommand::Abort, SupervisorCommand::EStop] {
        let report = scripted(&with_checkpoint(), vec![], vec![stop]);
        assert!(
            matches!(
                report.outcome,
                RunOutcome::Aborted {
                    throw: 0,
                    step: 0,
                    ..
                }
            ),
            "{:?}",
            report.outcome
        );
        assert!(attempted(&report).is_empty());
        let holds = report
            .journal
            .records()
            .iter()
            .filter(|r| matches!(r.entry, Entry::Hold { .. }))
            .count();
        assert_eq!(holds, 2, "held at the checkpoint and again at the abort");
    }
    // On the mock: the arms hold where they were, the needle still in the right jaw.
    let report = on_mock(
        &with_checkpoint(),
        SensingConfig::perfect(),
        vec![SupervisorCommand::Abort],
    );
    assert!(matches!(report.outcome, RunOutcome::Aborted { .. }));
    assert!(attempted(&report).is_empty());
}

#[test]
fn a_condition_the_robot_could_not_observe_is_not_decided_and_fails_in_the_needles_phase() {
    // The first `measured_cp` of the run is the condition's query of the right arm: stale.
    // Read as a missing jaw, `needle_confidence() >= 0.8` would be false, `not(..)` true, and
    // the plan would go on deciding on nothing; it must stop instead, the arms held.
    let plan = load(
        "let t = suture(wound()[0], [\n\
           repeat(#{ max: 3, stop_when: needle_confidence() >= 0.8 }, [estimate_needle()]),\n\
           insert(), sweep(), extract(), cinch(), handover(),\n\
         ]);\n\
         mission(#{ name: \"unobserved\", interventions: 0, throws: [t] })",
    );
    let mut scene = scene();
    scene.faults.schedule.push(stitch_sim::ScheduledFault {
        kind: stitch_sim::FaultKind::StaleMeasurement,
        nth: 1,
    });
    let (report, _) = on_mock_with(
        &plan,
        &scene,
        MockPerception::Model(SensingConfig::perfect()),
        vec![],
    );
    let records = report.journal.records();
    let at = records
        .iter()
        .position(|r| matches!(&r.entry, Entry::Unobserved { observation, .. } if !observation.faults.is_empty()))
        .unwrap_or_else(|| panic!("no unobserved condition journaled: {records:#?}"));
    assert!(
        !records
            .iter()
            .any(|r| matches!(r.entry, Entry::Condition { .. })),
        "nothing was decided"
    );
    assert!(
        !records[at..]
            .iter()
            .any(|r| matches!(r.entry, Entry::StepStart { .. })),
        "no step ran after it"
    );
    assert!(
        records[at..]
            .iter()
            .any(|r| matches!(r.entry, Entry::Hold { .. })),
        "the arms were held"
    );
    match &report.outcome {
        RunOutcome::Failed { class, reason, .. } => {
            assert_eq!(
                class.code(),
                'I',
                "the needle is in the right jaw: insertion"
            );
            let Some(stitch_primitives::FailureKind::ArmFault { message }) = reason else {
                panic!("{reason:?}");
            };
            assert!(message.contains("not decided"), "{message}");
            assert!(message.contains("measurement is"), "{message}");
        }
        other => panic!("{other:?}"),
    }
}

#[test]
fn a_thread_condition_with_the_pipeline_is_decided_on_a_trace_of_the_rendered_thread() {
    // A throw, then a condition on the thread from that stitch's exit to the swage (the
    // needle back in the right jaw after the handover); both branches only look, so the
    // world at the end is the world the trace was made of.
    let source = "let t = suture(wound()[0], [\n\
           insert(), sweep(), extract(), cinch(), handover(),\n\
           when(all([thread_free() > cm(2), thread_clearance(left_jaw()) > mm(1)]),\n\
                [estimate_needle()]).otherwise([estimate_needle()]),\n\
         ]);\n\
         mission(#{ name: \"traced\", throws: [t] })";
    let perception = MockPerception::Pipeline(Box::default(), None);
    let (report, world) = on_mock_with(&load(source), &scene(), perception, vec![]);
    assert_eq!(
        report.outcome,
        RunOutcome::Completed,
        "{:?}",
        report.outcome
    );
    let (value, observation) = report
        .journal
        .records()
        .iter()
        .find_map(|r| match &r.entry {
            Entry::Condition {
                value, observation, ..
            } => Some((*value, observation.clone())),
            _ => None,
        })
        .expect("a condition decided");
    let trace = observation
        .thread
        .unwrap_or_else(|| panic!("traced: {:?}", observation.thread_failure));
    let truth: Vec<stitch_robot::Point> = world.thread_in_view().iter().map(|(p, _)| *p).collect();
    let true_len: f64 = truth.windows(2).map(|w| (w[1] - w[0]).norm()).sum();
    // Where the thread runs along the image rows its depth is bridged, not measured, and the
    // trace says so: every point within its 2σ of the true thread (and a millimetre of
    // rounding), the ends where they are, the length within 10 %.
    for (p, s) in trace.points.iter().zip(&trace.sigma_m) {
        let e = stitch_robot::distance_to_polyline(p, &truth);
        assert!(e <= 2.0 * s + 0.001, "{p:?}: {e} m off, σ {s} m");
    }
    assert!((trace.points[0] - truth[0]).norm() < 0.002);
    assert!((trace.points[trace.points.len() - 1] - truth[truth.len() - 1]).norm() < 0.002);
    assert!(
        (trace.length_m - true_len).abs() < 0.1 * true_len,
        "{} m traced, {true_len} m true",
        trace.length_m
    );
    // Decided on that trace: the free length is the trace's, the clearance the left jaw's.
    let left = observation.left_jaw.expect("left jaw measured");
    let clearance = trace
        .points
        .iter()
        .zip(&trace.sigma_m)
        .map(|(p, s)| (p - left).norm() - 2.0 * s)
        .fold(f64::INFINITY, f64::min);
    // The left jaw waits at its home, well clear of the thread on the pad: the condition
    // holds, and not by a hair.
    assert!(
        value && trace.length_m > 0.02 && clearance > 0.006,
        "{value}: {} m free, {clearance} m clear",
        trace.length_m
    );
}

#[test]
fn track_thread_traces_a_thread_in_view_and_fails_typed_on_one_hidden() {
    let source = |retries: u32| {
        format!(
            "let t = suture(wound()[0], [\n\
               track_thread(#{{ retries: {retries} }}),\n\
               insert(), sweep(), extract(), cinch(), handover(),\n\
             ]);\n\
             mission(#{{ name: \"track\", throws: [t] }})"
        )
    };
    // In view: traced, its length measured (the whole thread before the first stitch).
    let (report, _) = on_mock_with(
        &load(&source(1)),
        &scene(),
        MockPerception::Model(SensingConfig::perfect()),
        vec![],
    );
    assert_eq!(report.outcome, RunOutcome::Completed);
    let first = report
        .journal
        .records()
        .iter()
        .find_map(|r| match &r.entry {
            Entry::StepEnd { outcome, .. } => Some(outcome.clone()),
            _ => None,
        });
    let Some(stitch_primitives::StepOutcome::Succeeded { measured }) = first else {
        panic!("track_thread: {first:?}");
    };
    let traced = measured.thread_left_m.expect("a length");
    let whole = scene().thread.length_m;
    assert!(
        (traced - whole).abs() < 0.1 * whole,
        "{traced} m of {whole} m"
    );

    // Hidden (most links within 20 cm of a tool, the most the mock allows): a perception
    // dropout naming the typed failure, retried, then the thread class; the arms hold.
    let mut hidden = scene();
    hidden.thread.occlusion_radius_m = 0.2;
    let (report, _) = on_mock_with(
        &load(&source(1)),
        &hidden,
        MockPerception::Model(SensingConfig::perfect()),
        vec![],
    );
    let ends: Vec<&stitch_primitives::StepOutcome> = report
        .journal
        .records()
        .iter()
        .filter_map(|r| match &r.entry {
            Entry::StepEnd { outcome, .. } => Some(outcome),
            _ => None,
        })
        .collect();
    assert_eq!(ends.len(), 2, "one try and one retry: {ends:?}");
    for e in &ends {
        let stitch_primitives::StepOutcome::Failed(f) = e else {
            panic!("{e:?}");
        };
        assert_eq!(f.kind, stitch_primitives::FailureKind::PerceptionDropout);
        assert!(
            f.measured
                .perception_failures
                .iter()
                .any(|m| m.starts_with("thread:") && m.contains("hidden")),
            "{:?}",
            f.measured.perception_failures
        );
    }
    assert!(
        report
            .journal
            .records()
            .iter()
            .any(|r| matches!(r.entry, Entry::Hold { .. })),
        "the arms were held"
    );
    match &report.outcome {
        RunOutcome::Failed { class, .. } => {
            assert_eq!(class.code(), 'T', "thread management")
        }
        other => panic!("{other:?}"),
    }
}
