//! The runner: drives the state machine with a [`Primitives`] implementation and a
//! [`Supervisor`], performs the effects it asks for, and keeps the journal and a per-throw
//! summary.

use crate::condition::Facts;
use crate::journal::{Arrival, During, Entry, Journal, RunOutcome};
use crate::machine::{
    Ctx, Cursor, Effect, Event, Interrupted, Mission, Pending, State, pending, state_label,
    state_parts,
};
use crate::plan::{NeedleHolder, Op, Plan};
use crate::supervisor::{
    CheckpointRequest, InterventionRequest, InterventionResult, Moment, NextPoll, Resumption,
    Supervisor, SupervisorCommand,
};
use serde::Serialize;
use statig::blocking::{InitializedStateMachine, IntoStateMachineExt};
use std::sync::Arc;
use std::time::Duration;
use stitch_primitives::{
    Control, Failure, FailureKind, Measurements, NeedleAt, ObserveRequest, PrimitiveError,
    Primitives, StepControl, StepOutcome, StepRequest,
};
use stitch_robot::Clock;

/// Something told of each step attempt as it ends (a live timeline), with its throw index.
pub type AttemptSink = Box<dyn FnMut(usize, &Attempt)>;

/// One step attempt as the runner saw it, for timelines.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Attempt {
    /// Step index within the throw, 0-based.
    pub step: usize,
    /// Step name.
    pub primitive: &'static str,
    /// Attempt number, 0-based.
    pub attempt: u32,
    /// Simulated time when it started, s.
    pub start_s: f64,
    /// Simulated time it took, s.
    pub duration_s: f64,
    /// What happened.
    pub outcome: StepOutcome,
    /// The intervention this attempt's failure led to, and how it ended.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub intervention: Option<InterventionResult>,
}

/// A plan's condition as the runner decided it, for timelines.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Decision {
    /// Program index, 0-based.
    pub step: usize,
    /// When it was decided, s.
    pub at_s: f64,
    /// The condition, as the script writes it.
    pub condition: String,
    /// Its value.
    pub value: bool,
}

/// A checkpoint the run reached, and the supervisor's answer, for timelines.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct CheckpointSeen {
    /// Program index, 0-based.
    pub step: usize,
    /// When the run reached it, s.
    pub at_s: f64,
    /// What the surgeon confirms.
    pub label: String,
    /// The answer; `None` if none came (the supervisor was gone, or the journal stops).
    pub answer: Option<SupervisorCommand>,
}

/// What happened in one throw.
#[derive(Clone, Debug, Default, PartialEq, Serialize)]
pub struct ThrowSummary {
    /// Every step attempt, in order.
    pub attempts: Vec<Attempt>,
    /// Every condition decided, in order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub decisions: Vec<Decision>,
    /// Every checkpoint reached, in order.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub checkpoints: Vec<CheckpointSeen>,
    /// Retries the machine granted in this throw.
    pub retries: u32,
    /// Interventions requested in this throw.
    pub interventions: u32,
    /// Whether every step of the throw succeeded.
    pub completed: bool,
}

/// What a run produced.
#[derive(Clone, Debug, PartialEq)]
pub struct Report {
    /// How it ended.
    pub outcome: RunOutcome,
    /// One summary per throw of the plan.
    pub throws: Vec<ThrowSummary>,
    /// Interventions used.
    pub interventions: u8,
    /// Simulated time at the end, s.
    pub duration_s: f64,
    /// The journal.
    pub journal: Journal,
}

/// Runs one plan.
pub struct Runner<'a> {
    machine: InitializedStateMachine<Mission>,
    ctx: Ctx,
    primitives: &'a mut dyn Primitives,
    supervisor: &'a mut dyn Supervisor,
    clock: Arc<dyn Clock>,
    throws: Vec<ThrowSummary>,
    attempts_started: usize,
    /// Where the plan has the needle before each operation (for a condition's query).
    holders: Vec<Vec<Option<NeedleHolder>>>,
    /// Told of each attempt as it ends.
    on_attempt: Option<AttemptSink>,
}

impl std::fmt::Debug for Runner<'_> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Runner")
            .field("state", self.machine.state())
            .finish_non_exhaustive()
    }
}

