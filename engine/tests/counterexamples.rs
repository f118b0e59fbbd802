//! Every counterexample the explorer has found, kept: `tests/counterexamples/NAME.rhai` is the
//! plan (its first line names the property, `// property: NAME`) and `NAME.json` the outcome
//! schedule `stitch check --explore --counterexample` wrote. The explorer must still find
//! exactly that shortest counterexample, and the runner must still follow it.

use std::path::Path;
use std::sync::Arc;
use stitch_engine::{ExploreOptions, OutcomeSchedule, PlanLoader, Runner, ScriptLimits, explore};
use stitch_robot::{SimClock, Wound, WoundSpec};

#[test]
fn every_committed_counterexample_is_still_found_and_replays() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/counterexamples");
    let loader = PlanLoader::new(
        &Wound::linear(&WoundSpec::default()).expect("wound"),
        ScriptLimits::default(),
    );
    let mut checked = 0;
    let mut entries: Vec<_> = std::fs::read_dir(&dir)
        .expect("the directory")
        .flatten()
        .collect();
    entries.sort_by_key(|e| e.path());
    for entry in entries {
        let path = entry.path();
        if path.extension().and_then(|e| e.to_str()) != Some("rhai") {
            continue;
        }
        let source = std::fs::read_to_string(&path).expect("plan");
        let property = source
            .lines()
            .next()
            .and_then(|l| l.strip_prefix("// property: "))
            .unwrap_or_else(|| panic!("{}: first line must be `// property: NAME`", path.display()))
            .trim()
            .to_string();
        let expected = OutcomeSchedule::read(&path.with_extension("json")).expect("schedule");
        let plan = loader
            .eval_str(&path.display().to_string(), &source)
            .expect("evaluates")
            .plan;

        let found = explore(Arc::new(plan.clone()), ExploreOptions::default());
        let verdict = found
            .verdicts
            .iter()
            .find(|v| v.name == property)
            .unwrap_or_else(|| panic!("{}: no property `{property}`", path.display()));
        assert!(!verdict.holds, "{}: `{property}` now holds", path.display());
        assert_eq!(
            verdict.schedule.as_ref(),
            Some(&expected),
            "{}",
            path.display()
        );

        let clock = SimClock::new();
        let steps = expected.outcomes.len();
        let (mut primitives, mut supervisor) = expected.into_parts(clock.clone());
        let report = Runner::new(
            Arc::new(plan),
            &mut primitives,
            &mut supervisor,
            Arc::new(clock),
            None,
        )
        .run();
        assert_eq!(
            primitives.calls.len(),
            steps,
            "{}: the replay takes the same steps",
            path.display()
        );
        assert!(matches!(
            report.outcome,
            stitch_engine::RunOutcome::Aborted { .. }
        ));
        checked += 1;
    }
    assert!(
        checked >= 2,
        "found only {checked} counterexamples in {}",
        dir.display()
    );
}
