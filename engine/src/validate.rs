//! Validation before anything moves: ranges, order within and across throws, budgets within
//! the engine's hard caps. Every error names the script position and what was expected.

use crate::condition::{Condition, Quantity as Observed};
use crate::plan::{NeedleHolder, Node, Plan, PlanError, PlanErrors, SourcePos, caps};
use stitch_primitives::{Quantity, StepKind, Value};

/// Check a plan; `Ok` only if nothing is wrong. All problems are reported, in script order.
pub fn validate(plan: &Plan) -> Result<(), PlanErrors> {
    let mut errors = Vec::new();
    let mut err = |pos: SourcePos, message: String| {
        errors.push(PlanError {
            file: plan.file.clone(),
            pos,
            message,
        });
    };

    if plan.name.trim().is_empty() {
        err(plan.pos, "mission: `name` must not be empty".into());
    }
    if plan.interventions > caps::INTERVENTIONS {
        err(
            plan.pos,
            format!(
                "mission: interventions {} exceeds the engine's hard cap of {}; a plan may lower \
                 a cap, never raise it",
                plan.interventions,
                caps::INTERVENTIONS
            ),
        );
    }
    if plan.throws.is_empty() {
        err(
            plan.pos,
            "mission: expected at least one throw, found none".into(),
        );
    }
    if plan.throws.len() > caps::THROWS {
        err(
            plan.pos,
            format!(
                "mission: {} throws exceeds the limit of {}",
                plan.throws.len(),
                caps::THROWS
            ),
        );
    }

    let mut holder = NeedleHolder::Right;
    for (ti, throw) in plan.throws.iter().enumerate() {
        let n = ti + 1;
        let (entry, exit) = (throw.point.entry, throw.point.exit);
        if !entry.iter().chain(exit.iter()).all(|v| v.is_finite()) {
            err(
                throw.pos,
                format!("throw {n}: entry and exit points must be finite"),
            );
        } else {
            let bite = (exit - entry).norm();
            if !(0.001..=0.05).contains(&bite) {
                err(
                    throw.pos,
                    format!(
                        "throw {n}: entry and exit are {:.1} mm apart; expected 1 mm to 50 mm",
                        bite * 1e3
                    ),
                );
            }
        }
        if throw.body.is_empty() {
            err(throw.pos, format!("throw {n}: expected steps, found none"));
        }
        let mut walk = Walk {
            plan,
            n,
            first_insert_seen: false,
            err: &mut err,
        };
        let (after, counts) = walk.nodes(&throw.body, holder);
        holder = after;
        if counts.steps > caps::STEPS_PER_THROW {
            err(
                throw.pos,
                format!(
                    "throw {n}: {} steps on its longest path (loops at their bound) exceeds the \
                     limit of {}",
                    counts.steps,
                    caps::STEPS_PER_THROW
                ),
            );
        }
        for (name, (lo, hi)) in [("insert", counts.inserts), ("extract", counts.extracts)] {
            if (lo, hi) == (1, 1) {
                continue;
            }
            let message = if lo == hi {
                format!("throw {n}: expected exactly one {name}(), found {lo}")
            } else {
                format!(
                    "throw {n}: {name}() must run exactly once on every path; here it runs {lo} \
                     to {hi} times (a when or repeat around it?)"
                )
            };
            err(throw.pos, message.replace("found 0", "found none"));
        }
    }

    if errors.is_empty() {
        Ok(())
    } else {
        Err(PlanErrors(errors))
    }
}

/// What runs on the paths through some nodes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
struct Counts {
    /// Fewest and most inserts on a path.
    inserts: (usize, usize),
    /// Fewest and most extracts on a path.
    extracts: (usize, usize),
    /// Most steps on a path.
    steps: usize,
}

impl Counts {
    fn then(self, o: Counts) -> Counts {
        let add = |a: (usize, usize), b: (usize, usize)| (a.0 + b.0, a.1 + b.1);
        Counts {
            inserts: add(self.inserts, o.inserts),
            extracts: add(self.extracts, o.extracts),
            steps: self.steps + o.steps,
        }
    }

    fn or(self, o: Counts) -> Counts {
        let join = |a: (usize, usize), b: (usize, usize)| (a.0.min(b.0), a.1.max(b.1));
        Counts {
            inserts: join(self.inserts, o.inserts),
            extracts: join(self.extracts, o.extracts),
            steps: self.steps.max(o.steps),
        }
    }

