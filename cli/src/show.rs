//! Text views of plans and runs.

use std::fmt::Write;
use stitch_engine::{
    InterventionResult, Node, Plan, PlanHeader, Rebuilt, Report, RunOutcome, caps, retry_cap,
};
use stitch_primitives::{StepOutcome, Value};

fn mm(p: &stitch_robot::Point) -> String {
    format!("({:.1}, {:.1}, {:.1}) mm", p.x * 1e3, p.y * 1e3, p.z * 1e3)
}

/// The plan as an indented tree, with each step's parameters in units and its script line.
/// The plan's parameters, one line each with where its value came from ("" if none).
pub fn params(loaded: &stitch_engine::Loaded) -> String {
    let mut s = String::new();
    for (name, p) in &loaded.params {
        let _ = writeln!(
            s,
            "param {name} = {}  ({})",
            p.value,
            if p.given {
                format!("given; default {}", p.default)
            } else {
                "default".into()
            }
        );
    }
    s
}

pub fn plan_tree(plan: &Plan) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "mission \"{}\"  ({}:{}:{})",
        plan.name, plan.file, plan.pos.line, plan.pos.col
    );
    let _ = writeln!(
        s,
        "  interventions: {} (engine cap {})",
        plan.interventions,
        caps::INTERVENTIONS
    );
    if let Some(l) = plan.thread_length_m {
        let _ = writeln!(s, "  thread: {:.1} cm", l * 100.0);
    }
    for (i, throw) in plan.throws.iter().enumerate() {
        let _ = writeln!(
            s,
            "  throw {}  wound point {}: entry {} → exit {}  (line {})",
            i + 1,
            throw.point.index + 1,
            mm(&throw.point.entry),
            mm(&throw.point.exit),
            throw.pos.line
        );
        let mut n = 0;
        nodes_tree(&mut s, &throw.body, 4, &mut n);
    }
    s
}

/// `nodes` at this indentation; steps numbered in script order from `n`.
fn nodes_tree(s: &mut String, nodes: &[Node], indent: usize, n: &mut usize) {
    let pad = " ".repeat(indent);
    for node in nodes {
        match node {
            Node::Step(step) => {
                *n += 1;
                let params: Vec<String> = step
                    .kind
                    .param_specs()
                    .iter()
                    .filter_map(|spec| {
                        let v = step.kind.get(spec.name)?;
                        Some(match v {
                            Value::Length(m) => format!("{} {:.1} mm", spec.name, m * 1e3),
                            Value::Angle(r) => format!("{} {:.1}°", spec.name, r.to_degrees()),
                            Value::Count(n) if spec.name == "retries" => {
                                let cap = retry_cap(&step.kind).map_or(0, |c| c.0);
                                format!("retries {n} (cap {cap})")
                            }
                            Value::Count(n) => format!("{} {n}", spec.name),
                        })
                    })
                    .collect();
                let _ = writeln!(
                    s,
                    "{pad}{}. {:<15} {}  (line {})",
                    n,
                    step.kind.name(),
                    params.join(", "),
                    step.pos.line
                );
            }
            Node::When {
                cond,
                then,
                otherwise,
                pos,
            } => {
                let _ = writeln!(s, "{pad}when {cond}  (line {})", pos.line);
                nodes_tree(s, then, indent + 3, n);
                if !otherwise.is_empty() {
                    let _ = writeln!(s, "{pad}otherwise");
                    nodes_tree(s, otherwise, indent + 3, n);
                }
            }
            Node::Repeat {
                max,
                until,
                body,
                pos,
            } => {
                let until = until.as_ref().map_or(String::new(), |c| {
                    format!(", stop when {c} (checked before each run)")
                });
                let _ = writeln!(
                    s,
                    "{pad}repeat at most {max} times (engine cap {}){until}  (line {})",
                    caps::REPEAT,
                    pos.line
                );
                nodes_tree(s, body, indent + 3, n);
            }
            Node::Checkpoint { label, pos } => {
                let _ = writeln!(
                    s,
                    "{pad}checkpoint \"{label}\": the arms hold until the surgeon says go  (line {})",
                    pos.line
                );
            }
        }
    }
}

fn checkpoint_line(s: &mut String, c: &stitch_engine::CheckpointSeen) {
    let answer = c.answer.map_or("no answer".to_string(), |a| a.to_string());
    let _ = writeln!(
        s,
        "  {:>7.1} s  checkpoint \"{}\": {answer}",
        c.at_s, c.label
    );
}

fn decision_line(s: &mut String, d: &stitch_engine::Decision) {
    let _ = writeln!(
        s,
        "  {:>7.1} s  decided {} → {}",
        d.at_s, d.condition, d.value
    );
}

