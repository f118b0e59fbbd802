//! The journal: every transition, step start and end, outcome, retry, intervention, supervisor
//! command and hold, with simulated time, as JSON Lines. The same seed gives the same journal,
//! byte for byte: records hold no wall-clock time, no addresses and no unordered maps.

use crate::condition::MissionFacts;
use crate::plan::{BranchRole, FailureClass};
use crate::supervisor::{InterventionResult, SupervisorCommand};
use serde::{Deserialize, Serialize};
use std::io::{self, Write};
use std::time::Duration;
use stitch_primitives::{FailureKind, Observation, StepOutcome};

/// Why a run was aborted.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum AbortCause {
    /// The supervisor aborted.
    Abort,
    /// The supervisor pressed the emergency stop.
    EStop,
    /// The supervisor gave no command while the run was paused or taken over.
    SupervisorSilent,
}

/// How a run ended.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "result", rename_all = "snake_case")]
pub enum RunOutcome {
    /// Every throw of the plan succeeded.
    Completed,
    /// A step failed beyond its retries and the intervention budget.
    Failed {
        /// The paper's error class.
        class: FailureClass,
        /// Throw index, 0-based.
        throw: usize,
        /// Step index within the throw, 0-based.
        step: usize,
        /// The step's name.
        primitive: String,
        /// The last failure of that step, if one was reported (an intervention can fail too).
        #[serde(skip_serializing_if = "Option::is_none")]
        reason: Option<FailureKind>,
    },
    /// The supervisor stopped the run; the arms hold.
    Aborted {
        /// Why.
        by: AbortCause,
        /// Throw index where it stopped, 0-based.
        throw: usize,
        /// Step index where it stopped, 0-based.
        step: usize,
    },
}

/// The step attempt a supervisor command landed in.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct During {
    /// Throw index, 0-based.
    pub throw: usize,
    /// Step index, 0-based.
    pub step: usize,
    /// Attempt, 0-based.
    pub attempt: u32,
    /// Whether the step had passed its commit point.
    pub committed: bool,
}

/// Where a command came from and when it landed, for its journal record.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Arrival {
    /// The supervisor's source.
    pub from: Option<String>,
    /// The attempt under way, if mid-step.
    pub during: Option<During>,
}

/// One journal line's content.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "event", rename_all = "snake_case")]
pub enum Entry {
    /// The plan about to run.
    Plan {
        /// Mission name.
        name: String,
        /// Script file.
        file: String,
        /// Number of throws.
        throws: usize,
        /// Intervention budget.
        interventions: u8,
        /// The seed that decides a simulated run, if any.
        #[serde(skip_serializing_if = "Option::is_none")]
        seed: Option<u64>,
        /// The plan's parameters (`param(name, default)`) and the values it was built with.
        #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
        params: crate::Params,
    },
    /// A state machine transition.
    Transition {
        /// Source state.
        from: String,
        /// Target state.
        to: String,
    },
    /// A step attempt begins.
    StepStart {
        /// Throw index, 0-based.
        throw: usize,
        /// Step index, 0-based.
        step: usize,
        /// Step name.
        primitive: String,
        /// Attempt, 0-based.
        attempt: u32,
    },
    /// A step attempt ended.
    StepEnd {
        /// Throw index, 0-based.
        throw: usize,
        /// Step index, 0-based.
        step: usize,
        /// Step name.
        primitive: String,
        /// Attempt, 0-based.
        attempt: u32,
        /// What happened.
        outcome: StepOutcome,
    },
    /// The machine retries a step because its recovery condition holds.
    Retry {
        /// Throw index, 0-based.
        throw: usize,
        /// Step index, 0-based.
        step: usize,
        /// Step name.
        primitive: String,
        /// This retry's number, 1-based.
        retry: u8,
        /// The effective cap: the plan's retries bounded by the engine's hard cap.
        cap: u8,
    },
    /// The robot asks the supervising surgeon for help.
    InterventionRequested {
        /// Throw index, 0-based.
        throw: usize,
        /// Step index, 0-based.
        step: usize,
        /// The failure's class.
        class: FailureClass,
        /// Interventions used, this one included.
        used: u8,
        /// The effective budget.
        budget: u8,
    },
    /// The surgeon's intervention ended.
    InterventionEnded {
        /// Throw index, 0-based.
        throw: usize,
        /// Step index, 0-based.
        step: usize,
        /// How.
        result: InterventionResult,
    },
    /// A command from the supervisor reached the machine (at the record's time).
    Supervisor {
        /// The command.
        command: SupervisorCommand,
        /// Whether the machine acted on it (a resume while running is ignored).
        acted: bool,
        /// Where it came from (`terminal`, `schedule`, ...), where the runner knows.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        from: Option<String>,
        /// The step attempt it landed in, if it landed mid-step (else before a step, at a
        /// checkpoint, or while paused or taken over: the transitions around it say where).
        #[serde(default, skip_serializing_if = "Option::is_none")]
        during: Option<During>,
    },
    /// A command that did not reach the machine: refused by the supervisor's channel (a
    /// console's command without the run's token, from another origin, from a viewer not
    /// in control, ...). Journaled when the engine next asks its supervisor, so its time is
    /// that moment's.
    Refused {
        /// What was asked, as it was written (possibly not a command at all).
        command: String,
        /// Who asked (`console`, with the peer's address where known).
        from: String,
        /// Why it was refused.
        why: String,
    },
    /// A plan's condition was decided.
    Condition {
        /// Throw index, 0-based.
        throw: usize,
        /// Program index, 0-based.
        step: usize,
        /// The condition, as the script writes it.
        condition: String,
        /// The construct: `when`, or `until` before run N of a repeat.
        role: BranchRole,
        /// Its value.
        value: bool,
        /// What the robot observed for it.
        observation: Observation,
        /// What the engine knew.
        mission: MissionFacts,
    },
    /// A condition the robot could not observe (an arm that could not say where it is, a
    /// failing camera: the observation's `faults`): not decided; the machine handles it as a
    /// failure in the phase the needle is in.
    Unobserved {
        /// Throw index, 0-based.
        throw: usize,
        /// Program index, 0-based.
        step: usize,
        /// The condition, as the script writes it.
        condition: String,
        /// The construct: `when`, or `until` before run N of a repeat.
        role: BranchRole,
        /// What the robot observed, and what it could not.
        observation: Observation,
        /// What the engine knew.
        mission: MissionFacts,
    },
    /// The plan reached a checkpoint; the arms hold until the surgeon says go.
    Checkpoint {
        /// Throw index, 0-based.
        throw: usize,
        /// Program index, 0-based.
        step: usize,
        /// What the surgeon confirms.
        label: String,
    },
    /// The arms were told to hold.
    Hold {
        /// The state that asked for it.
        state: String,
        /// Whether the robot confirmed; an error's message otherwise.
        #[serde(skip_serializing_if = "Option::is_none")]
        error: Option<String>,
    },
    /// The run ended.
    Finished {
        /// How.
        outcome: RunOutcome,
    },
}

