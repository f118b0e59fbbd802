//! The supervising surgeon, as the engine sees them: commands between steps, and
//! interventions the robot requests.

use serde::{Deserialize, Serialize};
use std::collections::VecDeque;
use std::fmt;
use std::str::FromStr;

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

/// The supervising surgeon. A real one sits at the console; [`ScriptedSupervisor`] follows a
/// schedule in tests and simulated runs.
pub trait Supervisor {
    /// A command given since the last poll, if any; asked before every step attempt.
    /// `attempts` is how many step attempts the run has started.
    fn poll(&mut self, attempts: usize) -> Option<SupervisorCommand>;

    /// Wait for the next command while the run is paused or taken over; `None` means the
    /// supervisor is gone and the run must abort.
    fn wait(&mut self) -> Option<SupervisorCommand>;

    /// Perform the intervention the robot asked for and say how it ended.
    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult;

    /// The plan reached a checkpoint; the arms hold. Wait for the surgeon's answer: `go`,
    /// or `abort`, `e-stop`, `take-over`; `None` means the supervisor is gone and the run
    /// must abort.
    fn checkpoint(&mut self, request: &CheckpointRequest) -> Option<SupervisorCommand>;
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

/// A command scheduled before a given step attempt.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TimedCommand {
    /// Delivered at the first poll once this many step attempts have started.
    pub at: usize,
    /// The command.
    pub command: SupervisorCommand,
}

/// A supervisor that follows a schedule.
///
/// Commands are delivered in order, each at the first poll once `at` step attempts have
/// started. While paused or taken over, the next scheduled command is delivered whatever its
/// `at`; once the schedule is empty the supervisor is silent and the run aborts, arms held.
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
    fn poll(&mut self, attempts: usize) -> Option<SupervisorCommand> {
        if self.commands.front().is_some_and(|c| c.at <= attempts) {
            self.commands.pop_front().map(|c| c.command)
        } else {
            None
        }
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
