//! The typed hierarchical state machine (statig) that executes a plan.
//!
//! ```text
//! supervised                      abort / e-stop → aborted (arms hold)
//! ├── mission
//! │   └── throw                   pause → paused; take-over → taken_over
//! │       ├── inserting · sweeping · extracting · cinching · handing_over · correcting
//! │       │   · perceiving        (one per phase: the step being attempted)
//! │       ├── deciding            (a plan's condition: when, repeat's until)
//! │       ├── at_checkpoint       (the arms hold until the surgeon says go)
//! │       └── awaiting_intervention
//! ├── paused                      resume → the step that was next, or the one interrupted
//! │                               (which goes on where it stopped)
//! └── taken_over                  hand-back → the step that was next, the interrupted one
//!                                 from its start, or (past its commit point) the one after
//! ready → (start) → first step;   completed · failed · aborted are final
//! ```
//!
//! The machine owns no hardware: the runner reads the state, performs the step it names, and
//! dispatches the outcome. The hard caps (retries, interventions) are guards here, so no plan
//! can exceed them whatever it asks for.

use crate::condition::{MissionFacts, Quantity};
use crate::journal::{AbortCause, Arrival, Entry, Journal};
use crate::plan::{FailureClass, Op, Plan, caps};
use crate::supervisor::{InterventionResult, SupervisorCommand};
use serde::Serialize;
use statig::prelude::*;
use std::sync::Arc;
use stitch_primitives::{Failure, FailureKind, StepKind, StepOutcome};

/// Where the machine is in the plan.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize)]
pub struct Cursor {
    /// Throw index, 0-based.
    pub throw: usize,
    /// Index into the throw's program, 0-based (a plan without constructs: the step index).
    pub step: usize,
    /// Retries of this step so far.
    pub retries: u8,
}

/// What the machine reacts to.
#[derive(Clone, Debug, PartialEq)]
pub enum Event {
    /// Begin the mission.
    Start,
    /// The step the machine is in finished one attempt.
    StepFinished(StepOutcome),
    /// The condition the machine is deciding has this value.
    Decided(bool),
    /// The requested intervention ended.
    InterventionFinished(InterventionResult),
    /// The supervisor commanded.
    Supervisor(SupervisorCommand),
    /// The supervisor is gone (no command will come while paused or taken over).
    SupervisorLost,
    /// The supervisor commanded while the step the machine is in was under way (its motion
    /// stopped at the command; `committed`: the step had passed its commit point).
    Interrupt {
        /// The command.
        command: SupervisorCommand,
        /// Whether the step had passed its commit point.
        committed: bool,
    },
}

/// Where the run was when the supervisor paused it or took over.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum Interrupted {
    /// Before a step attempt (or at a checkpoint): nothing was under way.
    #[default]
    Between,
    /// In the middle of a step, before its commit point: resumed, it goes on where it
    /// stopped; handed back after a take-over, it runs again from its start.
    MidStep,
    /// In the middle of a step past its commit point: resumed, it goes on; handed back after a
    /// take-over, the run goes on with the step after it (the surgeon finished it).
    Committed,
}

impl Interrupted {
    /// Mid-step, committed or not.
    pub fn mid_step(committed: bool) -> Self {
        if committed {
            Interrupted::Committed
        } else {
            Interrupted::MidStep
        }
    }
}

/// Side effects the machine asks of the runner, in order.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Effect {
    /// Stop all motion and hold both arms.
    HoldArms,
}

/// What the machine is given with each event: the journal, and a queue of effects.
#[derive(Debug, Default)]
pub struct Ctx {
    /// The run's journal.
    pub journal: Journal,
    /// Effects the runner must perform after this dispatch.
    pub effects: Vec<Effect>,
    /// Where the command being dispatched came from, for its journal record.
    pub arrival: Arrival,
}

