//! Exhaustive exploration of a plan through the real state machine: a stateright model whose
//! states wrap the engine's own [`Mission`] machine, with every step outcome, supervisor
//! command and intervention result a nondeterministic choice.
//!
//! The machine decides everything the engine decides; the model adds only what the engine
//! cannot see: an abstract world (where the needle is), the supervisor's choices, and the
//! checks of the properties below, each computed here from what the machine was asked to do,
//! not from its own counters.
//!
//! Termination is checked soundly: stateright's `eventually` ignores cycles, so the model also
//! checks that every transition not caused by the supervisor strictly increases a progress
//! rank (step index, then retries + interventions, then intervention → re-run), and bounds the
//! supervisor's commands per path. Together they make every path finite.

use crate::machine::{
    Ctx, Cursor, Effect, Event, Interrupted, Mission, Pending, State, pending, state_parts,
};
use crate::plan::{NeedleHolder, Op, Plan, caps};
use crate::schedule::OutcomeSchedule;
use crate::supervisor::{InStep, InterventionResult, SupervisorCommand, TimedCommand};
use stateright::{Checker, Model, Property};
use statig::blocking::{InitializedStateMachine, IntoStateMachineExt};
use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fmt;
use std::hash::{Hash, Hasher};
use std::sync::Arc;
use std::time::{Duration, Instant};
use stitch_primitives::{
    Failure, FailureKind, Measurements, SCRIPTED_TOKENS, Scripted, StepKind, StepOutcome,
};

/// Where the needle is, in the model's abstract world.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Needle {
    /// Held by the right (inserting) jaw.
    Right,
    /// In the tissue, held by neither jaw.
    Tissue,
    /// Held by the left (extracting) jaw.
    Left,
    /// Fallen.
    Dropped,
}

impl From<NeedleHolder> for Needle {
    fn from(h: NeedleHolder) -> Self {
        match h {
            NeedleHolder::Right => Needle::Right,
            NeedleHolder::Tissue => Needle::Tissue,
            NeedleHolder::Left => Needle::Left,
        }
    }
}

/// A property the model checks.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Violation {
    /// An extraction was retried more than 5 times, or more than the plan asked.
    ExtractionRetries,
    /// A handover was re-attempted more than 5 times, or more than the plan asked.
    HandoverRetries,
    /// Another step was retried beyond its cap.
    OtherRetries,
    /// More interventions than the plan's budget, or than 2.
    Interventions,
    /// An insertion began without the needle in the right (inserting) jaw.
    InsertWithoutNeedle,
    /// A jaw holding the needle opened while the other jaw did not hold it and it was not in
    /// the tissue.
    OpenedJawHoldingNeedle,
    /// A step began without the needle where it needs it.
    NeedleNotWhereNeeded,
    /// A step was attempted after an abort or e-stop.
    MotionAfterStop,
    /// An abort or e-stop did not make the arms hold.
    NoHoldAfterStop,
    /// A transition the supervisor did not cause made no progress (a possible cycle).
    NoProgress,
    /// A pause or take-over did not make the arms hold.
    NoHoldOnInterrupt,
    /// A supervisor command alone spent a retry or an intervention.
    BudgetByCommand,
}

impl Violation {
    fn bit(self) -> u16 {
        1 << (self as u16)
    }
}

/// The abstract world and the property bookkeeping, beside the machine.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub struct World {
    /// Where the needle is.
    pub needle: Needle,
    /// Supervisor commands given on this path.
    pub commands: u8,
    /// Whether an abort or e-stop was acted on.
    pub stopped: bool,
    /// The step the last attempt was at, `(throw, step)`.
    pub step: Option<(usize, usize)>,
    /// Attempts at that step since it began or since the last recovered intervention.
    pub attempts: u8,
    /// Interventions the machine asked for on this path.
    pub interventions: u8,
    /// Properties violated on this path (bits of [`Violation`]).
    pub violations: u16,
}

impl World {
    fn violate(&mut self, v: Violation) {
        self.violations |= v.bit();
    }

    /// Whether `v` was violated on the way here.
    pub fn violated(&self, v: Violation) -> bool {
        self.violations & v.bit() != 0
    }
}

/// One state of the model: the engine's machine and the world beside it.
#[derive(Clone)]
pub struct ExploreState {
    machine: InitializedStateMachine<Mission>,
    /// The world.
    pub world: World,
}

impl ExploreState {
    /// The machine's state.
    pub fn state(&self) -> &State {
        self.machine.state()
    }

    /// Whether the run is over.
    pub fn is_terminal(&self) -> bool {
        pending(self.machine.state()) == Pending::Done
    }

    fn key(&self) -> (&State, crate::machine::Counters, &World) {
        (
            self.machine.state(),
            self.machine.inner().counters(),
            &self.world,
        )
    }
}

