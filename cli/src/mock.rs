//! The supervising surgeon's stand-in on the mock dVRK.

use std::sync::Arc;
use stitch_engine::{
    InterventionRequest, InterventionResult, NeedleHolder, Plan, Supervisor, SupervisorCommand,
};
use stitch_primitives::StepKind;
use stitch_sim::{MockDvrk, NeedlePlace};

/// Gives no commands; when the robot asks for help, performs one recovery motion that returns
/// the workspace to a safe configuration for the failed step (`MockDvrk::recover`) and hands
/// control back, as the paper's "STITCH + Human" supervisor does.
#[derive(Debug)]
pub struct MockSupervisor {
    world: MockDvrk,
    plan: Arc<Plan>,
}

impl MockSupervisor {
    /// A supervisor for `plan` on `world`.
    pub fn new(world: MockDvrk, plan: Arc<Plan>) -> Self {
        Self { world, plan }
    }
}

impl Supervisor for MockSupervisor {
    fn poll(&mut self, _attempts: usize) -> Option<SupervisorCommand> {
        None
    }

    fn wait(&mut self) -> Option<SupervisorCommand> {
        None
    }

    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        let step = self
            .plan
            .throws
            .get(request.throw)
            .and_then(|t| t.steps.get(request.step));
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
        self.world.recover(needs);
        InterventionResult::Recovered
    }
}