impl<'a> Runner<'a> {
    /// A runner for `plan`. Validate the plan first ([`crate::load_plan`] does); the machine
    /// enforces the hard caps either way. `seed` is recorded in the journal.
    pub fn new(
        plan: Arc<Plan>,
        primitives: &'a mut dyn Primitives,
        supervisor: &'a mut dyn Supervisor,
        clock: Arc<dyn Clock>,
        seed: Option<u64>,
    ) -> Self {
        let mut ctx = Ctx::default();
        ctx.journal.set_now(clock.now());
        ctx.journal.push(Entry::Plan {
            name: plan.name.clone(),
            file: plan.file.clone(),
            throws: plan.throws.len(),
            interventions: plan.interventions,
            seed,
            params: plan.params.clone(),
        });
        let throws = vec![ThrowSummary::default(); plan.throws.len()];
        let holders = plan.holders();
        let machine = Mission::new(plan)
            .uninitialized_state_machine()
            .init_with_context(&mut ctx);
        Self {
            machine,
            ctx,
            primitives,
            supervisor,
            clock,
            throws,
            attempts_started: 0,
            holders,
            on_attempt: None,
        }
    }

    /// Tell `sink` of each step attempt as it ends (a timeline printed as the run goes).
    pub fn on_attempt(mut self, sink: AttemptSink) -> Self {
        self.on_attempt = Some(sink);
        self
    }

    /// Stream every record to `sink` (if any) as it is journaled (a flight recorder), those
    /// already journaled first; the report's journal still holds them all.
    pub fn streaming(mut self, sink: Option<crate::JournalSink>) -> Self {
        if let Some(sink) = sink {
            self.ctx.journal.stream_to(sink);
        }
        self
    }

    /// The machine's current state.
    pub fn state(&self) -> &State {
        self.machine.state()
    }

    fn dispatch(&mut self, event: Event) {
        let primitives = &mut *self.primitives;
        dispatch(
            &mut self.machine,
            &mut self.ctx,
            &*self.clock,
            &mut || primitives.hold_all(),
            event,
        );
    }

    /// Journal a command's source before it is dispatched.
    fn arriving(&mut self) {
        self.ctx.arrival = Arrival {
            from: Some(self.supervisor.source().to_string()),
            during: None,
        };
    }

    /// The supervisor's next command while the run waits on it (paused, taken over): a
    /// schedule's timed command is waited for on the run's clock.
    fn wait_command(&mut self) -> Event {
        wait_command(
            &mut *self.supervisor,
            &*self.clock,
            &mut self.ctx,
            self.attempts_started,
        )
    }

    /// Run to the end: completed, failed or aborted.
    pub fn run(mut self) -> Report {
        loop {
            match pending(self.machine.state()) {
                Pending::Done => break,
                Pending::Start => self.dispatch(Event::Start),
                Pending::Command(_) => {
                    let mut event = self.wait_command();
                    if let (
                        Event::Supervisor(SupervisorCommand::HandBack),
                        State::TakenOver { cursor, at },
                    ) = (&event, self.machine.state())
                    {
                        let to = Resumption {
                            throw: cursor.throw,
                            step: match at {
                                Interrupted::Committed => cursor.step + 1,
                                Interrupted::Between | Interrupted::MidStep => cursor.step,
                            },
                        };
                        event = Event::Supervisor(self.supervisor.hand_back(&to));
                    }
                    self.dispatch(event);
                }
                Pending::Intervention(c, class) => {
                    let request = InterventionRequest {
                        throw: c.throw,
                        step: c.step,
                        primitive: self.step_name(c),
                        class,
                    };
                    let result = self.supervisor.intervene(&request);
                    journal_refused(&mut *self.supervisor, &mut self.ctx, &*self.clock);
                    if let Some(t) = self.throws.get_mut(c.throw) {
                        t.interventions += 1;
                        if let Some(last) = t.attempts.last_mut() {
                            last.intervention = Some(result);
                        }
                    }
                    self.dispatch(Event::InterventionFinished(result));
                }
                Pending::Attempt(c) => {
                    // The supervisor may speak before every attempt.
                    let moment = Moment {
                        attempts: self.attempts_started,
                        now: self.clock.now(),
                        mid_step: false,
                        committed: false,
                    };
                    journal_refused(&mut *self.supervisor, &mut self.ctx, &*self.clock);
                    if let Some(command) = self.supervisor.poll(&moment) {
                        self.arriving();
                        self.dispatch(Event::Supervisor(command));
                        continue;
                    }
                    self.attempt(c);
                }
                Pending::Decide(c) => self.decide(c),
                Pending::Checkpoint(c) => {
                    let label = match self.machine.inner().op(c) {
                        Some(Op::Checkpoint { label, .. }) => label.clone(),
                        _ => String::new(),
                    };
                    self.ctx.journal.set_now(self.clock.now());
                    self.ctx.journal.push(Entry::Checkpoint {
                        throw: c.throw,
                        step: c.step,
                        label: label.clone(),
                    });
                    let at_s = self.clock.now().as_secs_f64();
                    let request = CheckpointRequest {
                        throw: c.throw,
                        step: c.step,
                        label,
                    };
                    let answer = self.supervisor.checkpoint(&request);
                    journal_refused(&mut *self.supervisor, &mut self.ctx, &*self.clock);
                    if let Some(t) = self.throws.get_mut(c.throw) {
                        t.checkpoints.push(CheckpointSeen {
                            step: c.step,
                            at_s,
                            label: request.label,
                            answer,
                        });
                    }
                    let event = match answer {
                        Some(command) => {
                            self.arriving();
                            Event::Supervisor(command)
                        }
                        None => Event::SupervisorLost,
                    };
                    self.dispatch(event);
                    self.note_throw_left(c.throw);
                }
            }
        }
        self.finish()
    }

