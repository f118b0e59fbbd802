#![doc = include_str!("../README.md")]

mod condition;
mod explore;
mod journal;
mod machine;
mod params;
mod plan;
mod reference;
mod runner;
mod schedule;
mod script;
mod supervisor;
pub mod trials;
mod validate;

pub use condition::{Cmp, Condition, End, Facts, MissionFacts, Quantity, Target, Unit};
pub use explore::{
    Action, EngineModel, Exploration, ExploreOptions, ExploreState, Needle, PROPERTY_NAMES,
    Verdict, Violation, World, explore, mermaid, schedule_of,
};
pub use journal::{AbortCause, Arrival, During, Entry, Journal, JournalSink, Record, RunOutcome};
pub use machine::{
    Counters, Ctx, Cursor, Effect, Event, Interrupted, Mission, Pending, State, pending,
    recovery_condition, state_label, state_parts,
};
pub use params::{DeclaredParam, ParamValue, Params, parse_param_arg, valid_param_name};
pub use plan::{
    BranchRole, FailureClass, NeedleHolder, Node, Op, Plan, PlanError, PlanErrors, SourcePos, Step,
    Throw, caps,
};
pub use reference::{REFERENCE_BEGIN, REFERENCE_END, reference_markdown};
pub use runner::{
    Attempt, AttemptSink, CheckpointSeen, Decision, PlanHeader, Rebuilt, Report, Runner,
    ThrowSummary, UnderWay,
};
pub use schedule::{OutcomeSchedule, ScheduleError};
pub use script::{API, Angle, Length, Loaded, PlanLoader, ScriptLimits, Time};
pub use supervisor::{
    CheckpointRequest, InStep, InterventionRequest, InterventionResult, LIVE_POLL, Moment,
    NextPoll, Refusal, Resumption, ScriptedSupervisor, Supervisor, SupervisorCommand, TimedCommand,
};
pub use validate::{retry_cap, validate};

use std::path::Path;

/// Evaluate the plan script at `path` in the sandbox and validate it: the plan is returned
/// only if nothing is wrong with it.
pub fn load_plan(loader: &PlanLoader, path: &Path) -> Result<Loaded, PlanErrors> {
    let loaded = loader.eval_file(path)?;
    validate(&loaded.plan)?;
    Ok(loaded)
}

/// As [`load_plan`], from a string named `file` in errors.
pub fn load_plan_str(loader: &PlanLoader, file: &str, source: &str) -> Result<Loaded, PlanErrors> {
    let loaded = loader.eval_str(file, source)?;
    validate(&loaded.plan)?;
    Ok(loaded)
}
