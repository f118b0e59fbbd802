//! Shared helpers for the workspace-level tests: plan builders, proptest strategies, and a
//! scripted run that keeps everything the tests inspect.

use proptest::prelude::*;
use std::cell::Cell;
use std::rc::Rc;
use std::sync::Arc;
use stitch_engine::{
    InterventionRequest, InterventionResult, Plan, Report, Runner, ScriptedSupervisor, SourcePos,
    Step, Supervisor, SupervisorCommand, Throw, TimedCommand,
};
use stitch_primitives::{
    PrimitiveError, Primitives, Scripted, ScriptedPrimitives, StepKind, StepOutcome, StepRequest,
    Value,
};
use stitch_robot::{SimClock, Wound, WoundSpec};

/// Step names of the paper's policies and a few perception-laden variants; each ends with the
/// needle back in the right jaw, so any sequence of them is a valid plan.
pub const TEMPLATES: &[&[&str]] = &[
    &["insert", "extract", "handover"],
    &["insert", "sweep", "extract", "cinch", "handover"],
    &["insert", "sweep", "extract", "cinch", "handover", "correct"],
    &[
        "estimate_needle",
        "insert",
        "track_thread",
        "sweep",
        "estimate_needle",
        "extract",
        "cinch",
        "estimate_needle",
        "handover",
        "correct",
        "estimate_needle",
    ],
];

/// Budgets a generated plan asks for; deliberately beyond the engine's caps at times.
#[derive(Clone, Copy, Debug)]
pub struct Budgets {
    /// Extraction retries asked for (0..=9).
    pub extract: u8,
    /// Handover re-attempts asked for (0..=9).
    pub handover: u8,
    /// Perception retries asked for (0..=9).
    pub perception: u8,
    /// Interventions asked for (0..=4).
    pub interventions: u8,
}

/// A plan of `templates` (indices into [`TEMPLATES`]), one throw each, with these budgets.
/// Built in Rust, not validated: budgets above the caps reach the machine as they are.
pub fn plan_from(templates: &[usize], budgets: Budgets) -> Plan {
    let spec = WoundSpec {
        count: templates.len().max(1),
        ..WoundSpec::default()
    };
    let wound = Wound::linear(&spec).expect("a valid wound spec");
    let throws = templates
        .iter()
        .zip(&wound.points)
        .map(|(&t, point)| Throw {
            point: point.clone(),
            steps: TEMPLATES[t % TEMPLATES.len()]
                .iter()
                .map(|name| {
                    let mut kind = StepKind::default_for(name).expect("a known step");
                    let retries = match kind {
                        StepKind::Extract(_) => Some(budgets.extract),
                        StepKind::Handover(_) => Some(budgets.handover),
                        StepKind::EstimateNeedle(_) | StepKind::TrackThread(_) => {
                            Some(budgets.perception)
                        }
                        _ => None,
                    };
                    if let Some(r) = retries {
                        kind.set("retries", Value::Count(i64::from(r)))
                            .expect("retries");
                    }
                    Step {
                        kind,
                        pos: SourcePos::default(),
                    }
                })
                .collect(),
            pos: SourcePos::default(),
        })
        .collect();
    Plan {
        name: "generated".into(),
        file: "generated.rhai".into(),
        interventions: budgets.interventions,
        throws,
        pos: SourcePos::default(),
    }
}

/// Everything a scripted run leaves for a test to inspect.
#[derive(Debug)]
pub struct Run {
    /// The plan that ran.
    pub plan: Arc<Plan>,
    /// What the runner reported.
    pub report: Report,
    /// The primitives, with every call and hold recorded.
    pub primitives: ScriptedPrimitives,
    /// The supervisor, with every intervention request recorded.
    pub supervisor: ScriptedSupervisor,
    /// The intervention results the schedule gave, in order.
    pub intervention_results: Vec<InterventionResult>,
    /// For each intervention request, how many step attempts the primitives had seen.
    pub intervention_after_calls: Vec<usize>,
}

impl Run {
    /// The result the n-th intervention request got.
    pub fn intervention_result(&self, n: usize) -> InterventionResult {
        self.intervention_results
            .get(n)
            .copied()
            .unwrap_or(InterventionResult::Recovered)
    }
}