    fn times(self, lo: usize, hi: usize) -> Counts {
        Counts {
            inserts: (self.inserts.0 * lo, self.inserts.1 * hi),
            extracts: (self.extracts.0 * lo, self.extracts.1 * hi),
            steps: self.steps * hi,
        }
    }
}

/// Validation of one throw's body: follows the needle through every branch.
struct Walk<'a, F: FnMut(SourcePos, String)> {
    plan: &'a Plan,
    /// Throw number, 1-based.
    n: usize,
    first_insert_seen: bool,
    err: &'a mut F,
}

impl<F: FnMut(SourcePos, String)> Walk<'_, F> {
    /// Check `nodes` from `holder`; where the needle is after them, and what runs.
    fn nodes(&mut self, nodes: &[Node], mut holder: NeedleHolder) -> (NeedleHolder, Counts) {
        let n = self.n;
        let mut counts = Counts::default();
        for (i, node) in nodes.iter().enumerate() {
            match node {
                Node::Step(step) => {
                    let next = match nodes.get(i + 1) {
                        Some(Node::Step(s)) => Some(&s.kind),
                        _ => None,
                    };
                    holder = self.step(step, holder, next);
                    let once = |b: bool| (usize::from(b), usize::from(b));
                    counts = counts.then(Counts {
                        inserts: once(matches!(step.kind, StepKind::Insert(_))),
                        extracts: once(matches!(step.kind, StepKind::Extract(_))),
                        steps: 1,
                    });
                }
                Node::Checkpoint { .. } => {}
                Node::When {
                    cond,
                    then,
                    otherwise,
                    pos,
                } => {
                    self.condition(cond, *pos);
                    if then.is_empty() && otherwise.is_empty() {
                        (self.err)(*pos, format!("throw {n}: when: expected steps, found none"));
                    }
                    let (h1, c1) = self.nodes(then, holder);
                    let (h2, c2) = self.nodes(otherwise, holder);
                    if h1 != h2 {
                        (self.err)(
                            *pos,
                            format!(
                                "throw {n}: when: the needle ends {} if `{cond}` holds and {} \
                                 if not; both branches must leave it in the same place for what \
                                 follows",
                                h1.describe(),
                                h2.describe()
                            ),
                        );
                    }
                    holder = h1;
                    counts = counts.then(c1.or(c2));
                }
                Node::Repeat {
                    max,
                    until,
                    body,
                    pos,
                } => {
                    if let Some(c) = until {
                        self.condition(c, *pos);
                    }
                    if *max == 0 || *max > caps::REPEAT {
                        (self.err)(
                            *pos,
                            format!(
                                "throw {n}: repeat: max {max} is out of range; expected 1 to {}",
                                caps::REPEAT
                            ),
                        );
                    }
                    let (after, c) = self.nodes(body, holder);
                    if after != holder {
                        (self.err)(
                            *pos,
                            format!(
                                "throw {n}: repeat: its steps take the needle from {} to {}; \
                                 repeated steps must leave it where they found it",
                                holder.describe(),
                                after.describe()
                            ),
                        );
                    }
                    let max = usize::from(*max);
                    let lo = if until.is_some() { 0 } else { max };
                    counts = counts.then(c.times(lo, max));
                }
            }
        }
        (holder, counts)
    }

    fn condition(&mut self, cond: &Condition, pos: SourcePos) {
        if cond.reads(&Observed::ThreadLeft) && self.plan.thread_length_m.is_none() {
            (self.err)(
                pos,
                format!(
                    "throw {}: `{cond}` reads thread_left(), which needs the mission's \
                     thread length: mission(#{{ .., thread_length: cm(..) }})",
                    self.n
                ),
            );
        }
    }

    /// Check one step from `holder`; where the needle is after it.
    fn step(
        &mut self,
        step: &crate::plan::Step,
        holder: NeedleHolder,
        next: Option<&StepKind>,
    ) -> NeedleHolder {
        let n = self.n;
        let name = step.kind.name();
        let err = &mut *self.err;
        check_ranges(&step.kind, n, |m| err(step.pos, m));
        check_retry_cap(&step.kind, n, |m| err(step.pos, m));
        if let StepKind::Cinch(c) = step.kind {
            let beta = c.beta_m(n);
            if beta <= 0.0 {
                err(
                    step.pos,
                    format!(
                        "throw {n}: cinch pulls β = l_des − (i − 1)·l_each = {:.1} cm − {}·{:.1} \
                         cm = {:.1} cm for suture {n}; expected more than 0",
                        c.l_des_m * 100.0,
                        n - 1,
                        c.l_each_m * 100.0,
                        beta * 100.0
                    ),
                );
            }
        }
        let first_insert = matches!(step.kind, StepKind::Insert(_)) && !self.first_insert_seen;
        if matches!(step.kind, StepKind::Insert(_)) {
            self.first_insert_seen = true;
        }
        match holder.after(&step.kind) {
            Ok(h) => h,
            Err(needs) => {
                let hint = match (&step.kind, holder) {
                    (StepKind::Insert(_), NeedleHolder::Left) if n > 1 && first_insert => {
                        format!("; add handover() to the end of throw {}", n - 1)
                    }
                    (StepKind::Handover(_), NeedleHolder::Tissue) => {
                        "; extract() must come before handover()".into()
                    }
                    (StepKind::Extract(_), NeedleHolder::Right) => {
                        "; insert() must come before extract()".into()
                    }
                    _ => String::new(),
                };
                err(
                    step.pos,
                    format!(
                        "throw {n}: {name} needs {needs}, but here the needle is {}{hint}",
                        holder.describe()
                    ),
                );
                // Go on so that later problems are still found but this one is not reported
                // again: either the step is out of place (the needle stays where it was) or
                // a step before it is missing (the needle is where this step leaves it).
                // Keep whichever lets the next step follow.
                let fits = |h: NeedleHolder| next.is_none_or(|k| h.after(k).is_ok());
                if fits(holder) {
                    holder
                } else {
                    assumed_after(&step.kind, holder)
                }
            }
        }
    }
}

