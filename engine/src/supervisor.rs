//! The supervising surgeon, as the engine sees them: commands at any moment (between steps,
//! and in the middle of one while it moves), and interventions the robot requests.

use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::fmt;
use std::str::FromStr;
use std::time::Duration;

use crate::plan::FailureClass;

/// A command from the supervising surgeon.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SupervisorCommand {
    /// Stop before the next step; the arms hold.
    Pause,
    /// Go on from a pause with the step that was next.
    Resume,
    /// End the run; the arms hold; no further motion.
    Abort,
    /// Emergency stop: as abort, recorded as such.
    EStop,
    /// The surgeon teleoperates; the engine commands nothing until hand-back.
    TakeOver,
    /// The surgeon hands control back; the engine re-runs the step that was next.
    HandBack,
    /// At a plan's checkpoint: the surgeon confirms, the plan goes on (ignored elsewhere).
    Go,
}

impl SupervisorCommand {
    /// Every command.
    pub const ALL: [SupervisorCommand; 7] = [
        SupervisorCommand::Pause,
        SupervisorCommand::Resume,
        SupervisorCommand::Abort,
        SupervisorCommand::EStop,
        SupervisorCommand::TakeOver,
        SupervisorCommand::HandBack,
        SupervisorCommand::Go,
    ];

    /// The command as written in schedules.
    pub fn as_str(&self) -> &'static str {
        match self {
            SupervisorCommand::Pause => "pause",
            SupervisorCommand::Resume => "resume",
            SupervisorCommand::Abort => "abort",
            SupervisorCommand::EStop => "e-stop",
            SupervisorCommand::TakeOver => "take-over",
            SupervisorCommand::HandBack => "hand-back",
            SupervisorCommand::Go => "go",
        }
    }
}

impl fmt::Display for SupervisorCommand {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

impl FromStr for SupervisorCommand {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, Self::Err> {
        Self::ALL
            .iter()
            .copied()
            .find(|c| c.as_str() == s)
            .ok_or_else(|| {
                let names: Vec<_> = Self::ALL.iter().map(Self::as_str).collect();
                format!(
                    "unknown supervisor command `{s}`; expected one of {}",
                    names.join(", ")
                )
            })
    }
}

/// How a requested intervention ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InterventionResult {
    /// The surgeon's recovery motion returned the workspace to a safe configuration; the
    /// engine re-runs the failed step.
    Recovered,
    /// The surgeon could not recover; the run fails with the step's class.
    Failed,
}

/// What the robot tells the surgeon when it asks for help.
#[derive(Clone, Debug, PartialEq)]
pub struct InterventionRequest {
    /// Throw index, 0-based.
    pub throw: usize,
    /// Step index, 0-based.
    pub step: usize,
    /// The failed step's name.
    pub primitive: &'static str,
    /// The failure's class.
    pub class: FailureClass,
}

/// When the engine asks a supervisor for a command.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Moment {
    /// How many step attempts the run has started.
    pub attempts: usize,
    /// The run's time (simulated, or the robot's), since its start.
    pub now: Duration,
    /// Whether a step attempt is under way (asked between its motions, or during one), or
    /// the run is between steps (asked before the next attempt).
    pub mid_step: bool,
    /// Mid-step: whether the step has passed its commit point.
    pub committed: bool,
}

/// Where in a step attempt a scheduled command lands (model-checker paths replayed).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum InStep {
    /// At the first chance in the attempt.
    Start,
    /// At the first chance once the step has passed its commit point.
    Committed,
}

/// When a supervisor wants to be asked again while a step runs.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NextPoll {
    /// After this much time on the run's clock (a command scheduled at a simulated time).
    In(Duration),
    /// Every this much wall-clock time (a person, whose commands come whenever they come;
    /// on a paced simulated clock the engine turns it into simulated time).
    Every(Duration),
}

/// How often the engine asks a person's supervisor for a command while a step moves: the
/// bound, in wall-clock time, on how long a command waits before the arms hold.
pub const LIVE_POLL: Duration = Duration::from_millis(2);