/// The mission's counters that conditions may read and that decide the machine's behaviour
/// (what identifies a machine beside its state, for the model checker).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub struct Counters {
    /// Interventions requested so far.
    pub interventions_used: u8,
    /// Retries granted in the current throw (kept only if a condition reads them).
    pub throw_retries: u8,
    /// Thread the cinches pulled, µm (kept only if a condition reads it).
    pub thread_used_um: u64,
}

/// The machine's shared storage: the plan and the mission's counters.
#[derive(Clone, Debug, PartialEq)]
pub struct Mission {
    plan: Arc<Plan>,
    counters: Counters,
    tracks_retries: bool,
    tracks_thread: bool,
    last_failure: Option<Failure>,
}

impl Mission {
    /// A mission for `plan`, ready to start. The plan should have been validated; the machine
    /// enforces the hard caps even if it was not.
    pub fn new(plan: Arc<Plan>) -> Self {
        Self {
            tracks_retries: plan.reads(&Quantity::RetriesUsed),
            tracks_thread: plan.reads(&Quantity::ThreadLeft),
            plan,
            counters: Counters::default(),
            last_failure: None,
        }
    }

    /// The counters.
    pub fn counters(&self) -> Counters {
        self.counters
    }

    /// What the engine knows for a condition decided at `c`.
    pub fn facts(&self, c: Cursor) -> MissionFacts {
        MissionFacts {
            throw_number: c.throw + 1,
            interventions_left: self
                .intervention_budget()
                .saturating_sub(self.counters.interventions_used),
            retries_used: self.counters.throw_retries,
            thread_left_m: self
                .plan
                .thread_length_m
                .map(|l| l - self.counters.thread_used_um as f64 * 1e-6),
        }
    }

    /// The operation at `c`, if there is one.
    pub fn op(&self, c: Cursor) -> Option<&Op> {
        self.plan.throws.get(c.throw)?.program.get(c.step)
    }

    /// The plan.
    pub fn plan(&self) -> &Plan {
        &self.plan
    }

    /// The plan, shared.
    pub fn plan_arc(&self) -> &Arc<Plan> {
        &self.plan
    }

    /// Interventions requested so far.
    pub fn interventions_used(&self) -> u8 {
        self.counters.interventions_used
    }

    /// The effective intervention budget: the plan's, bounded by the hard cap.
    pub fn intervention_budget(&self) -> u8 {
        self.plan.interventions.min(caps::INTERVENTIONS)
    }

    /// The last failure reported by a step.
    pub fn last_failure(&self) -> Option<&Failure> {
        self.last_failure.as_ref()
    }

    /// The step at `c`, if there is one.
    pub fn step_kind(&self, c: Cursor) -> Option<&StepKind> {
        self.plan.throws.get(c.throw)?.step(c.step).map(|s| &s.kind)
    }

    /// The state that attempts the step at `c`; a cursor past the end of its throw moves on
    /// to the first step of the next non-empty throw (validation refuses empty throws, but the
    /// machine must not stop early on a plan built some other way); past the last throw,
    /// `completed`.
    fn step_state(&self, mut c: Cursor) -> State {
        loop {
            let Some(throw) = self.plan.throws.get(c.throw) else {
                return State::completed();
            };
            let Some(op) = throw.program.get(c.step) else {
                c = Cursor {
                    throw: c.throw + 1,
                    step: 0,
                    retries: 0,
                };
                continue;
            };
            let step = match op {
                Op::Do(step) => step,
                Op::Branch { .. } => return State::deciding(c),
                Op::Checkpoint { .. } => return State::at_checkpoint(c),
                // Jumps go forward (the compiler makes them so); one that did not would be
                // skipped rather than loop.
                Op::Jump { to } => {
                    c.step = (*to).max(c.step + 1);
                    continue;
                }
            };
            return match step.kind {
                StepKind::Insert(_) => State::inserting(c),
                StepKind::Sweep(_) => State::sweeping(c),
                StepKind::Extract(_) => State::extracting(c),
                StepKind::Cinch(_) => State::cinching(c),
                StepKind::Handover(_) => State::handing_over(c),
                StepKind::Correct(_) => State::correcting(c),
                StepKind::EstimateNeedle(_) | StepKind::TrackThread(_) => State::perceiving(c),
            };
        }
    }

