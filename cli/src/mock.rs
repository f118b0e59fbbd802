//! The supervising surgeon's stand-in on the mock dVRK.

use std::sync::Arc;
use stitch_engine::{
    CheckpointRequest, InterventionRequest, InterventionResult, NeedleHolder, Plan, Supervisor,
    SupervisorCommand,
};
use stitch_primitives::StepKind;
use stitch_sim::{MockDvrk, NeedlePlace};

/// The recovery motion: readies the workspace with the needle at the given place, or says
/// why it could not.
pub type Recovery = Box<dyn FnMut(NeedlePlace) -> Result<(), String>>;

/// Gives no commands; when the robot asks for help, performs one recovery motion that returns
/// the workspace to a safe configuration for the failed step (`MockDvrk::recover`) and hands
/// control back, as the paper's "STITCH + Human" supervisor does.
pub struct MockSupervisor {
    recover: Recovery,
    plan: Arc<Plan>,
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
        Self { recover, plan }
    }
}

impl Supervisor for MockSupervisor {
    fn poll(&mut self, _attempts: usize) -> Option<SupervisorCommand> {
        None
    }

    fn wait(&mut self) -> Option<SupervisorCommand> {
        None
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