fn outcome_text(o: &StepOutcome) -> String {
    match o {
        StepOutcome::Succeeded { measured } => {
            let mut parts = vec!["ok".to_string()];
            if let Some(e) = measured.entry_error_m {
                parts.push(format!("entry error {:.2} mm", e * 1e3));
            }
            if let Some(e) = measured.exit_error_m {
                parts.push(format!("exit error {:.2} mm", e * 1e3));
            }
            if let Some(t) = measured.endpoint_travel_m {
                parts.push(format!("endpoint moved {:.1} cm", t * 100.0));
            }
            if let Some(t) = measured.thread_used_m {
                parts.push(format!("β {:.1} cm", t * 100.0));
            }
            if let Some(t) = measured.thread_left_m {
                parts.push(format!("thread left {:.1} cm", t * 100.0));
            }
            if let Some(c) = measured.thread_clearance_m {
                parts.push(format!("thread clearance {:.1} mm at the blades", c * 1e3));
            }
            parts.join(", ")
        }
        StepOutcome::Failed(f) => {
            let mut s = format!("FAILED: {}", f.kind.label());
            if let Some(t) = f.measured.endpoint_travel_m {
                let _ = write!(s, " (endpoint moved {:.1} cm)", t * 100.0);
            }
            if let Some(d) = f.measured.normal_change_rad {
                let _ = write!(s, " (normal changed {:.1}°)", d.to_degrees());
            }
            if let Some(c) = f.measured.thread_clearance_m {
                let _ = write!(s, " (thread clearance {:.1} mm at the blades)", c * 1e3);
            }
            s
        }
        StepOutcome::Interrupted { committed, .. } => if *committed {
            "INTERRUPTED by the supervisor (past its commit point)"
        } else {
            "INTERRUPTED by the supervisor"
        }
        .to_string(),
    }
}

/// A per-throw timeline of a run and its final outcome; `clock` names the run's time ("simulated time" on the mock, "wall time" over ROS 2).
pub fn timeline(plan: &Plan, report: &Report, source: &str, robot: &str, clock: &str) -> String {
    timeline_of(
        &Rebuilt {
            plan: PlanHeader {
                name: plan.name.clone(),
                file: plan.file.clone(),
                throws: plan.throws.len(),
                interventions: plan.interventions,
                seed: None,
            },
            throws: report.throws.clone(),
            interventions: report.interventions,
            duration_s: report.duration_s,
            outcome: Some(report.outcome.clone()),
            under_way: None,
        },
        source,
        robot,
        clock,
    )
}

/// One line for a step attempt as it ends, for the timeline printed while the run goes:
/// `throw 1  12.3 s  insert  4.1 s  ok, entry error 0.21 mm`.
pub fn attempt_line(throw: usize, a: &stitch_engine::Attempt) -> String {
    format!(
        "throw {} {:>7.1} s  {:<18} {:>5.1} s  {}",
        throw + 1,
        a.start_s,
        attempt_label(a.primitive, a.attempt),
        a.duration_s,
        outcome_text(&a.outcome)
    )
}

/// `insert`, `insert #2`, ...: a step and, after the first, which attempt.
fn attempt_label(primitive: &str, attempt: u32) -> String {
    if attempt > 0 {
        format!("{primitive} #{}", attempt + 1)
    } else {
        primitive.to_string()
    }
}