    /// Observe, decide the condition at `c`, journal it with what it was decided on.
    fn decide(&mut self, c: Cursor) {
        let plan = Arc::clone(self.machine.inner().plan_arc());
        let throw = &plan.throws[c.throw];
        let Some(Op::Branch { cond, role, .. }) = throw.program.get(c.step) else {
            // The machine decides only at branches: nothing to decide is a false condition.
            self.dispatch(Event::Decided(false));
            return;
        };
        let needle_at = match self.holders.get(c.throw).and_then(|t| t.get(c.step)) {
            Some(Some(NeedleHolder::Tissue)) => NeedleAt::Tissue,
            Some(Some(NeedleHolder::Left)) => NeedleAt::LeftJaw,
            _ => NeedleAt::RightJaw,
        };
        self.ctx.journal.set_now(self.clock.now());
        let observation = self.primitives.observe(&ObserveRequest {
            throw: c.throw,
            point: &throw.point,
            needle: cond.needs_needle(),
            thread: cond.needs_thread(),
            needle_at,
        });
        let now = self.clock.now();
        let mission = self.machine.inner().facts(c);
        if observation.scripted.is_none()
            && !observation.faults.is_empty()
            && cond.eval_known(&mission).is_none()
        {
            // Not decided on what the robot could not observe: journaled with what it did
            // observe, then a failure in the needle's phase (the surgeon asked, or the end).
            let message = format!(
                "condition `{cond}` not decided: the robot could not observe it ({})",
                observation.faults.join("; ")
            );
            self.ctx.journal.set_now(now);
            self.ctx.journal.push(Entry::Unobserved {
                throw: c.throw,
                step: c.step,
                condition: cond.to_string(),
                role: *role,
                observation,
                mission,
            });
            self.dispatch(Event::StepFinished(StepOutcome::Failed(Failure {
                kind: FailureKind::ArmFault { message },
                measured: Measurements::default(),
            })));
            self.note_throw_left(c.throw);
            return;
        }
        let value = observation.scripted.unwrap_or_else(|| {
            cond.eval(&Facts {
                observation: &observation,
                now_s: now.as_secs_f64(),
                mission,
            })
        });
        if let Some(t) = self.throws.get_mut(c.throw) {
            t.decisions.push(Decision {
                step: c.step,
                at_s: now.as_secs_f64(),
                condition: cond.to_string(),
                value,
            });
        }
        self.ctx.journal.set_now(now);
        self.ctx.journal.push(Entry::Condition {
            throw: c.throw,
            step: c.step,
            condition: cond.to_string(),
            role: *role,
            value,
            observation,
            mission,
        });
        self.dispatch(Event::Decided(value));
        self.note_throw_left(c.throw);
    }

    /// If the machine has left throw `throw` for a later one (or completed), the throw is
    /// done: its steps ran to its end on their path.
    fn note_throw_left(&mut self, throw: usize) {
        let left = match self.machine.state() {
            State::Completed {} => true,
            s => state_parts(s).1.is_some_and(|c| c.throw > throw),
        };
        if left {
            if let Some(t) = self.throws.get_mut(throw) {
                t.completed = true;
            }
        }
    }