impl fmt::Debug for ExploreState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("ExploreState")
            .field("state", &crate::machine::state_label(self.machine.state()))
            .field(
                "interventions_used",
                &self.machine.inner().interventions_used(),
            )
            .field("world", &self.world)
            .finish()
    }
}

// The machine's behaviour depends only on its state and its counters (the plan is shared by
// all states), so those and the world identify a model state.
impl Hash for ExploreState {
    fn hash<H: Hasher>(&self, h: &mut H) {
        self.key().hash(h);
    }
}

impl PartialEq for ExploreState {
    fn eq(&self, other: &Self) -> bool {
        self.key() == other.key()
    }
}

impl Eq for ExploreState {}

/// A nondeterministic choice.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum Action {
    /// The next step attempt ends so.
    Attempt(Scripted),
    /// The supervisor gives a command (before an attempt, or while paused or taken over).
    Command(SupervisorCommand),
    /// The supervisor gives a command in the middle of the attempt, its motion stopped there:
    /// before the step's commit point, or (`true`) past it.
    Interrupt(SupervisorCommand, bool),
    /// The requested intervention ends so.
    Intervention(InterventionResult),
    /// The supervisor is gone while the run waits for a command.
    SupervisorGone,
    /// The plan's condition has this value.
    Decide(bool),
    /// The robot cannot observe what the plan's condition reads (an arm or camera fault).
    Unobservable,
    /// The supervisor answers a checkpoint.
    Checkpoint(SupervisorCommand),
}

impl fmt::Display for Action {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Action::Attempt(t) => write!(f, "{t}"),
            Action::Command(c) => write!(f, "{c}"),
            Action::Interrupt(c, false) => write!(f, "{c} mid-step"),
            Action::Interrupt(c, true) => write!(f, "{c} mid-step (committed)"),
            Action::Intervention(InterventionResult::Recovered) => f.write_str("recovered"),
            Action::Intervention(InterventionResult::Failed) => f.write_str("intervention failed"),
            Action::SupervisorGone => f.write_str("supervisor gone"),
            Action::Decide(v) => write!(f, "condition {v}"),
            Action::Unobservable => f.write_str("condition unobservable"),
            Action::Checkpoint(c) => write!(f, "checkpoint: {c}"),
        }
    }
}

/// What the exploration may choose.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct ExploreOptions {
    /// The most supervisor commands on one path (each pause, resume, take-over, hand-back,
    /// abort or e-stop counts one).
    pub max_commands: u8,
    /// The step outcomes to branch on.
    pub outcomes: Vec<Scripted>,
}

impl Default for ExploreOptions {
    fn default() -> Self {
        Self {
            max_commands: 2,
            outcomes: SCRIPTED_TOKENS.to_vec(),
        }
    }
}

/// The engine as a stateright model, for one plan.
#[derive(Debug)]
pub struct EngineModel {
    plan: Arc<Plan>,
    holders: Vec<Vec<Option<NeedleHolder>>>,
    options: ExploreOptions,
}

impl EngineModel {
    /// A model of `plan`. The plan need not be valid: exploring an invalid one shows the paths
    /// on which its problems bite.
    pub fn new(plan: Arc<Plan>, options: ExploreOptions) -> Self {
        let holders = plan.holders();
        Self {
            plan,
            holders,
            options,
        }
    }

    /// The plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// Where the step at `c` needs the needle (perception queries need nothing).
    fn needs(kind: &StepKind) -> Option<Needle> {
        match kind {
            StepKind::Insert(_) | StepKind::Correct(_) => Some(Needle::Right),
            StepKind::Sweep(_) | StepKind::Extract(_) => Some(Needle::Tissue),
            StepKind::Cinch(_) | StepKind::Handover(_) => Some(Needle::Left),
            StepKind::EstimateNeedle(_) | StepKind::TrackThread(_) => None,
        }
    }

    /// Whether the step has a commit point (what it does to the needle, tissue or thread
    /// cannot be undone by running it again from there).
    fn commits(kind: &StepKind) -> bool {
        matches!(
            kind,
            StepKind::Insert(_) | StepKind::Extract(_) | StepKind::Cinch(_) | StepKind::Handover(_)
        )
    }

    /// Where a step that succeeds leaves the needle that was at `before`.
    fn effect(kind: &StepKind, before: Needle) -> Needle {
        match (kind, before) {
            // Insertion ends with the right jaw opening around a needle now in the tissue.
            (StepKind::Insert(_), _) => Needle::Tissue,
            (StepKind::Extract(_), Needle::Tissue) => Needle::Left,
            // The right jaw closes on the needle, then the left opens: the right holds it.
            (StepKind::Handover(_), Needle::Left) => Needle::Right,
            (_, n) => n,
        }
    }

