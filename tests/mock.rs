//! Missions on the mock dVRK: the real primitives, the mock's physics.

use std::sync::Arc;
use stitch_engine::{
    PlanLoader, Report, RunOutcome, Runner, ScriptLimits, ScriptedSupervisor, load_plan,
};
use stitch_primitives::mock_primitives;
use stitch_robot::{SimClock, Wound};
use stitch_sim::{SceneConfig, SensingConfig, ThreadConfig};

fn run(script: &str, scene: &SceneConfig, sensing: SensingConfig, seed: u64) -> Report {
    let wound = Wound::linear(&scene.wound).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scripts")
        .join(script);
    let plan = load_plan(&loader, &path)
        .unwrap_or_else(|e| panic!("{e}"))
        .plan;
    let clock = SimClock::new();
    let (mut primitives, _world) =
        mock_primitives(scene, sensing, seed, clock.clone()).expect("mock");
    let mut supervisor = ScriptedSupervisor::default();
    Runner::new(
        Arc::new(plan),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        Some(seed),
    )
    .run()
}

/// A thread that never gets in the way.
fn tame_thread() -> ThreadConfig {
    ThreadConfig {
        p_across_after_insert: 0.0,
        p_tangle_per_cinch: 0.0,
        ..ThreadConfig::default()
    }
}

#[test]
fn perfect_perception_and_no_faults_sutures_all_six_throws() {
    let scene = SceneConfig {
        thread: tame_thread(),
        ..SceneConfig::default()
    };
    let report = run("stitch.rhai", &scene, SensingConfig::perfect(), 1);
    for (i, t) in report.throws.iter().enumerate() {
        eprintln!(
            "throw {}: {:?}",
            i + 1,
            t.attempts
                .iter()
                .map(|a| (a.primitive, &a.outcome))
                .collect::<Vec<_>>()
        );
    }
    assert_eq!(
        report.outcome,
        RunOutcome::Completed,
        "{:?}",
        report.outcome
    );
}
