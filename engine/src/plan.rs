//! The plan a script returns: a typed tree of mission → throws → steps, each with the script
//! position it came from.

use serde::{Deserialize, Serialize};
use std::fmt;
use stitch_primitives::StepKind;
use stitch_robot::WoundPoint;

/// The engine's hard caps. A plan may ask for less, never more; the state machine's guards
/// enforce these whatever the plan says.
pub mod caps {
    /// Extraction retries ("Motion Failure Recovery": up to 5).
    pub const EXTRACT_RETRIES: u8 = 5;
    /// Handover re-attempts ("Needle Handover": up to 5 additional times).
    pub const HANDOVER_RETRIES: u8 = 5;
    /// Retries of a perception query after a dropout (modelling choice, same bound).
    pub const PERCEPTION_RETRIES: u8 = 5;
    /// Human interventions per mission ("Baselines": up to 2).
    pub const INTERVENTIONS: u8 = 2;
    /// Throws per mission: more than any wound the paper sutures (6), a sanity bound.
    pub const THROWS: usize = 20;
    /// Steps per throw, a sanity bound.
    pub const STEPS_PER_THROW: usize = 16;
}

/// A position in a plan script, 1-based.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct SourcePos {
    /// Line, 1-based; 0 when unknown (a plan built in Rust).
    pub line: u32,
    /// Column, 1-based; 0 when unknown.
    pub col: u32,
}

impl SourcePos {
    /// A position from a Rhai position.
    pub fn from_rhai(pos: rhai::Position) -> Self {
        Self {
            line: pos
                .line()
                .map_or(0, |l| u32::try_from(l).unwrap_or(u32::MAX)),
            col: pos
                .position()
                .map_or(0, |c| u32::try_from(c).unwrap_or(u32::MAX)),
        }
    }
}

/// One step of a throw.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Step {
    /// What to do and with which parameters.
    #[serde(flatten)]
    pub kind: StepKind,
    /// Where the script asked for it.
    pub pos: SourcePos,
}

/// One suture throw: the steps at one wound point.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Throw {
    /// The wound point (entry and exit) this throw sutures.
    pub point: WoundPoint,
    /// The steps, in order.
    pub steps: Vec<Step>,
    /// Where the script built the throw.
    pub pos: SourcePos,
}

/// A whole mission: what the engine executes.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Plan {
    /// The mission's name (the policy, e.g. "STITCH").
    pub name: String,
    /// The script it came from, as given.
    pub file: String,
    /// Human interventions the robot may request (≤ [`caps::INTERVENTIONS`]).
    pub interventions: u8,
    /// The throws, in suturing order.
    pub throws: Vec<Throw>,
    /// Where the script built the mission.
    pub pos: SourcePos,
}

/// A problem with a plan, at a script position: a syntax error, a sandbox limit, a type or
/// unit error, a range, an order or a budget.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, thiserror::Error)]
pub struct PlanError {
    /// The script file.
    pub file: String,
    /// Where in it.
    pub pos: SourcePos,
    /// What is wrong and what was expected, in one line.
    pub message: String,
}

impl fmt::Display for PlanError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}:{}:{}: {}",
            self.file, self.pos.line, self.pos.col, self.message
        )
    }
}

/// One or more plan errors, each on its own line.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, thiserror::Error)]
pub struct PlanErrors(pub Vec<PlanError>);

impl fmt::Display for PlanErrors {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, e) in self.0.iter().enumerate() {
            if i > 0 {
                writeln!(f)?;
            }
            write!(f, "{e}")?;
        }
        Ok(())
    }
}

impl From<PlanError> for PlanErrors {
    fn from(e: PlanError) -> Self {
        PlanErrors(vec![e])
    }
}

/// The paper's error classes ("Trial Specifications and Error Classification").
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum FailureClass {
    /// I: the needle did not pass through the wound edges as planned.
    #[serde(rename = "I")]
    Insertion,
    /// E: the needle remained in the wound after extraction.
    #[serde(rename = "E")]
    Extraction,
    /// H: the needle was dropped or the arms ended unrecoverable during handover.
    #[serde(rename = "H")]
    Handover,
    /// T: the thread was not cinched or became entangled.
    #[serde(rename = "T")]
    Thread,
}