    /// The model's physics for one attempt: checks what the step does with the jaws, and
    /// where the needle ends up.
    fn attempt(&self, world: &mut World, kind: &StepKind, token: Scripted) {
        let before = world.needle;
        if let Some(needed) = Self::needs(kind) {
            if before != needed {
                world.violate(Violation::NeedleNotWhereNeeded);
            }
        }
        match kind {
            StepKind::Insert(_) if before != Needle::Right => {
                world.violate(Violation::InsertWithoutNeedle);
            }
            // The sweep opens the right jaw wide: if it held the needle, the needle falls.
            StepKind::Sweep(_) if before == Needle::Right => {
                world.violate(Violation::OpenedJawHoldingNeedle);
                world.needle = Needle::Dropped;
                return;
            }
            _ => {}
        }
        if before == Needle::Dropped || token != Scripted::Ok {
            if token == Scripted::Dropped {
                world.needle = Needle::Dropped;
            }
            // A failed attempt leaves the needle where it was: a missed insertion is pulled
            // back still held, a grasp that did not take reopens a jaw that held nothing, an
            // extraction that made no progress reopens the left jaw around a needle that is
            // still in the tissue.
            return;
        }
        world.needle = Self::effect(kind, before);
    }

    /// Progress rank of a state; `None` for states the supervisor alone leaves.
    fn rank(&self, s: &State, interventions: u8) -> Option<(usize, u32, u8)> {
        let global = |c: &Cursor| {
            self.plan.throws[..c.throw.min(self.plan.throws.len())]
                .iter()
                .map(|t| t.program.len())
                .sum::<usize>()
                + c.step
        };
        match pending(s) {
            Pending::Attempt(c) => Some((
                global(&c),
                u32::from(c.retries) + u32::from(interventions),
                1,
            )),
            Pending::Intervention(c, _) => Some((
                global(&c),
                u32::from(c.retries) + u32::from(interventions),
                0,
            )),
            Pending::Decide(c) => Some((
                global(&c),
                u32::from(c.retries) + u32::from(interventions),
                1,
            )),
            Pending::Start => Some((0, 0, 0)),
            Pending::Command(_) | Pending::Checkpoint(_) | Pending::Done => None,
        }
    }

    /// The retry cap the model holds a step to: the engine's hard cap and the plan's ask.
    fn allowed_retries(kind: &StepKind) -> Option<(u8, Violation)> {
        let asked = kind.retries()?;
        let (cap, v) = match kind {
            StepKind::Extract(_) => (caps::EXTRACT_RETRIES, Violation::ExtractionRetries),
            StepKind::Handover(_) => (caps::HANDOVER_RETRIES, Violation::HandoverRetries),
            _ => (caps::PERCEPTION_RETRIES, Violation::OtherRetries),
        };
        Some((asked.min(cap), v))
    }

    /// The world after a command lands mid-step: the arms hold at once; an abort stops
    /// everything; a take-over past the step's commit point leaves the step to the surgeon,
    /// who finishes it (the hand-back goes on with the step after it).
    fn interrupted(
        &self,
        s: &mut ExploreState,
        kind: &StepKind,
        command: SupervisorCommand,
        committed: bool,
        effects: &[Effect],
    ) {
        let holds = effects.contains(&Effect::HoldArms);
        match (command, s.machine.state()) {
            (SupervisorCommand::Abort | SupervisorCommand::EStop, State::Aborted { .. }) => {
                s.world.stopped = true;
                if !holds {
                    s.world.violate(Violation::NoHoldAfterStop);
                }
            }
            (SupervisorCommand::Pause, State::Paused { .. }) => {
                if !holds {
                    s.world.violate(Violation::NoHoldOnInterrupt);
                }
            }
            (SupervisorCommand::TakeOver, State::TakenOver { .. }) => {
                if !holds {
                    s.world.violate(Violation::NoHoldOnInterrupt);
                }
                if committed {
                    s.world.needle = Self::effect(kind, s.world.needle);
                }
            }
            // Any other landing of a stopping command mid-step leaves the motion running.
            _ => s.world.violate(Violation::NoHoldOnInterrupt),
        }
    }

    fn dispatch(machine: &mut InitializedStateMachine<Mission>, event: Event) -> Vec<Effect> {
        let mut ctx = Ctx::default();
        machine.handle_with_context(&event, &mut ctx);
        ctx.effects
    }
}

impl Model for EngineModel {
    type State = ExploreState;
    type Action = Action;

    fn init_states(&self) -> Vec<ExploreState> {
        let mut ctx = Ctx::default();
        let mut machine = Mission::new(Arc::clone(&self.plan))
            .uninitialized_state_machine()
            .init_with_context(&mut ctx);
        machine.handle_with_context(&Event::Start, &mut ctx);
        let world = World {
            needle: Needle::Right,
            commands: 0,
            stopped: false,
            step: None,
            attempts: 0,
            interventions: 0,
            violations: 0,
        };
        vec![ExploreState { machine, world }]
    }