    fn step_name(&self, c: Cursor) -> &'static str {
        self.machine.inner().step_kind(c).map_or("?", |k| k.name())
    }

    fn attempt(&mut self, c: Cursor) {
        let plan = Arc::clone(self.machine.inner().plan_arc());
        let throw = &plan.throws[c.throw];
        let Some(step) = throw.step(c.step) else {
            // The machine attempts only steps: an operation that is not one is an engine bug
            // surfacing; fail it safely rather than move.
            self.dispatch(Event::StepFinished(StepOutcome::Failed(Failure {
                kind: FailureKind::ArmFault {
                    message: "engine: no step at this point of the plan".into(),
                },
                measured: Measurements::default(),
            })));
            return;
        };
        let summary = &mut self.throws[c.throw];
        let attempt = summary.attempts.iter().filter(|a| a.step == c.step).count() as u32;
        let start = self.clock.now();
        self.ctx.journal.set_now(start);
        self.ctx.journal.push(Entry::StepStart {
            throw: c.throw,
            step: c.step,
            primitive: step.kind.name().into(),
            attempt,
        });
        self.attempts_started += 1;
        let request = StepRequest {
            throw: c.throw,
            step: c.step,
            point: &throw.point,
            kind: &step.kind,
            attempt,
        };
        let mut live = Live {
            machine: &mut self.machine,
            ctx: &mut self.ctx,
            supervisor: &mut *self.supervisor,
            clock: &*self.clock,
            during: During {
                throw: c.throw,
                step: c.step,
                attempt,
                committed: false,
            },
            attempts: self.attempts_started,
            stopped: false,
        };
        let outcome = self.primitives.run(&request, &mut live);
        let stopped = live.stopped;
        let end = self.clock.now();
        self.ctx.journal.set_now(end);
        self.ctx.journal.push(Entry::StepEnd {
            throw: c.throw,
            step: c.step,
            primitive: step.kind.name().into(),
            attempt,
            outcome: outcome.clone(),
        });
        let summary = &mut self.throws[c.throw];
        let seen = Attempt {
            step: c.step,
            primitive: step.kind.name(),
            attempt,
            start_s: start.as_secs_f64(),
            duration_s: end.saturating_sub(start).as_secs_f64(),
            outcome: outcome.clone(),
            intervention: None,
        };
        if let Some(sink) = self.on_attempt.as_mut() {
            sink(c.throw, &seen);
        }
        summary.attempts.push(seen);
        if stopped {
            // The supervisor ended the attempt; the machine already went where the command
            // leads (taken over, aborted).
            return;
        }
        let outcome = match outcome {
            // Only a command ends an attempt early; a primitive that says otherwise is a
            // bug, failed safely.
            StepOutcome::Interrupted { measured, .. } => StepOutcome::Failed(Failure {
                kind: FailureKind::ArmFault {
                    message: "engine: the step stopped with no command to stop it".into(),
                },
                measured,
            }),
            o => o,
        };
        self.dispatch(Event::StepFinished(outcome));
        self.note_throw_left(c.throw);
    }

    fn finish(mut self) -> Report {
        // Retries granted, as the machine journaled them. (Counting attempts whose cursor
        // had retries also counted the re-run after a recovered intervention: a property
        // test rebuilding reports from journals found it.)
        for r in self.ctx.journal.records() {
            if let Entry::Retry { throw, .. } = r.entry {
                if let Some(t) = self.throws.get_mut(throw) {
                    t.retries += 1;
                }
            }
        }
        let mission = self.machine.inner();
        let outcome = match self.machine.state() {
            State::Completed {} => RunOutcome::Completed,
            State::Failed { cursor, class } => RunOutcome::Failed {
                class: *class,
                throw: cursor.throw,
                step: cursor.step,
                primitive: mission.step_kind(*cursor).map_or("?", |k| k.name()).into(),
                reason: mission.last_failure().map(|f| f.kind.clone()),
            },
            State::Aborted { cursor, by } => RunOutcome::Aborted {
                by: *by,
                throw: cursor.throw,
                step: cursor.step,
            },
            other => unreachable_state(state_parts(other).0),
        };
        let interventions = mission.interventions_used();
        self.ctx.journal.set_now(self.clock.now());
        self.ctx.journal.push(Entry::Finished {
            outcome: outcome.clone(),
        });
        Report {
            outcome,
            throws: self.throws,
            interventions,
            duration_s: self.clock.now().as_secs_f64(),
            journal: {
                let mut journal = std::mem::take(&mut self.ctx.journal);
                journal.stop_streaming();
                journal
            },
        }
    }
}