impl FailureClass {
    /// The paper's one-letter code.
    pub fn code(&self) -> char {
        match self {
            FailureClass::Insertion => 'I',
            FailureClass::Extraction => 'E',
            FailureClass::Handover => 'H',
            FailureClass::Thread => 'T',
        }
    }
}

impl fmt::Display for FailureClass {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = match self {
            FailureClass::Insertion => "insertion",
            FailureClass::Extraction => "extraction",
            FailureClass::Handover => "handover",
            FailureClass::Thread => "thread management",
        };
        write!(f, "{} ({name})", self.code())
    }
}

/// Who holds the needle, as the plan's order implies. Validation walks it through the
/// steps; the engine uses it to classify perception failures.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeedleHolder {
    /// The right (inserting) jaw, PSM1: where every throw starts.
    Right,
    /// In the tissue, released by the right jaw, not yet extracted.
    Tissue,
    /// The left (extracting) jaw, PSM2.
    Left,
}

impl NeedleHolder {
    /// Where the needle is after `kind` ran from `self`, or what the step needs instead.
    pub fn after(self, kind: &StepKind) -> Result<NeedleHolder, &'static str> {
        use NeedleHolder::*;
        match (kind, self) {
            (StepKind::Insert(_), Right) => Ok(Tissue),
            (StepKind::Insert(_), _) => Err("the needle in the right (inserting) jaw"),
            (StepKind::Sweep(_), Tissue) => Ok(Tissue),
            (StepKind::Sweep(_), _) => {
                Err("the needle in the tissue (after insert, before extract), the right jaw free")
            }
            (StepKind::Extract(_), Tissue) => Ok(Left),
            (StepKind::Extract(_), _) => Err("the needle in the tissue (after insert)"),
            (StepKind::Cinch(_), Left) => Ok(Left),
            (StepKind::Cinch(_), _) => Err("the needle in the left jaw (after extract)"),
            (StepKind::Handover(_), Left) => Ok(Right),
            (StepKind::Handover(_), _) => Err("the needle in the left jaw (after extract)"),
            (StepKind::Correct(_), Right) => Ok(Right),
            (StepKind::Correct(_), _) => Err("the needle in the right jaw (after handover)"),
            (StepKind::EstimateNeedle(_) | StepKind::TrackThread(_), h) => Ok(h),
        }
    }

    /// Where the needle is, in words.
    pub fn describe(self) -> &'static str {
        match self {
            NeedleHolder::Right => "in the right jaw",
            NeedleHolder::Tissue => "in the tissue",
            NeedleHolder::Left => "in the left jaw",
        }
    }
}

impl Plan {
    /// Where the needle is before each step of each throw, if the plan's order is valid up to
    /// there (`None` from the first step whose order is invalid).
    pub fn holders(&self) -> Vec<Vec<Option<NeedleHolder>>> {
        let mut holder = Some(NeedleHolder::Right);
        self.throws
            .iter()
            .map(|t| {
                t.steps
                    .iter()
                    .map(|s| {
                        let before = holder;
                        holder = holder.and_then(|h| h.after(&s.kind).ok());
                        before
                    })
                    .collect()
            })
            .collect()
    }

    /// The class a failure of step `step` of throw `throw` belongs to, from the phase: insert
    /// and correct (which prepares the next insertion) → I; extract → E; handover → H; sweep
    /// and cinch → T; a needle query → the phase the needle is in; a thread query → T.
    pub fn phase_class(&self, throw: usize, step: usize) -> FailureClass {
        let Some(s) = self.throws.get(throw).and_then(|t| t.steps.get(step)) else {
            return FailureClass::Insertion;
        };
        match s.kind {
            StepKind::Insert(_) | StepKind::Correct(_) => FailureClass::Insertion,
            StepKind::Extract(_) => FailureClass::Extraction,
            StepKind::Handover(_) => FailureClass::Handover,
            StepKind::Sweep(_) | StepKind::Cinch(_) | StepKind::TrackThread(_) => {
                FailureClass::Thread
            }
            StepKind::EstimateNeedle(_) => {
                let holder = self
                    .holders()
                    .get(throw)
                    .and_then(|t| t.get(step).copied().flatten());
                match holder {
                    Some(NeedleHolder::Tissue) => FailureClass::Extraction,
                    Some(NeedleHolder::Left) => FailureClass::Handover,
                    _ => FailureClass::Insertion,
                }
            }
        }
    }
}