    fn actions(&self, s: &ExploreState, actions: &mut Vec<Action>) {
        let more_commands = s.world.commands < self.options.max_commands;
        match pending(s.machine.state()) {
            Pending::Done | Pending::Start => {}
            Pending::Attempt(c) => {
                actions.extend(self.options.outcomes.iter().map(|t| Action::Attempt(*t)));
                if more_commands {
                    const STOPPING: [SupervisorCommand; 4] = [
                        SupervisorCommand::Pause,
                        SupervisorCommand::TakeOver,
                        SupervisorCommand::Abort,
                        SupervisorCommand::EStop,
                    ];
                    actions.extend(STOPPING.map(Action::Command));
                    // Mid-step: before the commit point, and past it where the step has one.
                    let commits = s.machine.inner().step_kind(c).is_some_and(Self::commits);
                    for committed in [false, true] {
                        if committed && !commits {
                            continue;
                        }
                        actions.extend(STOPPING.map(|k| Action::Interrupt(k, committed)));
                    }
                }
            }
            Pending::Intervention(..) => {
                actions.push(Action::Intervention(InterventionResult::Recovered));
                actions.push(Action::Intervention(InterventionResult::Failed));
            }
            Pending::Decide(c) => {
                let mission = s.machine.inner();
                let known = match mission.op(c) {
                    Some(Op::Branch { cond, .. }) => cond.eval_known(&mission.facts(c)),
                    _ => Some(false),
                };
                match known {
                    Some(v) => actions.push(Action::Decide(v)),
                    None => actions.extend([
                        Action::Decide(true),
                        Action::Decide(false),
                        Action::Unobservable,
                    ]),
                }
            }
            Pending::Checkpoint(_) => {
                // Go is always possible, so a path never stalls at the command bound.
                actions.push(Action::Checkpoint(SupervisorCommand::Go));
                if more_commands {
                    actions.extend(
                        [
                            SupervisorCommand::TakeOver,
                            SupervisorCommand::Abort,
                            SupervisorCommand::EStop,
                        ]
                        .map(Action::Checkpoint),
                    );
                }
                actions.push(Action::SupervisorGone);
            }
            Pending::Command(_) => {
                let paused = matches!(s.machine.state(), State::Paused { .. });
                // Going on is always possible, so a path never stalls at the command bound.
                actions.push(Action::Command(if paused {
                    SupervisorCommand::Resume
                } else {
                    SupervisorCommand::HandBack
                }));
                if more_commands {
                    if paused {
                        actions.push(Action::Command(SupervisorCommand::TakeOver));
                    }
                    actions.push(Action::Command(SupervisorCommand::Abort));
                    actions.push(Action::Command(SupervisorCommand::EStop));
                }
                actions.push(Action::SupervisorGone);
            }
        }
    }