/// Dispatch `event`, then perform the effects the machine asks for (`hold`: stop every motion
/// and hold both arms).
fn dispatch(
    machine: &mut InitializedStateMachine<Mission>,
    ctx: &mut Ctx,
    clock: &dyn Clock,
    hold: &mut dyn FnMut() -> Result<(), PrimitiveError>,
    event: Event,
) {
    ctx.journal.set_now(clock.now());
    machine.handle_with_context(&event, ctx);
    for effect in std::mem::take(&mut ctx.effects) {
        match effect {
            Effect::HoldArms => {
                let error = hold().err().map(|e| e.to_string());
                ctx.journal.set_now(clock.now());
                ctx.journal.push(Entry::Hold {
                    state: state_label(machine.state()),
                    error,
                });
            }
        }
    }
}

/// The supervisor's next command while the run waits on it; a schedule's timed command is
/// waited for on the run's clock (a simulated one advances to it).
fn wait_command(
    supervisor: &mut dyn Supervisor,
    clock: &dyn Clock,
    ctx: &mut Ctx,
    attempts: usize,
) -> Event {
    let moment = Moment {
        attempts,
        now: clock.now(),
        mid_step: false,
        committed: false,
    };
    if let Some(NextPoll::In(d)) = supervisor.next_poll(&moment) {
        clock.sleep(d);
    }
    journal_refused(supervisor, ctx, clock);
    let command = supervisor.wait();
    journal_refused(supervisor, ctx, clock);
    match command {
        Some(command) => {
            ctx.arrival = Arrival {
                from: Some(supervisor.source().to_string()),
                during: None,
            };
            Event::Supervisor(command)
        }
        None => Event::SupervisorLost,
    }
}

/// Journal the commands the supervisor refused since it was last asked.
fn journal_refused(supervisor: &mut dyn Supervisor, ctx: &mut Ctx, clock: &dyn Clock) {
    while let Some(r) = supervisor.refused() {
        ctx.journal.set_now(clock.now());
        ctx.journal.push(Entry::Refused {
            command: r.command,
            from: r.from,
            why: r.why,
        });
    }
}

/// What a running step asks of the engine: the supervisor's commands, heard mid-step.
struct Live<'r> {
    machine: &'r mut InitializedStateMachine<Mission>,
    ctx: &'r mut Ctx,
    supervisor: &'r mut dyn Supervisor,
    clock: &'r dyn Clock,
    during: During,
    attempts: usize,
    /// The supervisor ended the attempt (take-over, abort, e-stop, gone while paused).
    stopped: bool,
}

impl Live<'_> {
    /// Whether the machine is (back) in the step this attempt runs.
    fn in_step(&self) -> bool {
        matches!(pending(self.machine.state()), Pending::Attempt(c)
            if c.throw == self.during.throw && c.step == self.during.step)
    }
}

impl StepControl for Live<'_> {
    fn slice(&mut self) -> Option<Duration> {
        let moment = Moment {
            attempts: self.attempts,
            now: self.clock.now(),
            mid_step: true,
            committed: self.during.committed,
        };
        match self.supervisor.next_poll(&moment)? {
            NextPoll::In(d) => Some(d),
            // A person's command is waited for at most this much wall time: on a paced
            // simulated clock that much simulated time at its pace, unpaced the same.
            NextPoll::Every(w) => Some(w.mul_f64(self.clock.pace().unwrap_or(1.0))),
        }
    }

    fn commit(&mut self) {
        self.during.committed = true;
    }

    fn check(&mut self, hold: &mut dyn FnMut() -> Result<(), PrimitiveError>) -> Control {
        if self.stopped {
            return Control::Stop;
        }
        let moment = Moment {
            attempts: self.attempts,
            now: self.clock.now(),
            mid_step: true,
            committed: self.during.committed,
        };
        journal_refused(self.supervisor, self.ctx, self.clock);
        let Some(command) = self.supervisor.poll(&moment) else {
            return Control::Go;
        };
        self.ctx.arrival = Arrival {
            from: Some(self.supervisor.source().to_string()),
            during: Some(self.during),
        };
        let event = Event::Interrupt {
            command,
            committed: self.during.committed,
        };
        dispatch(self.machine, self.ctx, self.clock, hold, event);
        let mut paused = false;
        loop {
            if self.in_step() {
                return if paused {
                    Control::Resumed
                } else {
                    Control::Go
                };
            }
            if !matches!(self.machine.state(), State::Paused { .. }) {
                // Taken over, aborted: the attempt ends here.
                self.stopped = true;
                return Control::Stop;
            }
            paused = true;
            let event = wait_command(self.supervisor, self.clock, self.ctx, self.attempts);
            dispatch(self.machine, self.ctx, self.clock, hold, event);
        }
    }
}