/// Run `plan` on scripted primitives and a scripted supervisor.
pub fn run_scripted(
    plan: Plan,
    outcomes: Vec<Scripted>,
    commands: Vec<TimedCommand>,
    interventions: Vec<InterventionResult>,
) -> Run {
    let clock = SimClock::new();
    let plan = Arc::new(plan);
    let calls = Rc::new(Cell::new(0));
    let mut primitives = Counted {
        inner: ScriptedPrimitives::from_schedule(outcomes, clock.clone()),
        calls: Rc::clone(&calls),
    };
    let mut supervisor = Noted {
        inner: ScriptedSupervisor::new(commands, interventions.clone()),
        calls,
        at: Vec::new(),
    };
    let report = Runner::new(
        Arc::clone(&plan),
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        None,
    )
    .run();
    Run {
        plan,
        report,
        primitives: primitives.inner,
        supervisor: supervisor.inner,
        intervention_results: interventions,
        intervention_after_calls: supervisor.at,
    }
}

/// Counts the step attempts the engine asks for, so the supervisor wrapper can note when an
/// intervention came relative to them.
struct Counted {
    inner: ScriptedPrimitives,
    calls: Rc<Cell<usize>>,
}

impl Primitives for Counted {
    fn run(&mut self, req: &StepRequest<'_>) -> StepOutcome {
        self.calls.set(self.calls.get() + 1);
        self.inner.run(req)
    }
    fn hold_all(&mut self) -> Result<(), PrimitiveError> {
        self.inner.hold_all()
    }
}

/// Notes, for each intervention, how many attempts had been made before it.
struct Noted {
    inner: ScriptedSupervisor,
    calls: Rc<Cell<usize>>,
    at: Vec<usize>,
}

impl Supervisor for Noted {
    fn poll(&mut self, attempts: usize) -> Option<SupervisorCommand> {
        self.inner.poll(attempts)
    }
    fn wait(&mut self) -> Option<SupervisorCommand> {
        self.inner.wait()
    }
    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        self.at.push(self.calls.get());
        self.inner.intervene(request)
    }
}

/// Outcome tokens, weighted so that retries get exhausted and every failure kind appears.
pub fn token() -> impl Strategy<Value = Scripted> {
    prop_oneof![
        6 => Just(Scripted::Ok),
        4 => Just(Scripted::NoProgress),
        1 => Just(Scripted::Fail),
        1 => Just(Scripted::Thread),
        2 => Just(Scripted::Dropout),
        1 => Just(Scripted::Dropped),
        1 => Just(Scripted::Fault),
    ]
}

/// Supervisor commands at increasing attempt counts.
pub fn commands(max: usize) -> impl Strategy<Value = Vec<TimedCommand>> {
    prop::collection::vec(
        (
            0usize..60,
            prop::sample::select(SupervisorCommand::ALL.to_vec()),
        ),
        0..=max,
    )
    .prop_map(|mut v| {
        v.sort_by_key(|(at, _)| *at);
        v.into_iter()
            .map(|(at, command)| TimedCommand { at, command })
            .collect()
    })
}

/// Intervention results.
pub fn interventions() -> impl Strategy<Value = Vec<InterventionResult>> {
    prop::collection::vec(
        prop_oneof![3 => Just(InterventionResult::Recovered), 1 => Just(InterventionResult::Failed)],
        0..4,
    )
}

/// Plans of 1 to 6 throws with budgets from 0 to beyond the caps.
pub fn plans() -> impl Strategy<Value = Plan> {
    (
        prop::collection::vec(0..TEMPLATES.len(), 1..=6),
        0u8..=9,
        0u8..=9,
        0u8..=9,
        0u8..=4,
    )
        .prop_map(
            |(templates, extract, handover, perception, interventions)| {
                plan_from(
                    &templates,
                    Budgets {
                        extract,
                        handover,
                        perception,
                        interventions,
                    },
                )
            },
        )
}

/// Cases per property: `STITCH_PROPTEST_CASES` if set, else `default`.
pub fn cases(default: u32) -> u32 {
    std::env::var("STITCH_PROPTEST_CASES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(default)
}