    fn next_state(&self, last: &ExploreState, action: Action) -> Option<ExploreState> {
        let mut s = last.clone();
        let before = s.machine.state().clone();
        let rank_before = self.rank(&before, s.machine.inner().interventions_used());
        let mut by_supervisor = false;
        match (pending(&before), action) {
            (Pending::Attempt(c), Action::Attempt(token)) => {
                if s.world.stopped {
                    s.world.violate(Violation::MotionAfterStop);
                }
                let kind = *last.machine.inner().step_kind(c)?;
                if s.world.step != Some((c.throw, c.step)) {
                    s.world.step = Some((c.throw, c.step));
                    s.world.attempts = 0;
                }
                s.world.attempts = s.world.attempts.saturating_add(1);
                if let Some((allowed, v)) = Self::allowed_retries(&kind) {
                    if s.world.attempts - 1 > allowed {
                        s.world.violate(v);
                    }
                } else if s.world.attempts > 1 {
                    s.world.violate(Violation::OtherRetries);
                }
                self.attempt(&mut s.world, &kind, token);
                let outcome = token.outcome_for(&kind, c.throw + 1);
                Self::dispatch(&mut s.machine, Event::StepFinished(outcome));
            }
            (Pending::Decide(_), Action::Decide(v)) => {
                if s.world.stopped {
                    s.world.violate(Violation::MotionAfterStop);
                }
                Self::dispatch(&mut s.machine, Event::Decided(v));
            }
            (Pending::Decide(_), Action::Unobservable) => {
                if s.world.stopped {
                    s.world.violate(Violation::MotionAfterStop);
                }
                let failure = Failure {
                    kind: FailureKind::ArmFault {
                        message: "unobservable".into(),
                    },
                    measured: Measurements::default(),
                };
                Self::dispatch(
                    &mut s.machine,
                    Event::StepFinished(StepOutcome::Failed(failure)),
                );
            }
            (Pending::Attempt(c), Action::Interrupt(command, committed)) => {
                by_supervisor = true;
                if s.world.stopped {
                    s.world.violate(Violation::MotionAfterStop);
                }
                s.world.commands = s.world.commands.saturating_add(1);
                let effects =
                    Self::dispatch(&mut s.machine, Event::Interrupt { command, committed });
                let kind = *last.machine.inner().step_kind(c)?;
                self.interrupted(&mut s, &kind, command, committed, &effects);
            }
            (Pending::Attempt(_) | Pending::Command(_), Action::Command(command))
            | (Pending::Checkpoint(_), Action::Checkpoint(command)) => {
                by_supervisor = true;
                if command != SupervisorCommand::Go {
                    s.world.commands = s.world.commands.saturating_add(1);
                }
                // A take-over while paused past a step's commit point: the surgeon finishes
                // the step (the hand-back goes on with the one after it).
                if let (
                    State::Paused {
                        cursor,
                        at: Interrupted::Committed,
                    },
                    SupervisorCommand::TakeOver,
                ) = (&before, command)
                {
                    if let Some(kind) = last.machine.inner().step_kind(*cursor) {
                        s.world.needle = Self::effect(kind, s.world.needle);
                    }
                }
                let effects = Self::dispatch(&mut s.machine, Event::Supervisor(command));
                if matches!(command, SupervisorCommand::Abort | SupervisorCommand::EStop)
                    && matches!(s.machine.state(), State::Aborted { .. })
                {
                    s.world.stopped = true;
                    if !effects.contains(&Effect::HoldArms) {
                        s.world.violate(Violation::NoHoldAfterStop);
                    }
                }
            }
            (Pending::Command(_) | Pending::Checkpoint(_), Action::SupervisorGone) => {
                by_supervisor = true;
                Self::dispatch(&mut s.machine, Event::SupervisorLost);
            }
            (Pending::Intervention(c, _), Action::Intervention(result)) => {
                if result == InterventionResult::Recovered {
                    // The surgeon returns the workspace to a safe configuration: the needle
                    // where the failed step needs it, the step's attempts counted afresh.
                    let needed = last
                        .machine
                        .inner()
                        .step_kind(c)
                        .and_then(Self::needs)
                        .or_else(|| {
                            let h = self.holders.get(c.throw)?.get(c.step).copied().flatten()?;
                            Some(h.into())
                        });
                    s.world.needle = needed.unwrap_or(Needle::Right);
                    s.world.attempts = 0;
                }
                Self::dispatch(&mut s.machine, Event::InterventionFinished(result));
            }
            _ => return None,
        }
        let after = s.machine.state();
        if matches!(after, State::AwaitingIntervention { .. })
            && !matches!(before, State::AwaitingIntervention { .. })
        {
            s.world.interventions = s.world.interventions.saturating_add(1);
        }
        let budget = self.plan.interventions.min(caps::INTERVENTIONS);
        if s.world.interventions > budget {
            s.world.violate(Violation::Interventions);
        }
        if by_supervisor {
            // A command alone never spends a retry or an intervention.
            let used = |m: &InitializedStateMachine<Mission>| m.inner().interventions_used();
            let retries = |st: &State| state_parts(st).1.map(|c| (c.throw, c.step, c.retries));
            let spent_retry = match (retries(&before), retries(after)) {
                (Some((t0, s0, r0)), Some((t1, s1, r1))) => (t0, s0) == (t1, s1) && r1 > r0,
                _ => false,
            };
            if used(&s.machine) > used(&last.machine) || spent_retry {
                s.world.violate(Violation::BudgetByCommand);
            }
        }
        if !by_supervisor {
            let rank_after = self.rank(after, s.machine.inner().interventions_used());
            let progressed = match (rank_before, rank_after) {
                (_, None) => true, // terminal (or waiting on the supervisor)
                (Some(a), Some(b)) => b > a,
                (None, Some(_)) => true,
            };
            if !progressed {
                s.world.violate(Violation::NoProgress);
            }
        }
        Some(s)
    }