/// The loop only leaves terminal states, and every other state has a cursor: reaching this
/// is a bug in the engine, not bad input.
#[allow(clippy::panic)]
fn unreachable_state(name: &str) -> ! {
    panic!("engine bug: the runner cannot act in state `{name}`")
}

/// What a journal says about the plan it ran (its first record).
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct PlanHeader {
    /// Mission name.
    pub name: String,
    /// Script file.
    pub file: String,
    /// Number of throws.
    pub throws: usize,
    /// Intervention budget.
    pub interventions: u8,
    /// The seed of a simulated run.
    pub seed: Option<u64>,
}

/// A run's report rebuilt from its journal alone (a recorded run, perhaps cut short by a
/// crash): the per-throw summaries as the runner keeps them.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Rebuilt {
    /// The plan.
    pub plan: PlanHeader,
    /// One summary per throw of the plan.
    pub throws: Vec<ThrowSummary>,
    /// Interventions requested.
    pub interventions: u8,
    /// Time of the last record, s.
    pub duration_s: f64,
    /// How it ended; `None` if the journal stops before the end.
    pub outcome: Option<RunOutcome>,
    /// A step attempt that began and has no end in the journal (it stops mid-step).
    pub under_way: Option<UnderWay>,
}

/// A step attempt under way where a journal stops.
#[derive(Clone, Debug, PartialEq, Eq, Serialize)]
pub struct UnderWay {
    /// Throw index, 0-based.
    pub throw: usize,
    /// Step index, 0-based.
    pub step: usize,
    /// Step name.
    pub primitive: String,
    /// Attempt, 0-based.
    pub attempt: u32,
    /// When it began, s (as an integer number of ns, so the type stays `Eq`).
    pub start_ns: u64,
}