fn assumed_after(kind: &StepKind, holder: NeedleHolder) -> NeedleHolder {
    match kind {
        StepKind::Insert(_) | StepKind::Sweep(_) => NeedleHolder::Tissue,
        StepKind::Extract(_) | StepKind::Cinch(_) => NeedleHolder::Left,
        StepKind::Handover(_) | StepKind::Correct(_) => NeedleHolder::Right,
        StepKind::EstimateNeedle(_) | StepKind::TrackThread(_) => holder,
    }
}

fn check_ranges(kind: &StepKind, throw: usize, mut err: impl FnMut(String)) {
    let name = kind.name();
    for spec in kind.param_specs() {
        let Some(value) = kind.get(spec.name) else {
            continue;
        };
        let (v, shown, lo, hi) = match (spec.quantity, value) {
            (Quantity::Length, Value::Length(v)) => (
                v,
                format!("{:.2} mm", v * 1e3),
                format!("{:.1} mm", spec.range.min * 1e3),
                format!("{:.1} mm", spec.range.max * 1e3),
            ),
            (Quantity::Angle, Value::Angle(v)) => (
                v,
                format!("{:.1}°", v.to_degrees()),
                format!("{:.1}°", spec.range.min.to_degrees()),
                format!("{:.1}°", spec.range.max.to_degrees()),
            ),
            (Quantity::Count, Value::Count(c)) => (
                c as f64,
                c.to_string(),
                format!("{}", spec.range.min),
                format!("{}", spec.range.max),
            ),
            // The parameter tables and the step structs disagree: a programming error that
            // must not pass silently.
            _ => {
                err(format!(
                    "throw {throw}: {name}.{} has the wrong kind of value",
                    spec.name
                ));
                continue;
            }
        };
        // Retry counts above their cap get the cap message instead.
        if spec.name == "retries" && v > spec.range.max {
            continue;
        }
        if !spec.range.contains(v) {
            err(format!(
                "throw {throw}: {name}: {} = {shown} is out of range; expected {lo} to {hi} ({})",
                spec.name, spec.doc
            ));
        }
    }
}

/// The engine's cap for a step's retries, if it retries.
pub fn retry_cap(kind: &StepKind) -> Option<(u8, &'static str)> {
    match kind {
        StepKind::Extract(_) => Some((caps::EXTRACT_RETRIES, "extraction retries")),
        StepKind::Handover(_) => Some((caps::HANDOVER_RETRIES, "handover re-attempts")),
        StepKind::EstimateNeedle(_) | StepKind::TrackThread(_) => {
            Some((caps::PERCEPTION_RETRIES, "perception retries"))
        }
        _ => None,
    }
}