    fn properties(&self) -> Vec<Property<Self>> {
        fn ok(s: &ExploreState, v: Violation) -> bool {
            !s.world.violated(v)
        }
        vec![
            Property::always("extraction retries", |_, s| {
                ok(s, Violation::ExtractionRetries)
            }),
            Property::always("handover re-attempts", |_, s| {
                ok(s, Violation::HandoverRetries)
            }),
            Property::always("perception retries", |_, s| ok(s, Violation::OtherRetries)),
            Property::always("interventions", |_, s| ok(s, Violation::Interventions)),
            Property::always("insert holds needle", |_, s| {
                ok(s, Violation::InsertWithoutNeedle)
            }),
            Property::always("jaw opening", |_, s| {
                ok(s, Violation::OpenedJawHoldingNeedle)
            }),
            Property::always("needle where needed", |_, s| {
                ok(s, Violation::NeedleNotWhereNeeded)
            }),
            Property::always("motion after stop", |_, s| {
                ok(s, Violation::MotionAfterStop)
            }),
            Property::always("hold after stop", |_, s| ok(s, Violation::NoHoldAfterStop)),
            Property::always("hold on interrupt", |_, s| {
                ok(s, Violation::NoHoldOnInterrupt)
            }),
            Property::always("no budget by command", |_, s| {
                ok(s, Violation::BudgetByCommand)
            }),
            Property::always("progress", |_, s| ok(s, Violation::NoProgress)),
            Property::eventually(
                "ends completed, failed or aborted",
                |_, s: &ExploreState| s.is_terminal(),
            ),
            Property::sometimes("completed is reachable", |_, s: &ExploreState| {
                matches!(s.state(), State::Completed {})
            }),
        ]
    }
}

/// The stateright property names, in the order of [`Model::properties`], with the words the
/// report uses.
pub const PROPERTY_NAMES: [(&str, &str); 14] = [
    (
        "extraction retries",
        "extraction retries ≤ 5 (and ≤ the plan's)",
    ),
    (
        "handover re-attempts",
        "handover re-attempts ≤ 5 (and ≤ the plan's)",
    ),
    (
        "perception retries",
        "perception retries ≤ 5 (and ≤ the plan's)",
    ),
    ("interventions", "interventions ≤ the plan's budget ≤ 2"),
    (
        "insert holds needle",
        "never insert unless the inserting jaw holds the needle",
    ),
    (
        "jaw opening",
        "never open a jaw holding the needle unless the other jaw holds it or it is in tissue",
    ),
    (
        "needle where needed",
        "every step finds the needle where it needs it",
    ),
    ("motion after stop", "no motion after abort or e-stop"),
    ("hold after stop", "abort and e-stop make the arms hold"),
    (
        "hold on interrupt",
        "a pause or take-over, mid-step too, makes the arms hold",
    ),
    (
        "no budget by command",
        "no supervisor command alone spends a retry or an intervention",
    ),
    (
        "progress",
        "every engine transition makes progress (no cycles)",
    ),
    (
        "ends completed, failed or aborted",
        "every path ends in completed, failed or aborted",
    ),
    ("completed is reachable", "completed is reachable"),
];

/// One property's verdict.
#[derive(Clone, Debug, PartialEq)]
pub struct Verdict {
    /// The stateright property name.
    pub name: &'static str,
    /// What it says.
    pub says: &'static str,
    /// Whether it holds (for "reachable": whether an example was found).
    pub holds: bool,
    /// The shortest path that breaks it (for "reachable": that shows it), if any.
    pub path: Option<Vec<(String, Action)>>,
    /// That path as an outcome schedule to replay.
    pub schedule: Option<OutcomeSchedule>,
}

/// What an exploration found.
#[derive(Clone, Debug)]
pub struct Exploration {
    /// One verdict per property.
    pub verdicts: Vec<Verdict>,
    /// Unique states stateright's checker visited.
    pub states: usize,
    /// Unique states the counterexample pass visited (the same states, counted again).
    pub graph_states: usize,
    /// Complete paths from the start to an end (saturating).
    pub paths: u128,
    /// The farthest state from the start, in choices on its shortest path.
    pub max_depth: usize,
    /// Wall-clock time the exploration took.
    pub elapsed: Duration,
    /// State-to-state transitions seen, by state name, with the choices that caused them.
    pub edges: BTreeMap<(&'static str, &'static str), BTreeSet<String>>,
}

impl Exploration {
    /// Whether every safety property holds, every path ends, and completion is reachable.
    pub fn all_hold(&self) -> bool {
        self.verdicts.iter().all(|v| v.holds)
    }
}

