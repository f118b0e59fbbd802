//! Outcome schedules: the file `stitch run --robot scripted --outcomes FILE` replays. It
//! says, in order, how each step attempt ends, which supervisor commands arrive before which
//! attempt (`at`) or at which time on the run's clock, mid-step included (`at_s`), and how each
//! requested intervention ends.
//!
//! ```json
//! {
//!   "outcomes": ["ok", "ok", "no-progress", "ok"],
//!   "supervisor": [{ "at": 2, "command": "pause" }, { "at": 2, "command": "resume" }],
//!   "interventions": ["recovered"],
//!   "conditions": [false, true],
//!   "checkpoints": ["go", "abort"]
//! }
//! ```
//!
//! Every key is optional. Attempts past the end of `outcomes` succeed; interventions past the
//! end of `interventions` recover; the plan's conditions take the values of `conditions` in
//! the order they are decided (`null`: the robot cannot observe it), `true` past its end;
//! checkpoints are answered as `checkpoints`
//! says, `go` past its end.

use crate::supervisor::{InterventionResult, ScriptedSupervisor, SupervisorCommand, TimedCommand};
use serde::{Deserialize, Serialize};
use std::path::Path;
use stitch_primitives::{Scripted, ScriptedPrimitives};
use stitch_robot::SimClock;

/// A whole outcome schedule.
#[derive(Clone, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OutcomeSchedule {
    /// How each step attempt ends, in order.
    #[serde(default)]
    pub outcomes: Vec<Scripted>,
    /// Supervisor commands and when they arrive.
    #[serde(default)]
    pub supervisor: Vec<TimedCommand>,
    /// How each requested intervention ends, in order.
    #[serde(default)]
    pub interventions: Vec<InterventionResult>,
    /// The value of each condition the plan decides, in order; `null` for one the robot
    /// cannot observe (the engine then treats it as a failure in the needle's phase).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub conditions: Vec<Option<bool>>,
    /// The supervisor's answer at each checkpoint, in order.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub checkpoints: Vec<SupervisorCommand>,
}

/// An outcome schedule file that cannot be used.
#[derive(Debug, thiserror::Error)]
#[error("{file}:{line}:{col}: {message}")]
pub struct ScheduleError {
    /// The file.
    pub file: String,
    /// Line, 1-based (0 if the file could not be read).
    pub line: usize,
    /// Column, 1-based.
    pub col: usize,
    /// What is wrong.
    pub message: String,
}

impl OutcomeSchedule {
    /// Parse a schedule from JSON text; errors name the file, line and column.
    pub fn from_json(file: &str, text: &str) -> Result<Self, ScheduleError> {
        serde_json::from_str(text).map_err(|e| ScheduleError {
            file: file.into(),
            line: e.line(),
            col: e.column(),
            message: e
                .to_string()
                .split(" at line")
                .next()
                .unwrap_or_default()
                .to_string(),
        })
    }

    /// Read a schedule file.
    pub fn read(path: &Path) -> Result<Self, ScheduleError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|e| ScheduleError {
            file: file.clone(),
            line: 0,
            col: 0,
            message: format!("cannot read the outcome schedule: {e}"),
        })?;
        Self::from_json(&file, &text)
    }

    /// The scripted primitives and supervisor that replay this schedule.
    pub fn into_parts(self, clock: SimClock) -> (ScriptedPrimitives, ScriptedSupervisor) {
        (
            ScriptedPrimitives::from_schedule(self.outcomes, clock)
                .with_conditions(self.conditions),
            ScriptedSupervisor::new(self.supervisor, self.interventions)
                .with_checkpoints(self.checkpoints),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_schedule_parses_and_a_typo_names_its_line() {
        let s = OutcomeSchedule::from_json(
            "s.json",
            r#"{"outcomes":["ok","thread"],"supervisor":[{"at":1,"command":"e-stop"}]}"#,
        )
        .expect("valid");
        assert_eq!(s.outcomes, vec![Scripted::Ok, Scripted::Thread]);
        assert_eq!(s.supervisor[0].command, SupervisorCommand::EStop);
        let e =
            OutcomeSchedule::from_json("s.json", "{\n\"outcomes\": [\"okay\"]}").expect_err("bad");
        assert_eq!((e.line, e.file.as_str()), (2, "s.json"));
        assert!(e.to_string().contains("unknown variant `okay`"), "{e}");
    }
}