impl Rebuilt {
    /// Rebuild from `records`, which must begin with the plan record. Records that name a
    /// throw the plan does not have are an error (the journal is not this plan's).
    /// A throw is done when its last attempt succeeded and the run went on to a later throw
    /// (a step, a condition or a checkpoint there, or the run ended there) or completed; or,
    /// where `steps_per_throw` (program lengths) is known, when that attempt was at the
    /// program's last operation.
    pub fn from_journal(
        records: &[crate::Record],
        steps_per_throw: Option<&[usize]>,
    ) -> Result<Self, String> {
        let Some(Entry::Plan {
            name,
            file,
            throws,
            interventions,
            seed,
            ..
        }) = records.first().map(|r| &r.entry)
        else {
            return Err("the journal does not begin with its plan record".into());
        };
        let mut out = Self {
            plan: PlanHeader {
                name: name.clone(),
                file: file.clone(),
                throws: *throws,
                interventions: *interventions,
                seed: *seed,
            },
            throws: vec![ThrowSummary::default(); *throws],
            interventions: 0,
            duration_s: 0.0,
            outcome: None,
            under_way: None,
        };
        let mut started: Option<f64> = None;
        let mut reached: Option<usize> = None;
        let mut waiting: Option<usize> = None;
        for r in &records[1..] {
            out.duration_s = r.t_s;
            let throw = |t: usize, out: &mut Self| -> Result<usize, String> {
                if t < out.throws.len() {
                    Ok(t)
                } else {
                    Err(format!(
                        "record {}: throw {} of a plan of {} throws",
                        r.seq,
                        t + 1,
                        out.throws.len()
                    ))
                }
            };
            match &r.entry {
                Entry::StepStart {
                    throw: t,
                    step,
                    primitive,
                    attempt,
                } => {
                    started = Some(r.t_s);
                    out.under_way = Some(UnderWay {
                        throw: throw(*t, &mut out)?,
                        step: *step,
                        primitive: primitive.clone(),
                        attempt: *attempt,
                        start_ns: (r.t_s.max(0.0) * 1e9).round() as u64,
                    });
                }
                Entry::StepEnd {
                    throw: t,
                    step,
                    primitive,
                    attempt,
                    outcome,
                } => {
                    let t = throw(*t, &mut out)?;
                    out.under_way = None;
                    let start = started.take().unwrap_or(r.t_s);
                    let primitive = stitch_primitives::StepKind::default_for(primitive)
                        .map(|k| k.name())
                        .ok_or_else(|| format!("record {}: no step `{primitive}`", r.seq))?;
                    out.throws[t].attempts.push(Attempt {
                        step: *step,
                        primitive,
                        attempt: *attempt,
                        start_s: start,
                        duration_s: r.t_s - start,
                        outcome: outcome.clone(),
                        intervention: None,
                    });
                }
                Entry::Retry { throw: t, .. } => {
                    let t = throw(*t, &mut out)?;
                    out.throws[t].retries += 1;
                }
                Entry::InterventionRequested { throw: t, .. } => {
                    let t = throw(*t, &mut out)?;
                    out.throws[t].interventions += 1;
                    out.interventions = out.interventions.saturating_add(1);
                }
                Entry::InterventionEnded {
                    throw: t, result, ..
                } => {
                    let t = throw(*t, &mut out)?;
                    if let Some(last) = out.throws[t].attempts.last_mut() {
                        last.intervention = Some(*result);
                    }
                }
                Entry::Finished { outcome } => out.outcome = Some(outcome.clone()),
                Entry::Plan { .. } => {
                    return Err(format!("record {}: a second plan record", r.seq));
                }
                Entry::Condition {
                    throw: t,
                    step,
                    condition,
                    value,
                    ..
                } => {
                    let t = throw(*t, &mut out)?;
                    reached = reached.max(Some(t));
                    out.throws[t].decisions.push(Decision {
                        step: *step,
                        at_s: r.t_s,
                        condition: condition.clone(),
                        value: *value,
                    });
                }
                Entry::Checkpoint {
                    throw: t,
                    step,
                    label,
                } => {
                    let t = throw(*t, &mut out)?;
                    reached = reached.max(Some(t));
                    out.throws[t].checkpoints.push(CheckpointSeen {
                        step: *step,
                        at_s: r.t_s,
                        label: label.clone(),
                        answer: None,
                    });
                    waiting = Some(t);
                }
                // The command that answers a checkpoint is the next one journaled.
                Entry::Supervisor { command, .. } => {
                    if let Some(t) = waiting.take() {
                        if let Some(c) = out.throws[t].checkpoints.last_mut() {
                            c.answer = Some(*command);
                        }
                    }
                }
                Entry::Unobserved { throw: t, .. } => {
                    let t = throw(*t, &mut out)?;
                    reached = reached.max(Some(t));
                }
                Entry::Transition { .. } | Entry::Hold { .. } | Entry::Refused { .. } => {}
            }
        }
        // The last throw the run reached: by a step, a condition, a checkpoint, or where it
        // ended.
        let ended_at = match &out.outcome {
            Some(RunOutcome::Failed { throw, .. } | RunOutcome::Aborted { throw, .. }) => {
                Some(*throw)
            }
            _ => None,
        };
        let last_started = out
            .throws
            .iter()
            .rposition(|t| !t.attempts.is_empty())
            .max(reached)
            .max(ended_at);
        let completed = matches!(out.outcome, Some(RunOutcome::Completed));
        for (i, t) in out.throws.iter_mut().enumerate() {
            let last_ok = t
                .attempts
                .last()
                .filter(|a| matches!(a.outcome, StepOutcome::Succeeded { .. }));
            let later = Some(i) < last_started || completed;
            t.completed = match (last_ok, steps_per_throw.and_then(|s| s.get(i))) {
                (Some(a), Some(steps)) => a.step + 1 == *steps || later,
                (Some(_), None) => later,
                (None, _) => false,
            };
        }
        Ok(out)
    }
}
