//! The plan a script returns: a typed tree of mission → throws → steps, each with the script
//! position it came from.

use crate::condition::Condition;
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
    /// Steps on any one path through a throw (loops counted at their bound), a sanity bound.
    pub const STEPS_PER_THROW: usize = 32;
    /// The most times a `repeat` may run its steps.
    pub const REPEAT: u8 = 5;
    /// How deeply `when` and `repeat` may nest inside each other.
    pub const NESTING: usize = 3;
    /// Operations in a throw's compiled program (loops unrolled), a sanity bound.
    pub const OPS_PER_THROW: usize = 256;
    /// Terms (comparisons and combinators) in one condition, a sanity bound.
    pub const CONDITION_TERMS: usize = 64;
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

/// One element of a throw as the script wrote it: a step, or a construct around steps.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "node", rename_all = "snake_case")]
pub enum Node {
    /// A primitive or perception step.
    Step(Step),
    /// `when(cond, [then])`, with `.otherwise([..])` if given.
    When {
        /// Decided when the plan reaches it.
        cond: Condition,
        /// Run if it holds.
        then: Vec<Node>,
        /// Run if it does not.
        otherwise: Vec<Node>,
        /// Where the script wrote it.
        pos: SourcePos,
    },
    /// `repeat(#{ max: N, stop_when: cond }, [body])`: before each run of the body, stop if
    /// the condition holds; run it at most `max` times.
    Repeat {
        /// The most runs of the body (≤ [`caps::REPEAT`]).
        max: u8,
        /// Stop once it holds (checked before each run); `None`: run exactly `max` times.
        until: Option<Condition>,
        /// The steps repeated.
        body: Vec<Node>,
        /// Where the script wrote it.
        pos: SourcePos,
    },
    /// `checkpoint("label")`: the arms hold until the supervising surgeon says go.
    Checkpoint {
        /// What the surgeon confirms.
        label: String,
        /// Where the script wrote it.
        pos: SourcePos,
    },
}

/// Why a branch in the compiled program is there.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BranchRole {
    /// A `when`: past the `then` steps if the condition does not hold.
    When,
    /// A `repeat`'s `until`, before run `run` (1-based): out of the loop if it holds.
    Until {
        /// Which run of the body it comes before, 1-based.
        run: u8,
    },
}

/// One operation of a throw's compiled program: what the machine steps through. Loops are
/// unrolled to their bound and every jump goes forward, so every run of a throw is finite
/// by construction.
#[derive(Clone, Debug, PartialEq, Serialize)]
#[serde(tag = "op", rename_all = "snake_case")]
pub enum Op {
    /// Attempt a step.
    Do(Step),
    /// Decide `cond`; go to `to` if its value is `jump_if`, else to the next operation.
    Branch {
        /// The condition.
        cond: Condition,
        /// The value that jumps.
        jump_if: bool,
        /// Where to, an index past this one (the program's length: the throw's end).
        to: usize,
        /// Which construct it implements.
        role: BranchRole,
        /// Where the construct is in the script.
        pos: SourcePos,
    },
    /// Go to `to` (past the `otherwise` steps of a `when` whose `then` steps ran).
    Jump {
        /// Where to, an index past this one.
        to: usize,
    },
    /// Hold the arms until the supervisor says go.
    Checkpoint {
        /// What the surgeon confirms.
        label: String,
        /// Where the script wrote it.
        pos: SourcePos,
    },
}

impl Op {
    /// The step, if this operation attempts one.
    pub fn step(&self) -> Option<&Step> {
        match self {
            Op::Do(s) => Some(s),
            _ => None,
        }
    }

    /// Its position in the script (none for a jump).
    pub fn pos(&self) -> Option<SourcePos> {
        match self {
            Op::Do(s) => Some(s.pos),
            Op::Branch { pos, .. } | Op::Checkpoint { pos, .. } => Some(*pos),
            Op::Jump { .. } => None,
        }
    }

    /// The operations that may follow this one at index `at`.
    pub fn successors(&self, at: usize) -> Vec<usize> {
        match self {
            Op::Do(_) | Op::Checkpoint { .. } => vec![at + 1],
            Op::Branch { to, .. } => vec![at + 1, *to],
            Op::Jump { to } => vec![*to],
        }
    }
}

/// One suture throw: the steps at one wound point.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Throw {
    /// The wound point (entry and exit) this throw sutures.
    pub point: WoundPoint,
    /// What the script wrote, in order.
    pub body: Vec<Node>,
    /// The body compiled for the machine (see [`Op`]); indices into it are the journal's
    /// `step`. A plan without constructs compiles to one `Do` per step, in order.
    pub program: Vec<Op>,
    /// Where the script built the throw.
    pub pos: SourcePos,
}

impl Throw {
    /// A throw of `body` at `point`, compiled.
    pub fn new(point: WoundPoint, body: Vec<Node>, pos: SourcePos) -> Self {
        let mut program = Vec::new();
        compile(&body, &mut program);
        Self {
            point,
            body,
            program,
            pos,
        }
    }

    /// A throw of plain steps, in order.
    pub fn of_steps(point: WoundPoint, steps: Vec<Step>, pos: SourcePos) -> Self {
        Self::new(point, steps.into_iter().map(Node::Step).collect(), pos)
    }

    /// The step at program index `at`, if that operation attempts one.
    pub fn step(&self, at: usize) -> Option<&Step> {
        self.program.get(at).and_then(Op::step)
    }

