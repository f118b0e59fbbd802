//! Model checking: every outcome branch of a plan through the real state machine.

use std::path::Path;
use std::sync::Arc;
use stitch_engine::{
    Action, ExploreOptions, OutcomeSchedule, Plan, PlanLoader, RunOutcome, Runner, ScriptLimits,
    explore, load_plan, load_plan_str, mermaid,
};
use stitch_primitives::Scripted;
use stitch_robot::{SimClock, Wound, WoundSpec};

fn loader() -> PlanLoader {
    PlanLoader::new(
        &Wound::linear(&WoundSpec::default()).expect("wound"),
        ScriptLimits::default(),
    )
}

fn script(name: &str) -> Plan {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scripts")
        .join(name);
    load_plan(&loader(), &path)
        .unwrap_or_else(|e| panic!("{e}"))
        .plan
}

/// An invalid plan, built without validation, for the checker to catch.
fn unvalidated(source: &str) -> Plan {
    loader()
        .eval_str("broken.rhai", source)
        .unwrap_or_else(|e| panic!("{e}"))
        .plan
}

fn replay(plan: &Plan, schedule: OutcomeSchedule) -> (stitch_engine::Report, Vec<&'static str>) {
    let clock = SimClock::new();
    let (mut primitives, mut supervisor) = schedule.into_parts(clock.clone());
    let report = Runner::new(
        Arc::new(plan.clone()),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        None,
    )
    .run();
    (
        report,
        primitives.calls.iter().map(|c| c.primitive).collect(),
    )
}

#[test]
fn the_six_throw_stitch_plans_satisfy_every_property() {
    for name in [
        "stitch.rhai",
        "stitch_human.rhai",
        "stitch_reactive.rhai",
        "stitch_reactive_human.rhai",
    ] {
        let plan = script(name);
        assert_eq!(plan.throws.len(), 6);
        let found = explore(Arc::new(plan), ExploreOptions::default());
        // Reported in the note: states explored and time, from `cargo test -- --nocapture`.
        eprintln!(
            "{name}: {} states, {:.3e} complete paths, farthest state {} choices away, {:.2} s",
            found.states,
            found.paths as f64,
            found.max_depth,
            found.elapsed.as_secs_f64()
        );
        for v in &found.verdicts {
            assert!(v.holds, "{name}: {} fails: {:?}", v.says, v.path);
        }
        // stateright's checker and the counterexample pass saw the same states.
        assert_eq!(found.states, found.graph_states, "{name}");
        assert!(
            found.states > 1000,
            "{name}: {} states is too few to be exhaustive",
            found.states
        );
        assert!(found.paths > 1_000_000);
    }
}

#[test]
fn a_plan_that_sweeps_before_inserting_is_caught_with_the_shortest_counterexample() {
    let plan = unvalidated(
        "let t = suture(wound()[0], [sweep(), insert(), extract(), handover()]);\n\
         mission(#{ name: \"sweep first\", throws: [t] })",
    );
    let found = explore(Arc::new(plan.clone()), ExploreOptions::default());
    assert!(!found.all_hold());
    let jaw = found
        .verdicts
        .iter()
        .find(|v| v.name == "jaw opening")
        .expect("property");
    assert!(!jaw.holds);
    let path = jaw.path.as_ref().expect("a counterexample");
    assert_eq!(path.len(), 1, "{path:?}");
    assert_eq!(
        path[0],
        (
            "sweeping(t1 s1 r0)".to_string(),
            Action::Attempt(Scripted::Ok)
        )
    );
    let insert = found
        .verdicts
        .iter()
        .find(|v| v.name == "insert holds needle")
        .expect("property");
    assert_eq!(insert.path.as_ref().map(Vec::len), Some(2));

    // The schedule replays the same choices through the real runner, then stops.
    let (report, calls) = replay(&plan, insert.schedule.clone().expect("schedule"));
    assert_eq!(calls, vec!["sweep", "insert"]);
    assert!(matches!(
        report.outcome,
        RunOutcome::Aborted {
            throw: 0,
            step: 2,
            ..
        }
    ));
}

#[test]
fn a_plan_that_keeps_the_needle_in_the_left_jaw_breaks_the_next_insert() {
    // Valid budgets, unsafe order: throw 1 never hands the needle back.
    let plan = unvalidated(
        "let a = suture(wound()[0], [insert(), sweep(), extract(#{ retries: 2 }), cinch()]);\n\
         let b = suture(wound()[1], [insert(), sweep(), extract(), cinch(), handover()]);\n\
         mission(#{ name: \"no handover\", interventions: 1, throws: [a, b] })",
    );
    let found = explore(Arc::new(plan.clone()), ExploreOptions::default());
    let v = found
        .verdicts
        .iter()
        .find(|v| v.name == "insert holds needle")
        .expect("property");
    let path = v.path.as_ref().expect("counterexample");
    // insert, sweep, extract, cinch all succeed; then the second insert starts.
    assert_eq!(path.len(), 5, "{path:?}");
    assert_eq!(path[4].0, "inserting(t2 s1 r0)");
    let (_, calls) = replay(&plan, v.schedule.clone().expect("schedule"));
    assert_eq!(calls, vec!["insert", "sweep", "extract", "cinch", "insert"]);
}

