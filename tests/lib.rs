//! Shared helpers for the workspace-level tests: plan builders, proptest strategies, and a
//! scripted run that keeps everything the tests inspect.

use proptest::prelude::*;
use std::cell::Cell;
use std::rc::Rc;
use std::sync::Arc;
use stitch_engine::{
    CheckpointRequest, Cmp, Condition, End, InterventionRequest, InterventionResult, Moment,
    NextPoll, Node, Plan, Quantity, Report, Runner, ScriptedSupervisor, SourcePos, Step,
    Supervisor, SupervisorCommand, Target, Throw, TimedCommand, Unit,
};
use stitch_primitives::{
    Observation, ObserveRequest, PrimitiveError, Primitives, Scripted, ScriptedPrimitives,
    StepControl, StepKind, StepOutcome, StepRequest, Value,
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
        .map(|(&t, point)| {
            Throw::of_steps(
                point.clone(),
                template_steps(t, budgets),
                SourcePos::default(),
            )
        })
        .collect();
    Plan {
        name: "generated".into(),
        file: "generated.rhai".into(),
        interventions: budgets.interventions,
        thread_length_m: None,
        throws,
        pos: SourcePos::default(),
        params: Default::default(),
    }
}

/// The steps of template `t` with these budgets.
pub fn template_steps(t: usize, budgets: Budgets) -> Vec<Step> {
    TEMPLATES[t % TEMPLATES.len()]
        .iter()
        .map(|name| {
            let mut kind = StepKind::default_for(name).expect("a known step");
            let retries = match kind {
                StepKind::Extract(_) => Some(budgets.extract),
                StepKind::Handover(_) => Some(budgets.handover),
                StepKind::EstimateNeedle(_) | StepKind::TrackThread(_) => Some(budgets.perception),
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
        .collect()
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
    run_scripted_deciding(
        plan,
        outcomes,
        commands,
        interventions,
        Vec::new(),
        Vec::new(),
    )
}

/// [`run_scripted`], the plan's conditions taking `conditions` in order and its checkpoints
/// answered with `checkpoints`.
pub fn run_scripted_deciding(
    plan: Plan,
    outcomes: Vec<Scripted>,
    commands: Vec<TimedCommand>,
    interventions: Vec<InterventionResult>,
    conditions: Vec<bool>,
    checkpoints: Vec<SupervisorCommand>,
) -> Run {
    let clock = SimClock::new();
    let plan = Arc::new(plan);
    let calls = Rc::new(Cell::new(0));
    let mut primitives = Counted {
        inner: ScriptedPrimitives::from_schedule(outcomes, clock.clone())
            .with_conditions(conditions),
        calls: Rc::clone(&calls),
    };
    let mut supervisor = Noted {
        inner: ScriptedSupervisor::new(commands, interventions.clone())
            .with_checkpoints(checkpoints),
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
    fn run(&mut self, req: &StepRequest<'_>, control: &mut dyn StepControl) -> StepOutcome {
        self.calls.set(self.calls.get() + 1);
        self.inner.run(req, control)
    }
    fn observe(&mut self, req: &ObserveRequest<'_>) -> Observation {
        self.inner.observe(req)
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
    fn poll(&mut self, at: &Moment) -> Option<SupervisorCommand> {
        self.inner.poll(at)
    }
    fn next_poll(&self, at: &Moment) -> Option<NextPoll> {
        self.inner.next_poll(at)
    }
    fn source(&self) -> &str {
        self.inner.source()
    }
    fn wait(&mut self) -> Option<SupervisorCommand> {
        self.inner.wait()
    }
    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        self.at.push(self.calls.get());
        self.inner.intervene(request)
    }
    fn checkpoint(&mut self, request: &CheckpointRequest) -> Option<SupervisorCommand> {
        self.inner.checkpoint(request)
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
            .map(|(at, command)| TimedCommand::before(at, command))
            .collect()
    })
}

/// Supervisor commands at increasing times on the run's clock, s: most land in the middle of
/// a step (scripted steps take 15 s to 60 s), some between steps.
pub fn timed_commands(max: usize) -> impl Strategy<Value = Vec<TimedCommand>> {
    prop::collection::vec(
        (
            0.0f64..600.0,
            prop::sample::select(SupervisorCommand::ALL.to_vec()),
        ),
        0..=max,
    )
    .prop_map(|mut v| {
        v.sort_by(|a, b| a.0.total_cmp(&b.0));
        v.into_iter()
            .map(|(at_s, command)| TimedCommand::at_time(at_s, command))
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

/// Arbitrary conditions: every kind of quantity, comparison and combinator, nested.
pub fn condition() -> impl Strategy<Value = Condition> {
    let quantity = prop_oneof![
        Just(Quantity::NeedleConfidence),
        Just(Quantity::NeedleNormalAngle {
            to: [0.0, 1.0, 0.0]
        }),
        Just(Quantity::NeedleEndDistance {
            end: End::Tip,
            to: Target::RightJaw,
        }),
        Just(Quantity::NeedleEndDistance {
            end: End::Swage,
            to: Target::Point([0.0, 0.0, -0.12]),
        }),
        Just(Quantity::NeedleAge),
        Just(Quantity::ThreadLeft),
        Just(Quantity::ThrowNumber),
        Just(Quantity::InterventionsLeft),
        Just(Quantity::RetriesUsed),
    ];
    let cmp = prop::sample::select(vec![Cmp::Lt, Cmp::Le, Cmp::Gt, Cmp::Ge, Cmp::Eq, Cmp::Ne]);
    let leaf = prop_oneof![
        1 => Just(Condition::NeedleSeen),
        4 => (quantity, cmp, 0.0f64..4.0).prop_map(|(quantity, cmp, bound)| Condition::Compare {
            quantity,
            cmp,
            bound: if quantity.unit() == Unit::Count { bound.round() } else { bound * 0.01 },
        }),
    ];
    leaf.prop_recursive(3, 12, 3, |inner| {
        prop_oneof![
            prop::collection::vec(inner.clone(), 0..3).prop_map(|of| Condition::All { of }),
            prop::collection::vec(inner.clone(), 0..3).prop_map(|of| Condition::Any { of }),
            inner.prop_map(|c| Condition::Not { of: Box::new(c) }),
        ]
    })
}

/// How a generated throw wraps its template's steps.
#[derive(Clone, Debug)]
pub enum Shape {
    /// As they are.
    Plain,
    /// `when(c, [estimate_needle()]).otherwise([track_thread()])` first.
    WhenFirst(Condition),
    /// `repeat(#{ max, stop_when: c }, [estimate_needle()])` first (`c` optional).
    RepeatFirst(u8, Option<Condition>),
    /// `when(c, template).otherwise(other template)`: the whole throw in a branch.
    Branches(Condition, usize),
    /// A checkpoint first.
    Checkpoint,
}

/// Plans of 1 to 4 throws of templates in arbitrary constructs, with budgets from 0 to
/// beyond the caps. Every branch and loop body leaves the needle where it found it.
pub fn conditional_plans() -> impl Strategy<Value = Plan> {
    conditional_plans_with(9, 4)
}

/// [`conditional_plans`] with retries up to `max_retries` and interventions up to
/// `max_interventions` asked for.
pub fn conditional_plans_with(
    max_retries: u8,
    max_interventions: u8,
) -> impl Strategy<Value = Plan> {
    let shape = prop_oneof![
        1 => Just(Shape::Plain),
        2 => condition().prop_map(Shape::WhenFirst),
        2 => (1u8..=5, prop::option::of(condition())).prop_map(|(m, c)| Shape::RepeatFirst(m, c)),
        2 => (condition(), 0..TEMPLATES.len()).prop_map(|(c, t)| Shape::Branches(c, t)),
        1 => Just(Shape::Checkpoint),
    ];
    (
        prop::collection::vec((0..TEMPLATES.len(), shape), 1..=4),
        0u8..=max_retries,
        0u8..=max_retries,
        0u8..=max_retries,
        0u8..=max_interventions,
        prop::option::of(0.05f64..0.5),
    )
        .prop_map(
            |(throws, extract, handover, perception, interventions, thread)| {
                let budgets = Budgets {
                    extract,
                    handover,
                    perception,
                    interventions,
                };
                let templates: Vec<usize> = throws.iter().map(|(t, _)| *t).collect();
                let mut plan = plan_from(&templates, budgets);
                plan.thread_length_m = thread;
                for (throw, (t, shape)) in plan.throws.iter_mut().zip(throws) {
                    let steps = || {
                        template_steps(t, budgets)
                            .into_iter()
                            .map(Node::Step)
                            .collect::<Vec<_>>()
                    };
                    let query = |name: &str| {
                        let mut kind = StepKind::default_for(name).expect("a known step");
                        kind.set("retries", Value::Count(i64::from(budgets.perception)))
                            .expect("retries");
                        Node::Step(Step {
                            kind,
                            pos: SourcePos::default(),
                        })
                    };
                    let mut body = Vec::new();
                    match shape {
                        Shape::Plain => body = steps(),
                        Shape::WhenFirst(cond) => {
                            body.push(Node::When {
                                cond,
                                then: vec![query("estimate_needle")],
                                otherwise: vec![query("track_thread")],
                                pos: SourcePos::default(),
                            });
                            body.extend(steps());
                        }
                        Shape::RepeatFirst(max, until) => {
                            body.push(Node::Repeat {
                                max,
                                until,
                                body: vec![query("estimate_needle")],
                                pos: SourcePos::default(),
                            });
                            body.extend(steps());
                        }
                        Shape::Branches(cond, other) => body.push(Node::When {
                            cond,
                            then: steps(),
                            otherwise: template_steps(other, budgets)
                                .into_iter()
                                .map(Node::Step)
                                .collect(),
                            pos: SourcePos::default(),
                        }),
                        Shape::Checkpoint => {
                            body.push(Node::Checkpoint {
                                label: "go on".into(),
                                pos: SourcePos::default(),
                            });
                            body.extend(steps());
                        }
                    }
                    *throw = Throw::new(throw.point.clone(), body, SourcePos::default());
                }
                plan
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