    /// The step after `c`: the next in the throw, the first of the next throw, or `completed`.
    fn next_state(&self, c: Cursor) -> State {
        self.step_state(Cursor {
            throw: c.throw,
            step: c.step + 1,
            retries: 0,
        })
    }

    /// Where a decided condition at `c` leads.
    fn on_decided(&mut self, c: Cursor, ctx: &mut Ctx, event: &Event) -> Outcome<State> {
        // The robot could not make the observation the condition needs (an arm that cannot
        // say where it is, a failing camera): the condition is not decided on what is
        // missing. No retry: the surgeon is asked while the budget lasts, else the throw
        // fails in the phase the needle is in.
        if let Event::StepFinished(StepOutcome::Failed(failure)) = event {
            self.last_failure = Some(failure.clone());
            let class = if failure.kind.is_thread() {
                FailureClass::Thread
            } else {
                self.plan.needle_phase_class(c.throw, c.step)
            };
            return self.escalate(c, class, ctx);
        }
        let Event::Decided(value) = event else {
            return Super;
        };
        match self.op(c) {
            Some(Op::Branch { jump_if, to, .. }) if value == jump_if => {
                // Forward only, whatever the plan says: no cycle through a branch.
                let to = (*to).max(c.step + 1);
                Transition(self.step_state(Cursor {
                    throw: c.throw,
                    step: to,
                    retries: 0,
                }))
            }
            _ => Transition(self.next_state(c)),
        }
    }

    /// The hard-capped retry budget of the step at `c`.
    pub fn retry_cap(&self, c: Cursor) -> u8 {
        self.step_kind(c)
            .and_then(|k| Some(k.retries()?.min(crate::validate::retry_cap(k)?.0)))
            .unwrap_or(0)
    }

    /// The paper's class for a failure of the step at `c`.
    pub fn classify(&self, c: Cursor, failure: &FailureKind) -> FailureClass {
        if failure.is_thread() {
            FailureClass::Thread
        } else {
            self.plan.phase_class(c.throw, c.step)
        }
    }

    fn on_step_outcome(&mut self, c: Cursor, ctx: &mut Ctx, event: &Event) -> Outcome<State> {
        let Event::StepFinished(outcome) = event else {
            return Super;
        };
        let failure = match outcome {
            StepOutcome::Succeeded { measured } => {
                if self.tracks_thread {
                    let used = measured.thread_used_m.unwrap_or(0.0).max(0.0);
                    self.counters.thread_used_um = self
                        .counters
                        .thread_used_um
                        .saturating_add((used * 1e6).round() as u64);
                }
                return Transition(self.next_state(c));
            }
            StepOutcome::Failed(f) => f.clone(),
            // The runner never reports an interrupted attempt as an outcome (the command
            // moved the machine); one that came would be a bug, failed safely.
            StepOutcome::Interrupted { measured, .. } => Failure {
                kind: FailureKind::ArmFault {
                    message: "engine: an interrupted attempt reported as an outcome".into(),
                },
                measured: measured.clone(),
            },
        };
        let failure = &failure;
        self.last_failure = Some(failure.clone());
        let class = self.classify(c, &failure.kind);
        let name = self.step_kind(c).map_or("?", StepKind::name).to_string();
        let cap = self.retry_cap(c);
        if self
            .step_kind(c)
            .is_some_and(|k| recovery_condition(k, failure))
            && c.retries < cap
        {
            let retries = c.retries + 1;
            if self.tracks_retries {
                self.counters.throw_retries = self.counters.throw_retries.saturating_add(1);
            }
            ctx.journal.push(Entry::Retry {
                throw: c.throw,
                step: c.step,
                primitive: name,
                retry: retries,
                cap,
            });
            return Transition(self.step_state(Cursor { retries, ..c }));
        }
        self.escalate(c, class, ctx)
    }