    /// The steps of the program, with their indices.
    pub fn steps(&self) -> impl Iterator<Item = (usize, &Step)> {
        self.program
            .iter()
            .enumerate()
            .filter_map(|(i, op)| Some((i, op.step()?)))
    }
}

/// Unroll `nodes` into `out`. Jump targets are absolute indices into `out`.
fn compile(nodes: &[Node], out: &mut Vec<Op>) {
    for node in nodes {
        match node {
            Node::Step(s) => out.push(Op::Do(s.clone())),
            Node::Checkpoint { label, pos } => out.push(Op::Checkpoint {
                label: label.clone(),
                pos: *pos,
            }),
            Node::When {
                cond,
                then,
                otherwise,
                pos,
            } => {
                let branch = out.len();
                out.push(Op::Branch {
                    cond: cond.clone(),
                    jump_if: false,
                    to: 0,
                    role: BranchRole::When,
                    pos: *pos,
                });
                compile(then, out);
                let jump = (!otherwise.is_empty()).then(|| {
                    out.push(Op::Jump { to: 0 });
                    out.len() - 1
                });
                let else_at = out.len();
                compile(otherwise, out);
                let end = out.len();
                if let Some(Op::Branch { to, .. }) = out.get_mut(branch) {
                    *to = else_at;
                }
                if let Some(Op::Jump { to }) = jump.and_then(|j| out.get_mut(j)) {
                    *to = end;
                }
            }
            Node::Repeat {
                max,
                until,
                body,
                pos,
            } => {
                let mut exits = Vec::new();
                for run in 1..=*max {
                    if let Some(cond) = until {
                        exits.push(out.len());
                        out.push(Op::Branch {
                            cond: cond.clone(),
                            jump_if: true,
                            to: 0,
                            role: BranchRole::Until { run },
                            pos: *pos,
                        });
                    }
                    compile(body, out);
                }
                let end = out.len();
                for e in exits {
                    if let Some(Op::Branch { to, .. }) = out.get_mut(e) {
                        *to = end;
                    }
                }
            }
        }
    }
}

/// A whole mission: what the engine executes.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Plan {
    /// The mission's name (the policy, e.g. "STITCH").
    pub name: String,
    /// The script it came from, as given.
    pub file: String,
    /// Human interventions the robot may request (≤ [`caps::INTERVENTIONS`]).
    pub interventions: u8,
    /// The thread loaded on the needle, m, if the plan says (what `thread_left()` counts
    /// down from).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub thread_length_m: Option<f64>,
    /// The throws, in suturing order.
    pub throws: Vec<Throw>,
    /// Where the script built the mission.
    pub pos: SourcePos,
    /// The values of the parameters the script declared (`param(name, default)`), as it
    /// was built with them.
    #[serde(skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub params: crate::Params,
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
    /// Where the needle is before each operation of each throw's program, as the plan's
    /// order implies (`None` where no valid order reaches it: after a step out of place, or
    /// where branches disagree, whichever came first), and after the throw's last.
    /// Validation makes every branch agree, so for a valid plan each index has one holder.
    pub fn holders(&self) -> Vec<Vec<Option<NeedleHolder>>> {
        let mut start = Some(NeedleHolder::Right);
        self.throws
            .iter()
            .map(|t| {
                let n = t.program.len();
                let mut at: Vec<Option<Option<NeedleHolder>>> = vec![None; n + 1];
                at[0] = Some(start);
                for (i, op) in t.program.iter().enumerate() {
                    let Some(here) = at[i] else { continue };
                    let after = match op {
                        Op::Do(s) => here.and_then(|h| h.after(&s.kind).ok()),
                        _ => here,
                    };
                    for j in op.successors(i) {
                        let slot = &mut at[j.min(n)];
                        *slot = match *slot {
                            None => Some(after),
                            Some(prev) if prev == after => Some(prev),
                            Some(_) => Some(None),
                        };
                    }
                }
                let holders: Vec<Option<NeedleHolder>> =
                    at.into_iter().map(Option::flatten).collect();
                start = holders[n];
                holders
            })
            .collect()
    }

    /// The class a failure of the step at program index `step` of throw `throw` belongs to,
    /// from the phase: insert and correct (which prepares the next insertion) → I; extract →
    /// E; handover → H; sweep and cinch → T; a needle query → the phase the needle is in; a
    /// thread query → T.
    pub fn phase_class(&self, throw: usize, step: usize) -> FailureClass {
        let Some(s) = self.throws.get(throw).and_then(|t| t.step(step)) else {
            return FailureClass::Insertion;
        };
        match s.kind {
            StepKind::Insert(_) | StepKind::Correct(_) => FailureClass::Insertion,
            StepKind::Extract(_) => FailureClass::Extraction,
            StepKind::Handover(_) => FailureClass::Handover,
            StepKind::Sweep(_) | StepKind::Cinch(_) | StepKind::TrackThread(_) => {
                FailureClass::Thread
            }
            StepKind::EstimateNeedle(_) => self.needle_phase_class(throw, step),
        }
    }

    /// The class of the phase the needle is in before program index `step` of throw
    /// `throw`: in the tissue → E, in the left jaw → H, else I (a needle query's class, and a
    /// condition's that could not be observed).
    pub fn needle_phase_class(&self, throw: usize, step: usize) -> FailureClass {
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

    /// Whether any condition of the plan reads a quantity of `q`'s kind.
    pub fn reads(&self, q: &crate::condition::Quantity) -> bool {
        self.throws
            .iter()
            .flat_map(|t| &t.program)
            .any(|op| match op {
                Op::Branch { cond, .. } => cond.reads(q),
                _ => false,
            })
    }
}
