//! The supervising surgeon's stand-in on the mock dVRK.

use std::sync::Arc;
use std::sync::mpsc::Receiver;
use stitch_engine::{
    CheckpointRequest, InterventionRequest, InterventionResult, LIVE_POLL, Moment, NeedleHolder,
    NextPoll, Plan, Refusal, Resumption, ScriptedSupervisor, Supervisor, SupervisorCommand,
    TimedCommand,
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
    /// A console's commands, each with who sent it; a checkpoint waits for its answer.
    named: Option<Receiver<(String, String)>>,
    /// Who sent the last command heard from `named`.
    from: String,
    /// Commands a console refused, for the journal.
    refusals: Option<Receiver<Refusal>>,
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
            named: None,
            from: String::new(),
            refusals: None,
        }
    }

    /// The same, giving the commands that come through `feed` as they come (asked every
    /// [`LIVE_POLL`] while a step moves).
    pub fn fed(mut self, feed: Receiver<SupervisorCommand>) -> Self {
        self.feed = Some(feed);
        self.source = "live";
        self
    }

    /// The same, commanded by a person at the web console: its commands as they come, its
    /// refusals journaled, its answer awaited at every checkpoint. Interventions are still
    /// the simulated surgeon's (a person cannot move the mock's needle).
    #[cfg(feature = "console")]
    pub fn consoled(mut self, feeds: crate::ConsoleFeeds) -> Self {
        self.named = Some(feeds.commands);
        self.refusals = Some(feeds.refusals);
        self.source = "console";
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
        if let Some(named) = &self.named {
            let (word, from) = named.try_recv().ok()?;
            self.from = from;
            return word.parse().ok();
        }
        match &self.feed {
            Some(feed) => feed.try_recv().ok(),
            None => self.commands.poll(at),
        }
    }

    fn next_poll(&self, at: &Moment) -> Option<NextPoll> {
        if self.named.is_some() {
            return Some(NextPoll::Every(LIVE_POLL));
        }
        match &self.feed {
            Some(_) => Some(NextPoll::Every(LIVE_POLL)),
            None => self.commands.next_poll(at),
        }
    }

    fn source(&self) -> &str {
        if self.named.is_some() {
            &self.from
        } else {
            self.source
        }
    }

    fn refused(&mut self) -> Option<Refusal> {
        self.refusals.as_ref()?.try_recv().ok()
    }

    /// The next scheduled command, if any; with none left, the run aborts.
    fn wait(&mut self) -> Option<SupervisorCommand> {
        if let Some(named) = &self.named {
            loop {
                let (word, from) = named.recv().ok()?;
                self.from = from;
                if let Ok(c) = word.parse() {
                    return Some(c);
                }
            }
        }
        match &self.feed {
            Some(feed) => feed.recv().ok(),
            None => self.commands.wait(),
        }
    }

    /// The simulated surgeon readies the workspace for the step the run goes on at, as after
    /// an intervention: the needle where the plan has it then (one recovery motion).
    fn hand_back(&mut self, to: &Resumption) -> SupervisorCommand {
        let needs = match self
            .plan
            .holders()
            .get(to.throw)
            .and_then(|t| t.get(to.step).copied().flatten())
        {
            Some(NeedleHolder::Tissue) => NeedlePlace::Tissue,
            Some(NeedleHolder::Left) => NeedlePlace::Left,
            // In the right jaw, or past the throw's end: the next throw begins with it there.
            _ => NeedlePlace::Right,
        };
        match (self.recover)(needs) {
            Ok(()) => SupervisorCommand::HandBack,
            Err(e) => {
                eprintln!("hand-back: the workspace could not be readied ({e}); aborting");
                SupervisorCommand::Abort
            }
        }
    }

    /// The simulated supervisor confirms every checkpoint; a console's person is asked.
    fn checkpoint(&mut self, _request: &CheckpointRequest) -> Option<SupervisorCommand> {
        match &self.named {
            Some(named) => loop {
                let (word, from) = named.recv().ok()?;
                self.from = from;
                match word.parse() {
                    Err(_) => {}
                    // A pause or resume answers nothing here; the arms already hold.
                    Ok(SupervisorCommand::Pause | SupervisorCommand::Resume) => {}
                    Ok(c) => return Some(c),
                }
            },
            _ => Some(SupervisorCommand::Go),
        }
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

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::Mutex;

    fn plan() -> Arc<Plan> {
        let spec = stitch_robot::WoundSpec::default();
        let wound = stitch_robot::Wound::linear(&spec).expect("wound");
        let loader = stitch_engine::PlanLoader::new(&wound, stitch_engine::ScriptLimits::default());
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/stitch.rhai");
        Arc::new(stitch_engine::load_plan(&loader, &path).expect("plan").plan)
    }

    #[test]
    fn a_hand_back_readies_the_workspace_for_the_step_the_run_goes_on_at() {
        let asked = Arc::new(Mutex::new(Vec::new()));
        let log = Arc::clone(&asked);
        let mut s = MockSupervisor::with(
            Box::new(move |needs| {
                log.lock().expect("log").push(needs);
                Ok(())
            }),
            plan(),
        );
        // STITCH: insert, sweep, extract, cinch, handover, correct.
        for (step, needs) in [
            (0, NeedlePlace::Right),
            (1, NeedlePlace::Tissue),
            (2, NeedlePlace::Tissue),
            (3, NeedlePlace::Left),
            (4, NeedlePlace::Left),
            (5, NeedlePlace::Right),
            // Past the last step (a committed correction): the next throw's start.
            (6, NeedlePlace::Right),
        ] {
            let c = s.hand_back(&Resumption { throw: 0, step });
            assert_eq!(c, SupervisorCommand::HandBack);
            assert_eq!(asked.lock().expect("log").pop(), Some(needs), "step {step}");
        }
        let mut failing = MockSupervisor::with(Box::new(|_| Err("no side channel".into())), plan());
        assert_eq!(
            failing.hand_back(&Resumption { throw: 1, step: 0 }),
            SupervisorCommand::Abort
        );
    }
}