    /// A failure no retry covers: ask the surgeon while the budget lasts, else fail.
    fn escalate(&mut self, c: Cursor, class: FailureClass, ctx: &mut Ctx) -> Outcome<State> {
        let budget = self.intervention_budget();
        if self.counters.interventions_used < budget {
            self.counters.interventions_used += 1;
            ctx.journal.push(Entry::InterventionRequested {
                throw: c.throw,
                step: c.step,
                class,
                used: self.counters.interventions_used,
                budget,
            });
            return Transition(State::awaiting_intervention(c, class));
        }
        Transition(State::failed(c, class))
    }
}

/// The paper's recovery conditions ("Motion Failure Recovery", "Needle Handover"): retry an
/// extraction whose endpoint moved less than the threshold, a handover whose grasp left the
/// needle normal unchanged, and any perceiving step after a dropout. Thread failures, dropped
/// needles and arm faults are never retried.
pub fn recovery_condition(kind: &StepKind, failure: &Failure) -> bool {
    match &failure.kind {
        k if k.is_thread() => false,
        FailureKind::NeedleDropped | FailureKind::ArmFault { .. } => false,
        FailureKind::PerceptionDropout => matches!(
            kind,
            StepKind::Extract(_)
                | StepKind::Handover(_)
                | StepKind::EstimateNeedle(_)
                | StepKind::TrackThread(_)
        ),
        _ => match kind {
            StepKind::Extract(p) => failure
                .measured
                .endpoint_travel_m
                .is_some_and(|t| t < p.min_travel_m),
            StepKind::Handover(p) => failure
                .measured
                .normal_change_rad
                .is_some_and(|d| d <= p.normal_tolerance_rad),
            _ => false,
        },
    }
}

/// Journal a command, with where it came from and where it landed.
fn journal_command(ctx: &mut Ctx, command: SupervisorCommand, acted: bool) {
    let Arrival { from, during } = std::mem::take(&mut ctx.arrival);
    ctx.journal.push(Entry::Supervisor {
        command,
        acted,
        from,
        during,
    });
}

/// Abort or e-stop: journal the command and end the run at `cursor`.
fn stop(ctx: &mut Ctx, command: SupervisorCommand, cursor: Cursor) -> Outcome<State> {
    journal_command(ctx, command, true);
    let by = if command == SupervisorCommand::EStop {
        AbortCause::EStop
    } else {
        AbortCause::Abort
    };
    Transition(State::aborted(cursor, by))
}

/// Journal a command the machine acts on.
fn acted(ctx: &mut Ctx, command: SupervisorCommand) {
    journal_command(ctx, command, true);
}

fn supervisor_ignored(ctx: &mut Ctx, command: SupervisorCommand) -> Outcome<State> {
    journal_command(ctx, command, false);
    Handled
}

#[state_machine(
    initial = "State::ready()",
    state(derive(Debug, Clone, PartialEq, Eq, Hash)),
    superstate(derive(Debug)),
    after_transition = "Self::after_transition"
)]
impl Mission {
    /// Before the mission starts.
    #[state]
    fn ready(&mut self, context: &mut Ctx, event: &Event) -> Outcome<State> {
        match event {
            Event::Start => Transition(self.step_state(Cursor::default())),
            Event::Supervisor(c @ (SupervisorCommand::Abort | SupervisorCommand::EStop)) => {
                stop(context, *c, Cursor::default())
            }
            Event::Supervisor(c) => supervisor_ignored(context, *c),
            _ => Handled,
        }
    }