#[test]
fn budgets_above_the_caps_in_an_unvalidated_plan_are_still_held_by_the_machine() {
    let plan = unvalidated(
        "let t = suture(wound()[0], [insert(), sweep(), extract(#{ retries: 9 }), cinch(), handover(#{ retries: 9 })]);\n\
         mission(#{ name: \"greedy\", interventions: 7, throws: [t] })",
    );
    let found = explore(Arc::new(plan), ExploreOptions::default());
    for v in &found.verdicts {
        assert!(v.holds, "{} fails: {:?}", v.says, v.path);
    }
}

#[test]
fn exploring_without_supervisor_commands_never_aborts() {
    let found = explore(
        Arc::new(script("sensing_only.rhai")),
        ExploreOptions {
            max_commands: 0,
            ..ExploreOptions::default()
        },
    );
    assert!(found.all_hold());
    assert!(
        !found
            .edges
            .keys()
            .any(|(_, to)| *to == "aborted" || *to == "paused")
    );
    assert!(found.edges.keys().any(|(_, to)| *to == "failed"));
}

/// The lines around the generated diagram in docs/ARCHITECTURE.md.
const BEGIN: &str = "<!-- BEGIN GENERATED STATE DIAGRAM -->";
const END: &str = "<!-- END GENERATED STATE DIAGRAM -->";

#[test]
fn the_committed_state_diagram_is_the_one_the_exploration_generates() {
    let found = explore(
        Arc::new(script("stitch_reactive_human.rhai")),
        ExploreOptions::default(),
    );
    let fresh = format!("{BEGIN}\n```mermaid\n{}```\n{END}", mermaid(&found.edges));
    let doc_path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/ARCHITECTURE.md");
    let doc = std::fs::read_to_string(&doc_path).expect("docs/ARCHITECTURE.md");
    let (a, b) = (
        doc.find(BEGIN).expect("begin marker"),
        doc.find(END).expect("end marker"),
    );
    let committed = &doc[a..b + END.len()];
    assert!(
        committed == fresh,
        "docs/ARCHITECTURE.md's state diagram is stale; regenerate it with\n  \
         cargo run -p stitch-cli -- check scripts/stitch_reactive_human.rhai --explore --diagram docs/ARCHITECTURE.md"
    );
    // It shows every kind of state the machine can be in.
    for state in [
        "inserting",
        "sweeping",
        "extracting",
        "cinching",
        "handing_over",
        "correcting",
        "perceiving",
        "deciding",
        "at_checkpoint",
        "awaiting_intervention",
        "paused",
        "taken_over",
        "completed",
        "failed",
        "aborted",
    ] {
        assert!(fresh.contains(state), "{state} missing from the diagram");
    }
}

#[test]
fn a_state_of_each_kind_is_reached() {
    let plan = load_plan_str(
        &loader(),
        "p.rhai",
        "let t = suture(wound()[0], [estimate_needle(), insert(), sweep(), extract(), cinch(), handover(), correct()]);\n\
         mission(#{ name: \"all\", interventions: 1, throws: [t] })",
    )
    .expect("valid")
    .plan;
    let found = explore(Arc::new(plan), ExploreOptions::default());
    assert!(found.all_hold());
    assert!(found.edges.keys().any(|(from, _)| *from == "perceiving"));
}

#[test]
fn a_path_with_commands_mid_step_replays_through_the_runner_state_for_state() {
    use stateright::Model;
    use stitch_engine::{EngineModel, SupervisorCommand::*, schedule_of, state_label};
    let mut plan = script("stitch.rhai");
    plan.throws.truncate(1);
    let plan = Arc::new(plan);
    let actions = [
        Action::Interrupt(Pause, false),
        Action::Command(Resume),
        Action::Attempt(Scripted::Ok),
        Action::Attempt(Scripted::Ok),
        Action::Interrupt(TakeOver, true),
        Action::Command(HandBack),
        Action::Interrupt(TakeOver, false),
        Action::Command(HandBack),
        Action::Attempt(Scripted::Ok),
        Action::Interrupt(Abort, true),
    ];
    let model = EngineModel::new(Arc::clone(&plan), ExploreOptions::default());
    let mut state = model.init_states().remove(0);
    let mut expected = vec![state_label(state.state())];
    for a in actions {
        state = model
            .next_state(&state, a)
            .unwrap_or_else(|| panic!("{a} is not a choice in {}", state_label(state.state())));
        expected.push(state_label(state.state()));
    }
    assert!(state.world.violations == 0, "{:?}", state.world);
    assert_eq!(
        expected.last().map(String::as_str),
        Some("aborted(t1 s5 r0)"),
        "{expected:?}"
    );
    let (report, calls) = replay(&plan, schedule_of(actions));
    let seen: Vec<String> = report
        .journal
        .records()
        .iter()
        .filter_map(|r| match &r.entry {
            stitch_engine::Entry::Transition { to, .. } => Some(to.clone()),
            _ => None,
        })
        .collect();
    assert_eq!(seen, expected);
    // insert (paused, resumed, done), sweep, extract (taken over past its commit: the
    // surgeon finishes it), cinch (taken over before it: run again), cinch, handover
    // (aborted past its commit).
    assert_eq!(
        calls,
        vec!["insert", "sweep", "extract", "cinch", "cinch", "handover"]
    );
}