/// [`timeline`] of a run rebuilt from its journal (`stitch journal show`); one cut short
/// says where it stops.
pub fn timeline_of(run: &Rebuilt, source: &str, robot: &str, clock: &str) -> String {
    let mut s = String::new();
    let _ = writeln!(s, "{} on {robot}, {source}", run.plan.name);
    for (i, t) in run.throws.iter().enumerate() {
        let under_way = run.under_way.as_ref().filter(|u| u.throw == i);
        if t.attempts.is_empty()
            && under_way.is_none()
            && t.checkpoints.is_empty()
            && t.decisions.is_empty()
        {
            continue;
        }
        let start = t.attempts.first().map_or(0.0, |a| a.start_s);
        let end = t.attempts.last().map_or(0.0, |a| a.start_s + a.duration_s);
        let status = if t.completed { "done" } else { "stopped" };
        let _ = writeln!(
            s,
            "throw {} ({status}): {:.1} s, {} retries, {} interventions",
            i + 1,
            end - start,
            t.retries,
            t.interventions
        );
        let mut decisions = t.decisions.iter().peekable();
        let mut checkpoints = t.checkpoints.iter().peekable();
        for a in &t.attempts {
            while let Some(c) = checkpoints.next_if(|c| c.at_s <= a.start_s) {
                checkpoint_line(&mut s, c);
            }
            while let Some(d) = decisions.next_if(|d| d.at_s <= a.start_s) {
                decision_line(&mut s, d);
            }
            let label = attempt_label(a.primitive, a.attempt);
            let _ = writeln!(
                s,
                "  {:>7.1} s  {:<18} {:>5.1} s  {}",
                a.start_s,
                label,
                a.duration_s,
                outcome_text(&a.outcome)
            );
            if let Some(result) = a.intervention {
                let how = match result {
                    InterventionResult::Recovered => "recovered; the step runs again",
                    InterventionResult::Failed => "failed",
                };
                let _ = writeln!(s, "  {:>9}  human intervention: {how}", "");
            }
        }
        for c in checkpoints {
            checkpoint_line(&mut s, c);
        }
        for d in decisions {
            decision_line(&mut s, d);
        }
        if let Some(u) = under_way {
            let label = attempt_label(&u.primitive, u.attempt);
            let _ = writeln!(
                s,
                "  {:>7.1} s  {:<18}        under way where the journal stops",
                u.start_ns as f64 * 1e-9,
                label
            );
        }
    }
    let done = run.throws.iter().filter(|t| t.completed).count();
    let outcome = match &run.outcome {
        None => format!(
            "unknown: the journal stops at {:.3} s, before the run's end (cut short)",
            run.duration_s
        ),
        Some(RunOutcome::Completed) => "completed".to_string(),
        Some(RunOutcome::Failed {
            class,
            throw,
            primitive,
            reason,
            ..
        }) => format!(
            "failed, class {class}, in throw {} at {primitive}{}",
            throw + 1,
            reason
                .as_ref()
                .map(|r| format!(": {}", r.label()))
                .unwrap_or_default()
        ),
        Some(RunOutcome::Aborted { by, throw, step }) => {
            // Mid-step, the step's last attempt was interrupted.
            let during = run
                .throws
                .get(*throw)
                .and_then(|t| t.attempts.last())
                .is_some_and(|a| {
                    a.step == *step && matches!(a.outcome, StepOutcome::Interrupted { .. })
                });
            format!(
                "aborted ({by:?}) {} throw {} step {}; arms held",
                if during { "during" } else { "before" },
                throw + 1,
                step + 1
            )
        }
    };
    let _ = writeln!(s, "outcome: {outcome}");
    let _ = writeln!(
        s,
        "sutures completed: {done} of {}; interventions {} of {}; {clock} {:.1} s",
        run.plan.throws,
        run.interventions,
        run.plan.interventions.min(caps::INTERVENTIONS),
        run.duration_s
    );
    s
}

/// The verdicts of an exploration, with the shortest counterexample of each failed property.
pub fn exploration(
    plan_file: &std::path::Path,
    found: &stitch_engine::Exploration,
    options: &stitch_engine::ExploreOptions,
    valid: bool,
) -> String {
    let mut s = String::new();
    let paths = if found.paths == u128::MAX {
        "more than 3.4e38".to_string()
    } else {
        format!("{:.3e}", found.paths as f64)
    };
    let _ = writeln!(
        s,
        "explored {}: {} states, {paths} complete paths, farthest state {} choices away, in {:.2} s",
        plan_file.display(),
        found.states,
        found.max_depth,
        found.elapsed.as_secs_f64()
    );
    let outcomes: Vec<&str> = options.outcomes.iter().map(|t| t.as_str()).collect();
    let reached = |state: &str| found.edges.keys().any(|(a, b)| *a == state || *b == state);
    let mut also = String::new();
    if reached("deciding") {
        also.push_str(
            " both values of every condition on what the robot observes (the engine's own \
             counters decided exactly; every loop count up to its bound),",
        );
    }
    if reached("at_checkpoint") {
        also.push_str(" every answer at a checkpoint (go, take-over, abort, e-stop),");
    }
    let _ = writeln!(
        s,
        "  branching on every step outcome ({}),{also} every intervention result, and up to {} \
         supervisor commands per path, before a step or in its middle (before and past its \
         commit point)",
        outcomes.join(", "),
        options.max_commands
    );
    for v in &found.verdicts {
        let mark = if v.holds { "ok  " } else { "FAIL" };
        let _ = writeln!(s, "  {mark} {}", v.says);
        if v.holds {
            continue;
        }
        match &v.path {
            Some(path) => {
                let n = path.len();
                let _ = writeln!(
                    s,
                    "       shortest counterexample, {n} choice{}:",
                    if n == 1 { "" } else { "s" }
                );
                for (i, (state, action)) in path.iter().enumerate() {
                    let _ = writeln!(s, "       {:>3}. in {state}: {action}", i + 1);
                }
                if let Some(schedule) = &v.schedule {
                    let json = serde_json::to_string(schedule).unwrap_or_default();
                    let _ = writeln!(
                        s,
                        "       replay: stitch run {} --outcomes FILE{}, FILE holding\n       {json}",
                        plan_file.display(),
                        if valid { "" } else { " --skip-validation" }
                    );
                }
            }
            None => {
                let _ = writeln!(s, "       no path reaches it");
            }
        }
    }
    s
}