/// The supervising surgeon. A real one sits at the console; [`ScriptedSupervisor`] follows a
/// schedule in tests and simulated runs.
pub trait Supervisor {
    /// A command given since the last poll, if any: asked before every step attempt, and
    /// while one runs, between its motions and every [`Supervisor::next_poll`] during one.
    fn poll(&mut self, at: &Moment) -> Option<SupervisorCommand>;

    /// When to ask again while a step runs (`None`: not before the step ends, or its next
    /// motion does); `at` is now.
    fn next_poll(&self, at: &Moment) -> Option<NextPoll> {
        let _ = at;
        None
    }

    /// Where the commands come from, as the journal records it: `terminal`, `schedule`, ...
    fn source(&self) -> &str {
        "supervisor"
    }

    /// A command refused since the last call (by a console's guard, say), to journal: the
    /// engine asks until `None` whenever it asks for a command.
    fn refused(&mut self) -> Option<Refusal> {
        None
    }

    /// Wait for the next command while the run is paused or taken over; `None` means the
    /// supervisor is gone and the run must abort.
    fn wait(&mut self) -> Option<SupervisorCommand>;

    /// The surgeon, who took over, hands back: the run goes on at `to`. A supervisor that
    /// readies the workspace for it (a simulated surgeon) does so here, and says `hand-back`,
    /// or `abort` if it could not; a person has done so before saying `hand-back`.
    fn hand_back(&mut self, to: &Resumption) -> SupervisorCommand {
        let _ = to;
        SupervisorCommand::HandBack
    }

    /// Perform the intervention the robot asked for and say how it ended.
    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult;

    /// The plan reached a checkpoint; the arms hold. Wait for the surgeon's answer: `go`,
    /// or `abort`, `e-stop`, `take-over`; `None` means the supervisor is gone and the run
    /// must abort.
    fn checkpoint(&mut self, request: &CheckpointRequest) -> Option<SupervisorCommand>;
}

/// A command refused before it reached the machine, and why ([`Supervisor::refused`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Refusal {
    /// What was asked, as it was written.
    pub command: String,
    /// Who asked.
    pub from: String,
    /// Why it was refused.
    pub why: String,
}

/// Where the run goes on after a hand-back.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Resumption {
    /// Throw index, 0-based.
    pub throw: usize,
    /// Program index, 0-based: the interrupted step's, or the one after it if the step had
    /// passed its commit point (possibly past the throw's end: the next throw's start).
    pub step: usize,
}

/// What the robot tells the surgeon at a checkpoint.
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct CheckpointRequest {
    /// Throw index, 0-based.
    pub throw: usize,
    /// Program index, 0-based.
    pub step: usize,
    /// What the surgeon confirms, as the plan says.
    pub label: String,
}

/// A command scheduled before a given step attempt, or at a time on the run's clock.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimedCommand {
    /// Delivered before a step attempt, at the first poll between steps once this many step
    /// attempts have started (with `at_s`: not before then).
    #[serde(default)]
    pub at: usize,
    /// Delivered at the first poll at or after this time on the run's clock, s: in the
    /// middle of a step (and its motion) as well as between steps.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub at_s: Option<f64>,
    /// Delivered in the middle of the attempt that `at` attempts started make (the `at`-th,
    /// 1-based): at its start, or once it has committed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub in_step: Option<InStep>,
    /// The command.
    pub command: SupervisorCommand,
}

impl TimedCommand {
    /// `command` before the attempt once `at` attempts have started.
    pub fn before(at: usize, command: SupervisorCommand) -> Self {
        Self {
            at,
            at_s: None,
            in_step: None,
            command,
        }
    }

    /// `command` in the middle of the `at`-th attempt (1-based), where `in_step` says.
    pub fn in_attempt(at: usize, in_step: InStep, command: SupervisorCommand) -> Self {
        Self {
            at,
            at_s: None,
            in_step: Some(in_step),
            command,
        }
    }