fn check_retry_cap(kind: &StepKind, throw: usize, mut err: impl FnMut(String)) {
    if let (Some(asked), Some((cap, what))) = (kind.retries(), retry_cap(kind)) {
        if asked > cap {
            err(format!(
                "throw {throw}: {}: retries {asked} exceeds the engine's hard cap of {cap} {what}; \
                 a plan may lower a cap, never raise it",
                kind.name()
            ));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::plan::{Step, Throw};
    use stitch_robot::{Point, WoundPoint};

    fn step(name: &str, line: u32) -> Step {
        Step {
            kind: StepKind::default_for(name).expect("known"),
            pos: SourcePos { line, col: 5 },
        }
    }

    fn plan(throws: Vec<Vec<Step>>) -> Plan {
        Plan {
            name: "test".into(),
            file: "t.rhai".into(),
            interventions: 0,
            thread_length_m: None,
            throws: throws
                .into_iter()
                .enumerate()
                .map(|(i, steps)| {
                    Throw::of_steps(
                        WoundPoint {
                            index: i,
                            entry: Point::new(-0.005, 0.008 * i as f64, 0.0),
                            exit: Point::new(0.005, 0.008 * i as f64, 0.0),
                        },
                        steps,
                        SourcePos { line: 1, col: 1 },
                    )
                })
                .collect(),
            pos: SourcePos { line: 1, col: 1 },
            params: Default::default(),
        }
    }

    fn full(line: u32) -> Vec<Step> {
        ["insert", "sweep", "extract", "cinch", "handover", "correct"]
            .iter()
            .map(|n| step(n, line))
            .collect()
    }

    #[test]
    fn the_papers_full_policy_is_valid() {
        validate(&plan(vec![full(1), full(2), full(3)])).expect("valid");
    }

    #[test]
    fn handover_before_extract_is_rejected_at_its_position() {
        let steps = vec![step("insert", 3), step("handover", 4), step("extract", 5)];
        let e = validate(&plan(vec![steps])).expect_err("invalid");
        let first = &e.0[0];
        assert_eq!(first.pos.line, 4);
        assert!(
            first
                .message
                .contains("handover needs the needle in the left jaw"),
            "{first}"
        );
        assert!(
            first
                .message
                .contains("extract() must come before handover()"),
            "{first}"
        );
    }

    #[test]
    fn a_throw_that_keeps_the_needle_in_the_left_jaw_breaks_the_next_insert() {
        let first = vec![step("insert", 2), step("extract", 3)];
        let e = validate(&plan(vec![first, full(7)])).expect_err("invalid");
        assert_eq!(e.0.len(), 1, "{e}");
        assert_eq!(e.0[0].pos.line, 7);
        assert!(
            e.0[0]
                .message
                .contains("add handover() to the end of throw 1"),
            "{e}"
        );
    }

    #[test]
    fn retries_above_the_cap_and_interventions_above_two_are_rejected() {
        let mut steps = full(9);
        steps[2]
            .kind
            .set("retries", Value::Count(9))
            .expect("count");
        let mut p = plan(vec![steps]);
        p.interventions = 3;
        let e = validate(&p).expect_err("invalid");
        let text = e.to_string();
        assert!(
            text.contains("t.rhai:1:1: mission: interventions 3 exceeds"),
            "{text}"
        );
        assert!(
            text.contains(
                "t.rhai:9:5: throw 1: extract: retries 9 exceeds the engine's hard cap of 5"
            ),
            "{text}"
        );
    }

    #[test]
    fn a_cinch_that_runs_out_of_thread_names_the_suture() {
        let mut throws: Vec<_> = (0..6).map(|i| full(i + 1)).collect();
        for t in &mut throws {
            t[3].kind.set("l_des", Value::Length(0.05)).expect("length");
        }
        let e = validate(&plan(throws)).expect_err("invalid");
        // β = 5 − (i − 1)·2 cm ≤ 0 from suture 4 on.
        assert_eq!(e.0.len(), 3, "{e}");
        assert!(e.0[0].message.starts_with("throw 4: cinch pulls β"), "{e}");
    }

    #[test]
    fn out_of_range_parameters_say_the_range_in_units() {
        let mut steps = full(1);
        steps[0]
            .kind
            .set("rotation", Value::Angle(3.0))
            .expect("angle");
        let e = validate(&plan(vec![steps])).expect_err("invalid");
        assert!(
            e.0[0]
                .message
                .contains("rotation = 171.9° is out of range; expected 10.0° to 120.0°"),
            "{e}"
        );
    }
}