/// Explore every branch of `plan`: stateright's breadth-first checker decides each property
/// and counts the states; a second, single-threaded breadth-first pass over the same model
/// finds the shortest counterexample of each failed property (stateright keeps the last path
/// it found, not the first), counts the complete paths and collects the transitions.
pub fn explore(plan: Arc<Plan>, options: ExploreOptions) -> Exploration {
    let t0 = Instant::now();
    let model = EngineModel::new(plan, options);
    let checker = model.checker().spawn_bfs().join();
    let states = checker.unique_state_count();
    let discovered: BTreeSet<&'static str> = checker.discoveries().keys().copied().collect();
    let model = checker.model();
    let mut graph = Graph::build(model);
    // The start: `ready` to the plan's first state (dispatched before the model begins).
    if let Some(first) = graph.states.first() {
        graph
            .edges
            .entry(("ready", state_parts(first.state()).0))
            .or_default()
            .insert("start".to_string());
    }
    let verdicts = PROPERTY_NAMES
        .iter()
        .map(|(name, says)| {
            let reachability = *name == "completed is reachable";
            let found = discovered.contains(name);
            let holds = if reachability { found } else { !found };
            // A failed invariant has a shortest counterexample; "completed is reachable"
            // fails with none to show.
            let path = (!holds)
                .then(|| graph.first.get(name).map(|&i| graph.path_to(i)))
                .flatten();
            // The replay stops where the counterexample ends: an abort comes next.
            let schedule = path.as_ref().map(|p| {
                let mut s = schedule_of(p.iter().map(|(_, a)| *a));
                let at = s.outcomes.len();
                s.supervisor
                    .push(TimedCommand::before(at, SupervisorCommand::Abort));
                s
            });
            Verdict {
                name,
                says,
                holds,
                path,
                schedule,
            }
        })
        .collect();
    Exploration {
        verdicts,
        states,
        graph_states: graph.states.len(),
        paths: graph.count_paths(),
        max_depth: graph.depth,
        elapsed: t0.elapsed(),
        edges: graph.edges,
    }
}

/// The explored state graph, breadth first from the start.
struct Graph {
    states: Vec<ExploreState>,
    /// How each state was first reached: its parent and the choice.
    parent: Vec<Option<(usize, Action)>>,
    /// Successors of each state.
    succ: Vec<Vec<usize>>,
    /// The first (so shallowest) state at which each property's condition was met: a
    /// violation for invariants, an example for "sometimes", a non-terminal dead end for
    /// "eventually".
    first: BTreeMap<&'static str, usize>,
    /// Choices on the longest of the shortest paths.
    depth: usize,
    edges: BTreeMap<(&'static str, &'static str), BTreeSet<String>>,
}

impl Graph {
    fn build(model: &EngineModel) -> Graph {
        let properties = model.properties();
        let mut g = Graph {
            states: Vec::new(),
            parent: Vec::new(),
            succ: Vec::new(),
            first: BTreeMap::new(),
            depth: 0,
            edges: BTreeMap::new(),
        };
        let mut index: HashMap<ExploreState, usize> = HashMap::new();
        let mut depth: Vec<usize> = Vec::new();
        for s in model.init_states() {
            index.insert(s.clone(), g.states.len());
            g.states.push(s);
            g.parent.push(None);
            g.succ.push(Vec::new());
            depth.push(0);
        }
        let mut actions = Vec::new();
        let mut i = 0;
        while i < g.states.len() {
            let state = g.states[i].clone();
            for p in &properties {
                let met = match p.expectation {
                    stateright::Expectation::Always => !(p.condition)(model, &state),
                    stateright::Expectation::Sometimes => (p.condition)(model, &state),
                    stateright::Expectation::Eventually => false,
                };
                if met {
                    g.first.entry(p.name).or_insert(i);
                }
            }
            actions.clear();
            model.actions(&state, &mut actions);
            if actions.is_empty() && !state.is_terminal() {
                g.first
                    .entry("ends completed, failed or aborted")
                    .or_insert(i);
            }
            for a in actions.drain(..) {
                let Some(next) = model.next_state(&state, a) else {
                    continue;
                };
                let from = state_parts(state.state()).0;
                let to = state_parts(next.state()).0;
                g.edges
                    .entry((from, to))
                    .or_default()
                    .insert(edge_label(&state, &a, &next));
                let j = match index.get(&next) {
                    Some(&j) => j,
                    None => {
                        let j = g.states.len();
                        index.insert(next.clone(), j);
                        g.states.push(next);
                        g.parent.push(Some((i, a)));
                        g.succ.push(Vec::new());
                        depth.push(depth[i] + 1);
                        g.depth = g.depth.max(depth[i] + 1);
                        j
                    }
                };
                g.succ[i].push(j);
            }
            i += 1;
        }
        g
    }

    /// The choices from the start to state `i`, each with the state it was made in.
    fn path_to(&self, mut i: usize) -> Vec<(String, Action)> {
        let mut path = Vec::new();
        while let Some((p, a)) = self.parent[i] {
            path.push((crate::machine::state_label(self.states[p].state()), a));
            i = p;
        }
        path.reverse();
        path
    }

    /// Complete paths from the start to an end, saturating. Counted in reverse topological
    /// order; an edge back to a state on the current depth-first path (a cycle, which the
    /// progress property rules out) is not followed.
    fn count_paths(&self) -> u128 {
        let n = self.states.len();
        let mut count: Vec<Option<u128>> = vec![None; n];
        let mut on_path = vec![false; n];
        let mut stack: Vec<(usize, usize)> = Vec::new();
        for root in 0..n.min(1) {
            stack.push((root, 0));
            on_path[root] = true;
            while let Some(&mut (v, ref mut k)) = stack.last_mut() {
                if let Some(&w) = self.succ[v].get(*k) {
                    *k += 1;
                    if count[w].is_none() && !on_path[w] {
                        on_path[w] = true;
                        stack.push((w, 0));
                    }
                } else {
                    let c = if self.succ[v].is_empty() {
                        1
                    } else {
                        self.succ[v]
                            .iter()
                            .fold(0u128, |acc, &w| acc.saturating_add(count[w].unwrap_or(0)))
                    };
                    count[v] = Some(c);
                    on_path[v] = false;
                    stack.pop();
                }
            }
        }
        count.first().copied().flatten().unwrap_or(0)
    }
}