/// One journal line.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Record {
    /// Sequence number, from 0.
    pub seq: u64,
    /// Simulated (or robot) time since the run started, s.
    pub t_s: f64,
    /// What happened.
    #[serde(flatten)]
    pub entry: Entry,
}

/// Where each record goes as soon as it is journaled (a flight recorder), besides memory.
pub type JournalSink = Box<dyn FnMut(&Record) + Send>;

/// The journal of one run, kept in memory; [`Journal::write_jsonl`] writes it out, and a
/// [`JournalSink`] set with [`Journal::stream_to`] gets every record the moment it is pushed.
#[derive(Default)]
pub struct Journal {
    records: Vec<Record>,
    now: Duration,
    sink: Option<JournalSink>,
}

impl Clone for Journal {
    /// The records and time; not the sink (one run, one recorder).
    fn clone(&self) -> Self {
        Self {
            records: self.records.clone(),
            now: self.now,
            sink: None,
        }
    }
}

impl PartialEq for Journal {
    fn eq(&self, other: &Self) -> bool {
        self.records == other.records && self.now == other.now
    }
}

impl std::fmt::Debug for Journal {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Journal")
            .field("records", &self.records)
            .field("now", &self.now)
            .field("streaming", &self.sink.is_some())
            .finish()
    }
}

impl Journal {
    /// An empty journal.
    pub fn new() -> Self {
        Self::default()
    }

    /// Set the time stamped on the next records.
    pub fn set_now(&mut self, now: Duration) {
        self.now = now;
    }

    /// Append an entry at the current time (and hand it to the sink, if any).
    pub fn push(&mut self, entry: Entry) {
        let seq = self.records.len() as u64;
        let record = Record {
            seq,
            t_s: self.now.as_secs_f64(),
            entry,
        };
        if let Some(sink) = &mut self.sink {
            sink(&record);
        }
        self.records.push(record);
    }

    /// From now on, hand every record to `sink` as it is pushed; the records already
    /// journaled go to it first, in order.
    pub fn stream_to(&mut self, mut sink: JournalSink) {
        for r in &self.records {
            sink(r);
        }
        self.sink = Some(sink);
    }

    /// Stop streaming (the sink is dropped: a recorder's queue sender closes).
    pub fn stop_streaming(&mut self) {
        self.sink = None;
    }

    /// All records, in order.
    pub fn records(&self) -> &[Record] {
        &self.records
    }

    /// Write every record as one JSON object per line.
    pub fn write_jsonl(&self, mut out: impl Write) -> io::Result<()> {
        for r in &self.records {
            serde_json::to_writer(&mut out, r)?;
            out.write_all(b"\n")?;
        }
        out.flush()
    }

    /// The journal as JSON Lines text.
    pub fn to_jsonl(&self) -> String {
        let mut buf = Vec::new();
        // Writing to a Vec cannot fail; serialising these types cannot either.
        let _ = self.write_jsonl(&mut buf);
        String::from_utf8_lossy(&buf).into_owned()
    }
}
