//! The supervising surgeon's stand-in on the mock dVRK.

use std::sync::Arc;
use std::sync::mpsc::Receiver;
use stitch_engine::{
    CheckpointRequest, InterventionRequest, InterventionResult, LIVE_POLL, Moment, NeedleHolder,
    NextPoll, Plan, ScriptedSupervisor, Supervisor, SupervisorCommand, TimedCommand,
};
use stitch_primitives::StepKind;
use stitch_sim::{MockDvrk, NeedlePlace};

/// The recovery motion: readies the workspace with the needle at the given place, or says
/// why it could not.
pub type Recovery = Box<dyn FnMut(NeedlePlace) -> Result<(), String>>;

/// Gives the commands of its schedule, if it has one (none by default), each at its step or
/// simulated time, mid-step included; when the robot asks for help, performs one recovery
/// motion that returns the workspace to a safe configuration for the failed step
/// (`MockDvrk::recover`) and hands control back, as the paper's "STITCH + Human" supervisor
/// does.
pub struct MockSupervisor {
    recover: Recovery,
    plan: Arc<Plan>,
    commands: ScriptedSupervisor,
    source: &'static str,
    /// Commands given live, from another thread (a benchmark's, a console's).
    feed: Option<Receiver<SupervisorCommand>>,
}

impl std::fmt::Debug for MockSupervisor {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("MockSupervisor").finish_non_exhaustive()
    }
}

impl MockSupervisor {
    /// A supervisor for `plan` on `world`.
    pub fn new(world: MockDvrk, plan: Arc<Plan>) -> Self {
        Self::with(
            Box::new(move |needs| {
                world.recover(needs);
                Ok(())
            }),
            plan,
        )
    }

    /// A supervisor for `plan` whose recovery motion is `recover` (the sim-node's, over ROS 2).
    pub fn with(recover: Recovery, plan: Arc<Plan>) -> Self {
        Self {
            recover,
            plan,
            commands: ScriptedSupervisor::default(),
            source: "mock",
            feed: None,
        }
    }

    /// The same, giving the commands that come through `feed` as they come (asked every
    /// [`LIVE_POLL`] while a step moves).
    pub fn fed(mut self, feed: Receiver<SupervisorCommand>) -> Self {
        self.feed = Some(feed);
        self.source = "live";
        self
    }

    /// The same, giving `commands` (a `--commands` schedule).
    pub fn commanding(mut self, commands: Vec<TimedCommand>) -> Self {
        self.commands = ScriptedSupervisor::new(commands, []);
        self.source = "schedule";
        self
    }
}

impl Supervisor for MockSupervisor {
    fn poll(&mut self, at: &Moment) -> Option<SupervisorCommand> {
        match &self.feed {
            Some(feed) => feed.try_recv().ok(),
            None => self.commands.poll(at),
        }
    }

    fn next_poll(&self, at: &Moment) -> Option<NextPoll> {
        match &self.feed {
            Some(_) => Some(NextPoll::Every(LIVE_POLL)),
            None => self.commands.next_poll(at),
        }
    }

    fn source(&self) -> &str {
        self.source
    }

    /// The next scheduled command, if any; with none left, the run aborts.
    fn wait(&mut self) -> Option<SupervisorCommand> {
        match &self.feed {
            Some(feed) => feed.recv().ok(),
            None => self.commands.wait(),
        }
    }

    /// The simulated supervisor confirms every checkpoint.
    fn checkpoint(&mut self, _request: &CheckpointRequest) -> Option<SupervisorCommand> {
        Some(SupervisorCommand::Go)
    }

    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        let step = self
            .plan
            .throws
            .get(request.throw)
            .and_then(|t| t.step(request.step));
        let needs = match step.map(|s| &s.kind) {
            Some(StepKind::Insert(_) | StepKind::Correct(_)) => NeedlePlace::Right,
            Some(StepKind::Sweep(_) | StepKind::Extract(_)) => NeedlePlace::Tissue,
            Some(StepKind::Cinch(_) | StepKind::Handover(_)) => NeedlePlace::Left,
            // A perception query: wherever the plan has the needle at that point.
            _ => match self
                .plan
                .holders()
                .get(request.throw)
                .and_then(|t| t.get(request.step).copied().flatten())
            {
                Some(NeedleHolder::Tissue) => NeedlePlace::Tissue,
                Some(NeedleHolder::Left) => NeedlePlace::Left,
                _ => NeedlePlace::Right,
            },
        };
        match (self.recover)(needs) {
            Ok(()) => InterventionResult::Recovered,
            Err(e) => {
                eprintln!("intervention failed: {e}");
                InterventionResult::Failed
            }
        }
    }
}