    /// Needle insertion (right PSM).
    #[state(superstate = "throw")]
    fn inserting(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// Thread sweeping (right PSM, jaw open).
    #[state(superstate = "throw")]
    fn sweeping(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// Needle extraction (left PSM).
    #[state(superstate = "throw")]
    fn extracting(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// Suture cinching (left PSM).
    #[state(superstate = "throw")]
    fn cinching(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// Needle handover (left → right).
    #[state(superstate = "throw")]
    fn handing_over(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// Needle pose correction (right PSM).
    #[state(superstate = "throw")]
    fn correcting(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// A perception query (needle pose or thread).
    #[state(superstate = "throw")]
    fn perceiving(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_step_outcome(*cursor, context, event)
    }

    /// A plan's condition (a `when`, a `repeat`'s `until`): the runner observes, decides, and
    /// the machine goes where the value leads.
    #[state(superstate = "throw")]
    fn deciding(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        self.on_decided(*cursor, context, event)
    }

    /// A surgeon checkpoint: the arms hold until the supervisor says go.
    #[state(superstate = "throw", entry_action = "hold_arms")]
    fn at_checkpoint(
        &mut self,
        cursor: &mut Cursor,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        match event {
            Event::Supervisor(SupervisorCommand::Go) => {
                acted(context, SupervisorCommand::Go);
                Transition(self.next_state(*cursor))
            }
            // Already holding, waiting on the surgeon: a pause changes nothing.
            Event::Supervisor(c @ SupervisorCommand::Pause) => supervisor_ignored(context, *c),
            _ => Super,
        }
    }

    /// The robot asked the surgeon for help; the arms hold until the intervention ends.
    #[state(superstate = "throw", entry_action = "hold_arms")]
    fn awaiting_intervention(
        &mut self,
        cursor: &mut Cursor,
        class: &mut FailureClass,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        match event {
            Event::InterventionFinished(result) => {
                context.journal.push(Entry::InterventionEnded {
                    throw: cursor.throw,
                    step: cursor.step,
                    result: *result,
                });
                match result {
                    InterventionResult::Recovered => Transition(self.step_state(*cursor)),
                    InterventionResult::Failed => Transition(State::failed(*cursor, *class)),
                }
            }
            // The surgeon is already at the console: pause and take-over change nothing.
            Event::Supervisor(
                c @ (SupervisorCommand::Pause
                | SupervisorCommand::TakeOver
                | SupervisorCommand::Resume
                | SupervisorCommand::HandBack
                | SupervisorCommand::Go),
            ) => supervisor_ignored(context, *c),
            _ => Super,
        }
    }

    /// A throw in progress: the supervisor may pause or take over before any step, or in the
    /// middle of one (an interrupt: the step's motion was stopped at the command).
    #[superstate(superstate = "mission")]
    fn throw(cursor: &mut Cursor, context: &mut Ctx, event: &Event) -> Outcome<State> {
        match event {
            Event::Supervisor(SupervisorCommand::Pause) => {
                acted(context, SupervisorCommand::Pause);
                Transition(State::paused(*cursor, Interrupted::Between))
            }
            Event::Supervisor(SupervisorCommand::TakeOver) => {
                acted(context, SupervisorCommand::TakeOver);
                Transition(State::taken_over(*cursor, Interrupted::Between))
            }
            Event::Interrupt {
                command: SupervisorCommand::Pause,
                committed,
            } => {
                acted(context, SupervisorCommand::Pause);
                Transition(State::paused(*cursor, Interrupted::mid_step(*committed)))
            }
            Event::Interrupt {
                command: SupervisorCommand::TakeOver,
                committed,
            } => {
                acted(context, SupervisorCommand::TakeOver);
                Transition(State::taken_over(
                    *cursor,
                    Interrupted::mid_step(*committed),
                ))
            }
            Event::Interrupt {
                command: c @ (SupervisorCommand::Abort | SupervisorCommand::EStop),
                ..
            } => stop(context, *c, *cursor),
            Event::Interrupt { command: c, .. } => supervisor_ignored(context, *c),
            Event::Supervisor(
                c @ (SupervisorCommand::Resume
                | SupervisorCommand::HandBack
                | SupervisorCommand::Go),
            ) => supervisor_ignored(context, *c),
            _ => Super,
        }
    }

    /// The mission: every throw of the plan.
    #[superstate(superstate = "supervised")]
    fn mission(cursor: &mut Cursor, event: &Event) -> Outcome<State> {
        let _ = (cursor, event);
        Super
    }

    /// Paused by the supervisor; the arms hold. Resumed, the run goes on with the step at the
    /// cursor: the next one, or the one interrupted, which goes on where it stopped.
    #[state(superstate = "supervised", entry_action = "hold_arms")]
    fn paused(
        &mut self,
        cursor: &mut Cursor,
        at: &mut Interrupted,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        match event {
            Event::Supervisor(SupervisorCommand::Resume) => {
                acted(context, SupervisorCommand::Resume);
                Transition(self.step_state(*cursor))
            }
            Event::Supervisor(SupervisorCommand::TakeOver) => {
                acted(context, SupervisorCommand::TakeOver);
                Transition(State::taken_over(*cursor, *at))
            }
            Event::Supervisor(c @ (SupervisorCommand::Pause | SupervisorCommand::HandBack)) => {
                supervisor_ignored(context, *c)
            }
            _ => Super,
        }
    }

    /// The surgeon teleoperates; the engine commands nothing. Handed back, the run goes on
    /// with the step at the cursor from its start (the next one, or the one interrupted), or,
    /// where the interrupted step had passed its commit point, with the step after it.
    #[state(superstate = "supervised", entry_action = "hold_arms")]
    fn taken_over(
        &mut self,
        cursor: &mut Cursor,
        at: &mut Interrupted,
        context: &mut Ctx,
        event: &Event,
    ) -> Outcome<State> {
        match event {
            Event::Supervisor(SupervisorCommand::HandBack) => {
                acted(context, SupervisorCommand::HandBack);
                Transition(match at {
                    Interrupted::Committed => self.next_state(*cursor),
                    Interrupted::Between | Interrupted::MidStep => self.step_state(*cursor),
                })
            }
            Event::Supervisor(
                c @ (SupervisorCommand::Pause
                | SupervisorCommand::Resume
                | SupervisorCommand::TakeOver),
            ) => supervisor_ignored(context, *c),
            _ => Super,
        }
    }

    /// Everything under supervision: abort and e-stop end the run from any state here.
    #[superstate]
    fn supervised(cursor: &mut Cursor, context: &mut Ctx, event: &Event) -> Outcome<State> {
        match event {
            Event::Supervisor(c @ (SupervisorCommand::Abort | SupervisorCommand::EStop)) => {
                stop(context, *c, *cursor)
            }
            Event::Supervisor(c) => supervisor_ignored(context, *c),
            Event::SupervisorLost => {
                Transition(State::aborted(*cursor, AbortCause::SupervisorSilent))
            }
            _ => Handled,
        }
    }

    /// Every throw succeeded; the arms hold, as at every end (nothing moves until the next
    /// run commands it).
    #[state(entry_action = "hold_arms")]
    fn completed(event: &Event) -> Outcome<State> {
        let _ = event;
        Handled
    }

    /// A step failed beyond its retries and the intervention budget; the arms hold.
    #[state(entry_action = "hold_arms")]
    fn failed(cursor: &mut Cursor, class: &mut FailureClass, event: &Event) -> Outcome<State> {
        let _ = (cursor, class, event);
        Handled
    }

    /// The supervisor stopped the run; the arms hold; nothing moves again.
    #[state(entry_action = "hold_arms")]
    fn aborted(cursor: &mut Cursor, by: &mut AbortCause, event: &Event) -> Outcome<State> {
        let _ = (cursor, by, event);
        Handled
    }

    #[action]
    fn hold_arms(context: &mut Ctx) {
        context.effects.push(Effect::HoldArms);
    }
}

impl Mission {
    fn after_transition(&mut self, source: &State, target: &State, context: &mut Ctx) {
        // Retries are counted per throw.
        if let (Some(a), Some(b)) = (state_parts(source).1, state_parts(target).1) {
            if b.throw != a.throw {
                self.counters.throw_retries = 0;
            }
        }
        context.journal.push(Entry::Transition {
            from: state_label(source),
            to: state_label(target),
        });
    }
}

/// What the machine waits for in a state: what its driver (the runner, or the explorer)
/// must do next.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Pending {
    /// Dispatch [`Event::Start`].
    Start,
    /// Ask the supervisor for a command, then attempt the step at the cursor and dispatch
    /// its outcome.
    Attempt(Cursor),
    /// Ask the supervisor to intervene for the step at the cursor; dispatch the result.
    Intervention(Cursor, FailureClass),
    /// Observe, decide the condition at the cursor, dispatch [`Event::Decided`].
    Decide(Cursor),
    /// Ask the supervisor for go at the checkpoint at the cursor; dispatch the answer.
    Checkpoint(Cursor),
    /// Wait for the supervisor's next command (paused or taken over).
    Command(Cursor),
    /// Nothing: the run is over.
    Done,
}

/// What the machine waits for in `state`.
pub fn pending(state: &State) -> Pending {
    match state {
        State::Ready {} => Pending::Start,
        State::Inserting { cursor }
        | State::Sweeping { cursor }
        | State::Extracting { cursor }
        | State::Cinching { cursor }
        | State::HandingOver { cursor }
        | State::Correcting { cursor }
        | State::Perceiving { cursor } => Pending::Attempt(*cursor),
        State::AwaitingIntervention { cursor, class } => Pending::Intervention(*cursor, *class),
        State::Deciding { cursor } => Pending::Decide(*cursor),
        State::AtCheckpoint { cursor } => Pending::Checkpoint(*cursor),
        State::Paused { cursor, .. } | State::TakenOver { cursor, .. } => Pending::Command(*cursor),
        State::Completed {} | State::Failed { .. } | State::Aborted { .. } => Pending::Done,
    }
}

/// A state's name with its cursor, as the journal writes it: `extracting(t1 s3 r0)` (throw
/// and step 1-based, retries so far).
/// Paused or taken over mid-step says so: `paused(t1 s3 r0 mid-step)`, `taken_over(t1 s3 r0
/// committed)`.
pub fn state_label(state: &State) -> String {
    let (name, cursor) = state_parts(state);
    let mid = match state {
        State::Paused { at, .. } | State::TakenOver { at, .. } => match at {
            Interrupted::Between => "",
            Interrupted::MidStep => " mid-step",
            Interrupted::Committed => " committed",
        },
        _ => "",
    };
    match cursor {
        Some(c) => format!(
            "{name}(t{} s{} r{}{mid})",
            c.throw + 1,
            c.step + 1,
            c.retries
        ),
        None => name.to_string(),
    }
}

/// A state's name and cursor.
pub fn state_parts(state: &State) -> (&'static str, Option<Cursor>) {
    match state {
        State::Ready {} => ("ready", None),
        State::Inserting { cursor } => ("inserting", Some(*cursor)),
        State::Sweeping { cursor } => ("sweeping", Some(*cursor)),
        State::Extracting { cursor } => ("extracting", Some(*cursor)),
        State::Cinching { cursor } => ("cinching", Some(*cursor)),
        State::HandingOver { cursor } => ("handing_over", Some(*cursor)),
        State::Correcting { cursor } => ("correcting", Some(*cursor)),
        State::Perceiving { cursor } => ("perceiving", Some(*cursor)),
        State::AwaitingIntervention { cursor, .. } => ("awaiting_intervention", Some(*cursor)),
        State::Deciding { cursor } => ("deciding", Some(*cursor)),
        State::AtCheckpoint { cursor } => ("at_checkpoint", Some(*cursor)),
        State::Paused { cursor, .. } => ("paused", Some(*cursor)),
        State::TakenOver { cursor, .. } => ("taken_over", Some(*cursor)),
        State::Completed {} => ("completed", None),
        State::Failed { cursor, .. } => ("failed", Some(*cursor)),
        State::Aborted { cursor, .. } => ("aborted", Some(*cursor)),
    }
}
