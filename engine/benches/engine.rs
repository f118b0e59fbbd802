//! Loading + validating the STITCH plan, and one state-machine dispatch.
//!
//! `cargo bench -p stitch-engine --bench engine`

use criterion::{BatchSize, Criterion, criterion_group, criterion_main};
use statig::blocking::IntoStateMachineExt;
use std::hint::black_box;
use std::sync::Arc;
use stitch_engine::{Ctx, Event, Mission, PlanLoader, ScriptLimits, load_plan_str};
use stitch_primitives::StepOutcome;
use stitch_robot::{Wound, WoundSpec};

fn benches(c: &mut Criterion) {
    let wound = Wound::linear(&WoundSpec::default()).expect("default wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../scripts/stitch.rhai");
    let source = std::fs::read_to_string(path).expect("scripts/stitch.rhai");

    c.bench_function("load_and_validate_stitch_rhai", |b| {
        b.iter(|| load_plan_str(&loader, "stitch.rhai", black_box(&source)).expect("valid"))
    });

    let plan = Arc::new(
        load_plan_str(&loader, "stitch.rhai", &source)
            .expect("valid")
            .plan,
    );
    let mut ctx = Ctx::default();
    let mut machine = Mission::new(plan)
        .uninitialized_state_machine()
        .init_with_context(&mut ctx);
    machine.handle_with_context(&Event::Start, &mut ctx); // now in `inserting`
    let success = Event::StepFinished(StepOutcome::ok());
    c.bench_function("dispatch_step_success", |b| {
        b.iter_batched_ref(
            || (machine.clone(), Ctx::default()),
            |(m, ctx)| m.handle_with_context(black_box(&success), ctx),
            BatchSize::SmallInput,
        )
    });
}

criterion_group!(engine, benches);
criterion_main!(engine);