/// The outcome schedule that makes `stitch run --robot scripted --outcomes` follow these
/// choices.
pub fn schedule_of(actions: impl IntoIterator<Item = Action>) -> OutcomeSchedule {
    let mut schedule = OutcomeSchedule::default();
    // Attempts started, as the runner counts them: ended by an outcome, or by a command.
    let mut attempts = 0;
    // An attempt paused mid-step, waiting to go on or to be ended.
    let mut suspended = false;
    for a in actions {
        match a {
            Action::Attempt(t) => {
                schedule.outcomes.push(t);
                attempts += 1;
                suspended = false;
            }
            Action::Command(command) => {
                schedule
                    .supervisor
                    .push(TimedCommand::before(attempts, command));
                if suspended && command != SupervisorCommand::Resume {
                    // Taken over or stopped while paused mid-step: that attempt ended.
                    attempts += 1;
                    suspended = false;
                }
            }
            Action::Interrupt(command, committed) => {
                let at = if committed {
                    InStep::Committed
                } else {
                    InStep::Start
                };
                schedule
                    .supervisor
                    .push(TimedCommand::in_attempt(attempts + 1, at, command));
                // Paused, the attempt goes on after a resume (its outcome is the next
                // Attempt's); otherwise it ends here, with no outcome drawn.
                if command == SupervisorCommand::Pause {
                    suspended = true;
                } else {
                    attempts += 1;
                }
            }
            Action::Intervention(r) => schedule.interventions.push(r),
            Action::Decide(v) => schedule.conditions.push(Some(v)),
            Action::Unobservable => schedule.conditions.push(None),
            Action::Checkpoint(c) => schedule.checkpoints.push(c),
            Action::SupervisorGone => {
                if suspended {
                    attempts += 1;
                    suspended = false;
                }
            }
        }
    }
    schedule
}

/// How a transition is labelled in the diagram: the choice, or what it means.
fn edge_label(from: &ExploreState, action: &Action, to: &ExploreState) -> String {
    match action {
        Action::Attempt(t) => {
            let (_, c0) = state_parts(from.state());
            let (_, c1) = state_parts(to.state());
            match (c0, c1, to.state()) {
                (Some(a), Some(b), _)
                    if a.throw == b.throw && a.step == b.step && b.retries > a.retries =>
                {
                    "retry".to_string()
                }
                (_, _, State::AwaitingIntervention { .. }) => "failure: ask for help".to_string(),
                (_, _, State::Failed { .. }) => "failure".to_string(),
                _ if *t == Scripted::Ok => "success".to_string(),
                _ => t.to_string(),
            }
        }
        other => other.to_string(),
    }
}

/// A Mermaid state diagram of the transitions an exploration saw.
pub fn mermaid(edges: &BTreeMap<(&'static str, &'static str), BTreeSet<String>>) -> String {
    let in_throw = |n: &str| {
        matches!(
            n,
            "inserting"
                | "sweeping"
                | "extracting"
                | "cinching"
                | "handing_over"
                | "correcting"
                | "perceiving"
                | "deciding"
                | "at_checkpoint"
                | "awaiting_intervention"
        )
    };
    let mut nodes: BTreeSet<&str> = BTreeSet::new();
    for (a, b) in edges.keys() {
        nodes.insert(a);
        nodes.insert(b);
    }
    let mut s = String::from("stateDiagram-v2\n    [*] --> ready\n");
    s.push_str("    state supervised {\n        state mission {\n            state throw {\n");
    for n in nodes.iter().filter(|n| in_throw(n)) {
        s.push_str(&format!("                {n}\n"));
    }
    s.push_str("            }\n        }\n");
    for n in ["paused", "taken_over"] {
        if nodes.contains(n) {
            s.push_str(&format!("        {n}\n"));
        }
    }
    s.push_str("    }\n");
    for ((a, b), labels) in edges {
        let labels: Vec<&str> = labels.iter().map(String::as_str).collect();
        s.push_str(&format!("    {a} --> {b} : {}\n", labels.join(", ")));
    }
    for end in ["completed", "failed", "aborted"] {
        if nodes.contains(end) {
            s.push_str(&format!("    {end} --> [*]\n"));
        }
    }
    s
}