    /// `command` at `at_s` seconds on the run's clock, mid-step or not.
    pub fn at_time(at_s: f64, command: SupervisorCommand) -> Self {
        Self {
            at: 0,
            at_s: Some(at_s),
            in_step: None,
            command,
        }
    }

    /// When it is due on the run's clock, if it is timed.
    fn due(&self) -> Option<Duration> {
        self.at_s
            .map(|s| Duration::try_from_secs_f64(s.max(0.0)).unwrap_or(Duration::MAX))
    }
}

/// A supervisor that follows a schedule.
///
/// Commands are delivered in order: one with only `at`, at the first poll between steps once
/// `at` step attempts have started; one with `at_s`, at the first poll at or after that time
/// (between steps or mid-step), once `at` attempts have started. While paused or taken over,
/// the next scheduled command is delivered whatever its `at` (at its `at_s`: the engine lets
/// the run's clock reach it); once the schedule is empty the supervisor is silent and the run
/// aborts, arms held.
/// Interventions end as the `interventions` list says, `Recovered` once it is exhausted;
/// checkpoints are answered as the `checkpoints` list says, `go` once it is exhausted.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct ScriptedSupervisor {
    commands: VecDeque<TimedCommand>,
    interventions: VecDeque<InterventionResult>,
    checkpoints: VecDeque<SupervisorCommand>,
    /// Every intervention request received, in order.
    pub requests: Vec<InterventionRequest>,
    /// Every checkpoint reached, in order.
    pub checkpoints_reached: Vec<CheckpointRequest>,
}

impl ScriptedSupervisor {
    /// A supervisor with this schedule.
    pub fn new(
        commands: impl IntoIterator<Item = TimedCommand>,
        interventions: impl IntoIterator<Item = InterventionResult>,
    ) -> Self {
        Self {
            commands: commands.into_iter().collect(),
            interventions: interventions.into_iter().collect(),
            checkpoints: VecDeque::new(),
            requests: Vec::new(),
            checkpoints_reached: Vec::new(),
        }
    }

    /// Checkpoints are answered with these, in order (`go` once they run out).
    pub fn with_checkpoints(
        mut self,
        answers: impl IntoIterator<Item = SupervisorCommand>,
    ) -> Self {
        self.checkpoints = answers.into_iter().collect();
        self
    }
}

impl Supervisor for ScriptedSupervisor {
    fn poll(&mut self, at: &Moment) -> Option<SupervisorCommand> {
        let due = self.commands.front().is_some_and(|c| {
            c.at <= at.attempts
                && match (c.in_step, c.due()) {
                    (Some(InStep::Start), _) => at.mid_step,
                    (Some(InStep::Committed), _) => at.mid_step && at.committed,
                    (None, Some(t)) => t <= at.now,
                    (None, None) => !at.mid_step,
                }
        });
        if due {
            self.commands.pop_front().map(|c| c.command)
        } else {
            None
        }
    }

    fn next_poll(&self, at: &Moment) -> Option<NextPoll> {
        let c = self.commands.front()?;
        if c.at > at.attempts {
            return None;
        }
        let now = at.now;
        match c.in_step {
            // At once: the first check of the attempt delivers it.
            Some(InStep::Start) => Some(NextPoll::In(Duration::ZERO)),
            // At the first check after the commit (a primitive checks after every motion).
            Some(InStep::Committed) => None,
            None => Some(NextPoll::In(c.due()?.saturating_sub(now))),
        }
    }

    fn source(&self) -> &str {
        "schedule"
    }

    fn wait(&mut self) -> Option<SupervisorCommand> {
        self.commands.pop_front().map(|c| c.command)
    }

    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        self.requests.push(request.clone());
        self.interventions
            .pop_front()
            .unwrap_or(InterventionResult::Recovered)
    }

    fn checkpoint(&mut self, request: &CheckpointRequest) -> Option<SupervisorCommand> {
        self.checkpoints_reached.push(request.clone());
        Some(
            self.checkpoints
                .pop_front()
                .unwrap_or(SupervisorCommand::Go),
        )
    }
}
