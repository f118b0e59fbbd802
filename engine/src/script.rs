//! The Rhai host: a sandboxed engine that evaluates a plan script once and returns a typed
//! [`Plan`].
//!
//! The sandbox starts from `Engine::new_raw()` and opts into only what plans need: arithmetic,
//! logic, strings, arrays, maps, maths and iterators. No `import` (the `no_module` feature),
//! no `eval`, no `sleep` or `exit` (the language-core package is left out), no time. Limits
//! on operations, call depth, expression depth and string/array/map sizes, strict variables,
//! and a wall-clock deadline checked through `on_progress`.

use crate::condition::{Cmp, Condition, End, Quantity as Q, Target, Unit};
use crate::params::{DeclaredParam, ParamState, ParamValue, Params};
use crate::plan::{Node, Plan, PlanError, SourcePos, Step, Throw, caps};
use rhai::packages::{
    ArithmeticPackage, BasicArrayPackage, BasicIteratorPackage, BasicMapPackage, BasicMathPackage,
    BasicStringPackage, LogicPackage, Package,
};
use rhai::{Array, Dynamic, EvalAltResult, INT, ImmutableString, Map, NativeCallContext, Position};
use std::collections::BTreeMap;
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};
use stitch_primitives::{Quantity, STEP_NAMES, StepKind, Value, param_specs};
use stitch_robot::{Wound, WoundPoint};

type RhaiResult<T> = Result<T, Box<EvalAltResult>>;

/// Limits the sandbox puts on a script.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScriptLimits {
    /// Operations before the script is stopped.
    pub max_operations: u64,
    /// Depth of nested function calls.
    pub max_call_levels: usize,
    /// Depth of nested expressions (global, in functions).
    pub max_expr_depth: (usize, usize),
    /// Longest string, bytes.
    pub max_string_size: usize,
    /// Longest array, elements.
    pub max_array_size: usize,
    /// Largest object map, entries.
    pub max_map_size: usize,
    /// Wall-clock time before the script is stopped.
    pub deadline: Duration,
}

impl Default for ScriptLimits {
    fn default() -> Self {
        // A 6-throw plan evaluates in well under 5,000 operations; these bounds leave room for
        // helper functions and loops while stopping a runaway script in milliseconds.
        Self {
            max_operations: 200_000,
            max_call_levels: 32,
            max_expr_depth: (64, 32),
            max_string_size: 4096,
            max_array_size: 1024,
            max_map_size: 64,
            deadline: Duration::from_millis(500),
        }
    }
}

/// A length in metres, as scripts make it with `mm`, `cm` or `m`.
#[derive(Clone, Copy, Debug, PartialEq, PartialOrd)]
pub struct Length(pub f64);

/// An angle in radians, as scripts make it with `deg` or `rad`.
#[derive(Clone, Copy, Debug, PartialEq, PartialOrd)]
pub struct Angle(pub f64);

/// A time in seconds, as scripts make it with `s` or `ms`.
#[derive(Clone, Copy, Debug, PartialEq, PartialOrd)]
pub struct Time(pub f64);

/// A unit direction in the robot frame, as scripts make it with `direction(x, y, z)`.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Direction([f64; 3]);

/// A quantity decided at run time, as `needle_confidence()` and the like return it: compared
/// with a bound, it makes a condition.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Observable(Q);

/// A construct (`when`, `repeat`, `checkpoint`) in a step list.
#[derive(Clone, Debug, PartialEq)]
struct Block(Node);

/// What scripts may call, with usage, for error messages and the scripting reference.
pub const API: &[(&str, &str)] = &[
    ("mm", "mm(number) → length in millimetres"),
    ("cm", "cm(number) → length in centimetres"),
    ("m", "m(number) → length in metres"),
    ("deg", "deg(number) → angle in degrees"),
    ("rad", "rad(number) → angle in radians"),
    ("wound", "wound() → the wound's points, in suturing order"),
    (
        "param",
        "param(\"name\", default) → the value given with --param name=.. or by a sweep, else default (an integer, number, boolean or string; name the unit: param(\"standoff_mm\", 12))",
    ),
    ("suture", "suture(wound_point, [steps]) → one suture throw"),
    (
        "mission",
        "mission(#{ name: \"..\", interventions: 0..2, throws: [..], thread_length: cm(..) }) → the plan (thread_length optional)",
    ),
    (
        "insert",
        "insert() or insert(#{ rotation: deg(..), push: mm(..), standoff: cm(..), samples: 0..20 })",
    ),
    (
        "sweep",
        "sweep() or sweep(#{ distance: cm(..), jaw_open: deg(..) })",
    ),
    (
        "extract",
        "extract() or extract(#{ retries: 0..5, offset: cm(..), approach: cm(..), rotation: deg(..), min_travel: cm(..), pull: cm(..) })",
    ),
    (
        "cinch",
        "cinch() or cinch(#{ l_des: cm(..), l_each: cm(..) })",
    ),
    (
        "handover",
        "handover() or handover(#{ retries: 0..5, offset: cm(..), jitter: mm(..), normal_tolerance: deg(..), tug: deg(..), inset: deg(..) })",
    ),
    (
        "correct",
        "correct() or correct(#{ samples: 1..100, final_rotation: deg(..) })",
    ),
    (
        "estimate_needle",
        "estimate_needle() or estimate_needle(#{ samples: 1..100, retries: 0..5 })",
    ),
    (
        "track_thread",
        "track_thread() or track_thread(#{ retries: 0..5 })",
    ),
    ("s", "s(number) → time in seconds"),
    ("ms", "ms(number) → time in milliseconds"),
    (
        "when",
        "when(condition, [steps]) → run the steps if the condition holds when reached; add .otherwise([steps]) for the other case",
    ),
    (
        "otherwise",
        "when(..).otherwise([steps]) → the steps run if the when's condition does not hold",
    ),
    (
        "repeat",
        "repeat(#{ max: 1..5, stop_when: condition }, [steps]) → before each run, stop if `stop_when` holds; at most `max` runs (`stop_when` optional: exactly `max`)",
    ),
    (
        "checkpoint",
        "checkpoint(\"label\") → hold the arms until the supervising surgeon says go",
    ),
    (
        "needle_seen",
        "needle_seen() → condition: a needle query now sees the needle",
    ),
    (
        "needle_confidence",
        "needle_confidence() → the latest needle estimate's confidence, compare with a number 0..1",
    ),
    (
        "needle_normal_angle",
        "needle_normal_angle(direction(x, y, z)) → angle of the latest estimate's normal to a robot-frame direction, compare with deg(..)",
    ),
    (
        "needle_tip_distance",
        "needle_tip_distance(target) → the latest estimate's tip to a target (point(..), wound_point.entry/.exit, right_jaw(), left_jaw(), needle_point(..)), compare with mm(..)",
    ),
    (
        "needle_swage_distance",
        "needle_swage_distance(target) → as needle_tip_distance, from the swage",
    ),
    (
        "needle_age",
        "needle_age() → time since the latest needle estimate's images, compare with s(..)",
    ),
    (
        "thread_left",
        "thread_left() → the mission's thread_length less what the cinches pulled, compare with cm(..)",
    ),
    (
        "thread_clearance",
        "thread_clearance(target) → a thread trace made now (from the last exit to the needle's swage): how far it stays from a target (right_jaw(), left_jaw(), a point, needle_point(..)) less twice its uncertainty, compare with mm(..)",
    ),
    (
        "thread_free",
        "thread_free() → a thread trace made now: its length from the last exit to the needle's swage, compare with cm(..)",
    ),
    (
        "thread_wrap",
        "thread_wrap(target) → a thread trace made now: how far its part within 3 cm of a target winds round the vertical through it, compare with deg(..) (a loop: deg(360))",
    ),
    (
        "throw_number",
        "throw_number() → the throw under way, 1-based, compare with a whole number",
    ),
    (
        "interventions_left",
        "interventions_left() → interventions the robot may still ask for, compare with a whole number",
    ),
    (
        "retries_used",
        "retries_used() → retries granted in this throw so far, compare with a whole number",
    ),
    ("all", "all([conditions]) → condition: every one holds"),
    ("any", "any([conditions]) → condition: at least one holds"),
    ("not", "not(condition) → condition: it does not hold"),
    (
        "direction",
        "direction(x, y, z) → a robot-frame direction (+x along the wound's bite, +y down the wound, +z up)",
    ),
    (
        "point",
        "point(x, y, z) → a robot-frame point, each a length",
    ),
    (
        "right_jaw",
        "right_jaw() → the right (PSM1) jaw's tip, as a target",
    ),
    (
        "left_jaw",
        "left_jaw() → the left (PSM2) jaw's tip, as a target",
    ),
    (
        "needle_point",
        "needle_point(deg(a)) → the point a along the latest needle estimate's arc from the tip (deg(0)) to the swage (deg(180)), as a target: deg(160) is the handover's grasp site",
    ),
];

/// Evaluates plan scripts in the sandbox.
#[derive(Debug)]
pub struct PlanLoader {
    engine: rhai::Engine,
    started: Arc<Mutex<Instant>>,
    printed: Arc<Mutex<Vec<String>>>,
    params: Arc<Mutex<ParamState>>,
}

/// A plan and what its script printed while building it.
#[derive(Clone, Debug, PartialEq)]
pub struct Loaded {
    /// The plan, not yet validated.
    pub plan: Plan,
    /// Lines the script printed with `print`/`debug`.
    pub printed: Vec<String>,
    /// The parameters the script declared with `param(name, default)`, by name.
    pub params: BTreeMap<String, DeclaredParam>,
    /// Parameters given to the loader ([`PlanLoader::with_params`]) that the script never
    /// asked for: a caller that gave them for this plan should refuse to run it.
    pub unused_params: Vec<String>,
}

impl PlanLoader {
    /// A sandbox whose `wound()` returns `wound`.
    pub fn new(wound: &Wound, limits: ScriptLimits) -> Self {
        let mut engine = rhai::Engine::new_raw();
        for pkg in [
            ArithmeticPackage::new().as_shared_module(),
            LogicPackage::new().as_shared_module(),
            BasicStringPackage::new().as_shared_module(),
            BasicIteratorPackage::new().as_shared_module(),
            BasicArrayPackage::new().as_shared_module(),
            BasicMapPackage::new().as_shared_module(),
            BasicMathPackage::new().as_shared_module(),
        ] {
            engine.register_global_module(pkg);
        }
        engine.disable_symbol("eval");
        engine
            .set_max_operations(limits.max_operations)
            .set_max_call_levels(limits.max_call_levels)
            .set_max_expr_depths(limits.max_expr_depth.0, limits.max_expr_depth.1)
            .set_max_string_size(limits.max_string_size)
            .set_max_array_size(limits.max_array_size)
            .set_max_map_size(limits.max_map_size)
            .set_strict_variables(true);

        // The deadline is a guard on the host process, so it is measured in real time: the
        // one place the engine reads the wall clock.
        let started = Arc::new(Mutex::new(Instant::now()));
        let deadline = limits.deadline;
        let start = Arc::clone(&started);
        engine.on_progress(move |ops| {
            if ops % 1024 != 0 {
                return None;
            }
            let t0 = *start
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            (t0.elapsed() > deadline).then(|| {
                Dynamic::from(format!(
                    "the script ran past the sandbox deadline of {} ms",
                    deadline.as_millis()
                ))
            })
        });
        let printed = Arc::new(Mutex::new(Vec::new()));
        let sink = Arc::clone(&printed);
        engine.on_print(move |s| {
            sink.lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .push(s.to_string());
        });
        let sink = Arc::clone(&printed);
        engine.on_debug(move |s, _, pos| {
            sink.lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner)
                .push(format!("{pos:?}: {s}"));
        });

        let params = Arc::new(Mutex::new(ParamState::default()));
        register_units(&mut engine);
        register_params(&mut engine, &params);
        register_plan_api(&mut engine, wound.clone());
        register_conditions(&mut engine);
        Self {
            engine,
            started,
            printed,
            params,
        }
    }

    /// This loader with `given` as the values of the scripts' `param(name, default)` calls.
    #[must_use]
    pub fn with_params(self, given: Params) -> Self {
        lock(&self.params).given = given;
        self
    }

    /// Evaluate the script at `path` (not validated: see [`crate::load_plan`]).
    pub fn eval_file(&self, path: &Path) -> Result<Loaded, PlanError> {
        let file = path.display().to_string();
        let source = std::fs::read_to_string(path).map_err(|e| PlanError {
            file: file.clone(),
            pos: SourcePos::default(),
            message: format!("cannot read the plan: {e}"),
        })?;
        self.eval_str(&file, &source)
    }

    /// Evaluate `source`, naming it `file` in errors (not validated).
    pub fn eval_str(&self, file: &str, source: &str) -> Result<Loaded, PlanError> {
        *self
            .started
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner) = Instant::now();
        self.printed
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clear();
        lock(&self.params).declared.clear();
        let at = |pos: Position, message: String| PlanError {
            file: file.to_string(),
            pos: SourcePos::from_rhai(pos),
            message,
        };
        let ast = self
            .engine
            .compile(source)
            .map_err(|e| at(e.position(), format!("syntax error: {}", e.err_type())))?;
        let result: Dynamic = self
            .engine
            .eval_ast(&ast)
            .map_err(|e| script_error(file, *e))?;
        let printed = std::mem::take(
            &mut *self
                .printed
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner),
        );
        let type_name = result.type_name().to_string();
        let mut plan = result.try_cast::<Plan>().ok_or_else(|| {
            let line = source.lines().count().max(1);
            at(
                Position::new(u16::try_from(line).unwrap_or(u16::MAX), 1),
                format!(
                    "the script must end with a mission(#{{ .. }}) value; it returned {}",
                    friendly_type(&type_name)
                ),
            )
        })?;
        plan.file = file.to_string();
        let state = lock(&self.params);
        let params: BTreeMap<String, DeclaredParam> = state
            .declared
            .iter()
            .map(|(name, (default, value))| {
                let declared = DeclaredParam {
                    default: default.clone(),
                    value: value.clone(),
                    given: state.given.contains_key(name),
                };
                (name.clone(), declared)
            })
            .collect();
        let unused_params = state
            .given
            .keys()
            .filter(|k| !state.declared.contains_key(*k))
            .cloned()
            .collect();
        plan.params = params
            .iter()
            .map(|(k, p)| (k.clone(), p.value.clone()))
            .collect();
        Ok(Loaded {
            plan,
            printed,
            params,
            unused_params,
        })
    }
}

fn lock<T>(m: &Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// `param(name, default)`, one overload per type a default may have.
fn register_params(engine: &mut rhai::Engine, state: &Arc<Mutex<ParamState>>) {
    // One overload per type: the default wrapped as a `ParamValue`, the answer (of the same
    // variant) unwrapped.
    macro_rules! overload {
        ($ty:ty, $wrap:expr, $variant:ident, $unwrap:expr) => {{
            let state = Arc::clone(state);
            engine.register_fn(
                "param",
                move |ctx: NativeCallContext, name: ImmutableString, d: $ty| -> RhaiResult<$ty> {
                    match lock(&state)
                        .get(&name, $wrap(d))
                        .map_err(|e| runtime(&ctx, e))?
                    {
                        ParamValue::$variant(v) => Ok($unwrap(v)),
                        _ => unreachable_type(&ctx),
                    }
                },
            );
        }};
    }
    overload!(INT, ParamValue::Int, Int, |v| v);
    overload!(f64, ParamValue::Float, Float, |v| v);
    overload!(bool, ParamValue::Bool, Bool, |v| v);
    overload!(
        ImmutableString,
        |d: ImmutableString| ParamValue::Text(d.to_string()),
        Text,
        |v: String| ImmutableString::from(v)
    );
}

/// [`ParamState::get`] answers in its default's type; an error rather than a panic if not.
fn unreachable_type<T>(ctx: &NativeCallContext) -> RhaiResult<T> {
    Err(runtime(
        ctx,
        "param: internal error: the value's type differs from its default's".into(),
    ))
}

/// Turn a Rhai evaluation error into a one-line plan error at the innermost position.
fn script_error(file: &str, mut err: EvalAltResult) -> PlanError {
    let mut context = String::new();
    // Errors inside script functions: report where they happened, and say through which call.
    while let EvalAltResult::ErrorInFunctionCall(name, _, inner, pos) = err {
        context.push_str(&format!(
            " (in `{name}` called at {}:{})",
            pos.line().unwrap_or(0),
            pos.position().unwrap_or(0)
        ));
        err = *inner;
    }
    let pos = err.take_position();
    let message = match &err {
        EvalAltResult::ErrorRuntime(d, _) => d.to_string(),
        EvalAltResult::ErrorTerminated(d, _) => format!("stopped by the sandbox: {d}"),
        EvalAltResult::ErrorTooManyOperations(_) => {
            "stopped by the sandbox: too many operations (an endless loop?)".to_string()
        }
        EvalAltResult::ErrorStackOverflow(_) => {
            "stopped by the sandbox: calls nested too deeply (an endless recursion?)".to_string()
        }
        EvalAltResult::ErrorFunctionNotFound(sig, _) => function_not_found(sig),
        EvalAltResult::ErrorDataTooLarge(what, _) => {
            format!("stopped by the sandbox: {what} too large")
        }
        other => other.to_string(),
    };
    PlanError {
        file: file.to_string(),
        pos: SourcePos::from_rhai(pos),
        message: format!("{message}{context}"),
    }
}

fn function_not_found(sig: &str) -> String {
    let name = sig.split([' ', '(']).next().unwrap_or(sig);
    let args = sig[name.len()..].trim();
    if let Some((_, usage)) = API.iter().find(|(n, _)| *n == name) {
        let args = args
            .replace("f64", "number")
            .replace("i64", "integer")
            .replace("()", "");
        format!("`{name}` cannot take {args}; expected {usage}")
    } else {
        let names: Vec<_> = API.iter().map(|(n, _)| *n).collect();
        format!(
            "unknown function or primitive `{name}`; plan scripts may call {} and the functions \
             they define",
            names.join(", ")
        )
    }
}

fn friendly_type(rust_name: &str) -> String {
    match rust_name {
        "()" => "nothing".into(),
        "i64" => "an integer".into(),
        "f64" => "a number".into(),
        "bool" => "a boolean".into(),
        n if n.ends_with("Length") => "a length".into(),
        n if n.ends_with("Angle") => "an angle".into(),
        n if n.ends_with("Time") => "a time".into(),
        n if n.ends_with("Condition") => "a condition".into(),
        n if n.ends_with("Observable") => {
            "a quantity read at run time (compare it with a bound to make a condition)".into()
        }
        n if n.ends_with("Block") => "a when, repeat or checkpoint".into(),
        n if n.ends_with("Target") => "a target".into(),
        n if n.ends_with("Direction") => "a direction".into(),
        n if n.ends_with("Throw") => "a throw".into(),
        n if n.ends_with("Step") => "a step".into(),
        n if n.ends_with("WoundPoint") => "a wound point".into(),
        n if n.contains("Array") => "an array".into(),
        n if n.contains("Map") => "an object map".into(),
        n if n.contains("ImmutableString") || n.contains("String") => "a string".into(),
        n => n.rsplit("::").next().unwrap_or(n).to_string(),
    }
}

fn runtime(ctx: &NativeCallContext, message: String) -> Box<EvalAltResult> {
    Box::new(EvalAltResult::ErrorRuntime(
        message.into(),
        ctx.call_position(),
    ))
}

fn finite(ctx: &NativeCallContext, what: &str, v: f64) -> RhaiResult<f64> {
    if v.is_finite() {
        Ok(v)
    } else {
        Err(runtime(
            ctx,
            format!("{what}({v}): expected a finite number"),
        ))
    }
}

fn register_units(engine: &mut rhai::Engine) {
    engine.register_type_with_name::<Length>("Length");
    engine.register_type_with_name::<Angle>("Angle");
    macro_rules! unit {
        ($name:literal, $ty:ident, $scale:expr) => {
            engine.register_fn($name, |ctx: NativeCallContext, v: f64| -> RhaiResult<$ty> {
                Ok($ty(finite(&ctx, $name, v)? * $scale))
            });
            engine.register_fn($name, |v: INT| $ty(v as f64 * $scale));
        };
    }
    unit!("mm", Length, 1e-3);
    unit!("cm", Length, 1e-2);
    unit!("m", Length, 1.0);
    unit!("deg", Angle, std::f64::consts::PI / 180.0);
    unit!("rad", Angle, 1.0);
    engine.register_type_with_name::<Time>("Time");
    unit!("s", Time, 1.0);
    unit!("ms", Time, 1e-3);

    macro_rules! arithmetic {
        ($ty:ident) => {
            engine.register_fn("+", |a: $ty, b: $ty| $ty(a.0 + b.0));
            engine.register_fn("-", |a: $ty, b: $ty| $ty(a.0 - b.0));
            engine.register_fn("-", |a: $ty| $ty(-a.0));
            engine.register_fn("*", |a: $ty, k: f64| $ty(a.0 * k));
            engine.register_fn("*", |a: $ty, k: INT| $ty(a.0 * k as f64));
            engine.register_fn("*", |k: f64, a: $ty| $ty(a.0 * k));
            engine.register_fn("*", |k: INT, a: $ty| $ty(a.0 * k as f64));
            engine.register_fn("/", |a: $ty, k: f64| $ty(a.0 / k));
            engine.register_fn("/", |a: $ty, k: INT| $ty(a.0 / k as f64));
            engine.register_fn("/", |a: $ty, b: $ty| a.0 / b.0);
            engine.register_fn("<", |a: $ty, b: $ty| a.0 < b.0);
            engine.register_fn(">", |a: $ty, b: $ty| a.0 > b.0);
            engine.register_fn("<=", |a: $ty, b: $ty| a.0 <= b.0);
            engine.register_fn(">=", |a: $ty, b: $ty| a.0 >= b.0);
        };
    }
    arithmetic!(Length);
    arithmetic!(Angle);
    arithmetic!(Time);
    engine.register_fn("to_string", |a: &mut Time| format!("{} s", a.0));
    engine.register_fn("to_debug", |a: &mut Time| format!("{} s", a.0));
    engine.register_fn("to_string", |a: &mut Length| format!("{} mm", a.0 * 1e3));
    engine.register_fn("to_debug", |a: &mut Length| format!("{} mm", a.0 * 1e3));
    engine.register_fn("to_string", |a: &mut Angle| {
        format!("{}°", a.0.to_degrees())
    });
    engine.register_fn("to_debug", |a: &mut Angle| format!("{}°", a.0.to_degrees()));
}

fn register_plan_api(engine: &mut rhai::Engine, wound: Wound) {
    engine.register_type_with_name::<WoundPoint>("WoundPoint");
    engine.register_type_with_name::<Step>("Step");
    engine.register_type_with_name::<Throw>("Throw");
    engine.register_type_with_name::<Plan>("Mission");
    engine.register_get("index", |p: &mut WoundPoint| p.index as INT);
    engine.register_fn("to_string", |p: &mut WoundPoint| {
        format!("wound point {}", p.index + 1)
    });
    engine.register_fn("to_string", |s: &mut Step| s.kind.name().to_string());
    engine.register_fn("to_string", |t: &mut Throw| {
        format!(
            "throw at wound point {} ({} steps)",
            t.point.index + 1,
            t.steps().count()
        )
    });

    let points = wound.points;
    engine.register_fn("wound", move || -> Array {
        points.iter().cloned().map(Dynamic::from).collect()
    });

    for name in STEP_NAMES {
        engine.register_fn(name, move |ctx: NativeCallContext| -> RhaiResult<Step> {
            make_step(&ctx, name, None)
        });
        engine.register_fn(
            name,
            move |ctx: NativeCallContext, params: Map| -> RhaiResult<Step> {
                make_step(&ctx, name, Some(params))
            },
        );
    }

    engine.register_fn(
        "suture",
        |ctx: NativeCallContext, point: WoundPoint, steps: Array| -> RhaiResult<Throw> {
            let body = nodes(&ctx, "suture", steps)?;
            let ops = unrolled_len(&body);
            if ops > caps::OPS_PER_THROW {
                return Err(runtime(
                    &ctx,
                    format!(
                        "suture: the throw unrolls to {ops} operations (loops at their bound); \
                         the limit is {}",
                        caps::OPS_PER_THROW
                    ),
                ));
            }
            Ok(Throw::new(
                point,
                body,
                SourcePos::from_rhai(ctx.call_position()),
            ))
        },
    );

    engine.register_fn("mission", |ctx: NativeCallContext, map: Map| -> RhaiResult<Plan> {
        let mut plan = Plan {
            name: String::new(),
            file: String::new(),
            interventions: 0,
            thread_length_m: None,
            throws: Vec::new(),
            pos: SourcePos::from_rhai(ctx.call_position()),
            params: BTreeMap::new(),
        };
        let mut has_throws = false;
        for (key, value) in map {
            let type_name = friendly_type(value.type_name());
            match key.as_str() {
                "name" => {
                    plan.name = value.into_immutable_string().map(|s| s.to_string()).map_err(
                        |_| runtime(&ctx, format!("mission: `name` must be a string, found {type_name}")),
                    )?;
                }
                "interventions" => {
                    let n = value.as_int().map_err(|_| {
                        runtime(&ctx, format!("mission: `interventions` must be a whole number 0 to 2, found {type_name}"))
                    })?;
                    if n < 0 {
                        return Err(runtime(&ctx, format!("mission: interventions {n} must be 0 or more")));
                    }
                    plan.interventions = u8::try_from(n).unwrap_or(u8::MAX);
                }
                "throws" => {
                    has_throws = true;
                    let arr = value.into_array().map_err(|_| {
                        runtime(&ctx, format!("mission: `throws` must be an array of suture(..), found {type_name}"))
                    })?;
                    for (i, t) in arr.into_iter().enumerate() {
                        let type_name = friendly_type(t.type_name());
                        plan.throws.push(t.try_cast::<Throw>().ok_or_else(|| {
                            runtime(
                                &ctx,
                                format!("mission: throws[{i}] is {type_name}; expected suture(point, [steps])"),
                            )
                        })?);
                    }
                }
                "thread_length" => {
                    let found = describe_value(&value);
                    let l = value.try_cast::<Length>().ok_or_else(|| {
                        runtime(&ctx, format!("mission: `thread_length` must be a length, written cm(..), found {found}"))
                    })?;
                    plan.thread_length_m = Some(l.0);
                }
                other => {
                    return Err(runtime(
                        &ctx,
                        format!("mission: unknown key `{other}`; expected name, interventions, throws, thread_length"),
                    ));
                }
            }
        }
        if !has_throws {
            return Err(runtime(&ctx, "mission: missing `throws`".into()));
        }
        Ok(plan)
    });
}

fn make_step(ctx: &NativeCallContext, name: &'static str, params: Option<Map>) -> RhaiResult<Step> {
    let mut kind = StepKind::default_for(name)
        .ok_or_else(|| runtime(ctx, format!("unknown primitive `{name}`")))?;
    let specs = param_specs(name);
    for (key, value) in params.unwrap_or_default() {
        let Some(spec) = specs.iter().find(|s| s.name == key.as_str()) else {
            let names: Vec<_> = specs.iter().map(|s| s.name).collect();
            return Err(runtime(
                ctx,
                format!(
                    "{name}: unknown parameter `{key}`; expected {}",
                    if names.is_empty() {
                        "none".to_string()
                    } else {
                        names.join(", ")
                    }
                ),
            ));
        };
        let found = describe_value(&value);
        let wrong = |expected: &str| {
            runtime(
                ctx,
                format!("{name}: `{key}` must be {expected}, found {found}"),
            )
        };
        let v = match spec.quantity {
            Quantity::Length => match value.try_cast::<Length>() {
                Some(l) => Value::Length(l.0),
                None => return Err(wrong("a length, written mm(..), cm(..) or m(..)")),
            },
            Quantity::Angle => match value.try_cast::<Angle>() {
                Some(a) => Value::Angle(a.0),
                None => return Err(wrong("an angle, written deg(..) or rad(..)")),
            },
            Quantity::Count => match value.as_int() {
                Ok(n) => Value::Count(n),
                Err(_) => {
                    let found = value.as_float().map_or(found, |x| x.to_string());
                    return Err(runtime(
                        ctx,
                        format!("{name}: `{key}` must be a whole number, found {found}"),
                    ));
                }
            },
        };
        kind.set(spec.name, v)
            .map_err(|e| runtime(ctx, e.to_string()))?;
    }
    Ok(Step {
        kind,
        pos: SourcePos::from_rhai(ctx.call_position()),
    })
}

fn describe_value(v: &Dynamic) -> String {
    if let Some(l) = v.clone().try_cast::<Length>() {
        format!("a length ({} mm)", l.0 * 1e3)
    } else if let Some(a) = v.clone().try_cast::<Angle>() {
        format!("an angle ({}°)", a.0.to_degrees())
    } else if let Ok(n) = v.as_int() {
        format!("a bare number {n} (say its unit, e.g. mm({n}) or deg({n}))")
    } else if let Ok(x) = v.as_float() {
        format!("a bare number {x} (say its unit, e.g. mm({x}) or deg({x}))")
    } else {
        friendly_type(v.type_name())
    }
}

/// The elements of a step list: steps and constructs.
fn nodes(ctx: &NativeCallContext, what: &str, items: Array) -> RhaiResult<Vec<Node>> {
    items
        .into_iter()
        .enumerate()
        .map(|(i, item)| {
            let type_name = item.type_name().to_string();
            if item.is::<Step>() {
                return Ok(Node::Step(item.cast::<Step>()));
            }
            item.try_cast::<Block>().map(|b| b.0).ok_or_else(|| {
                runtime(
                    ctx,
                    format!(
                        "{what}: element {} of the step list is {}; expected a primitive such as \
                         insert() or extract(#{{ retries: 5 }}), or when(..), repeat(..), \
                         checkpoint(..)",
                        i + 1,
                        friendly_type(&type_name)
                    ),
                )
            })
        })
        .collect()
}

/// How deeply constructs nest in `nodes` (0: none).
fn depth(nodes: &[Node]) -> usize {
    nodes
        .iter()
        .map(|n| match n {
            Node::Step(_) | Node::Checkpoint { .. } => 0,
            Node::When {
                then, otherwise, ..
            } => 1 + depth(then).max(depth(otherwise)),
            Node::Repeat { body, .. } => 1 + depth(body),
        })
        .max()
        .unwrap_or(0)
}

/// Operations `nodes` compile to (saturating), without compiling them.
fn unrolled_len(nodes: &[Node]) -> usize {
    nodes.iter().fold(0usize, |acc, n| {
        acc.saturating_add(match n {
            Node::Step(_) | Node::Checkpoint { .. } => 1,
            Node::When {
                then, otherwise, ..
            } => 2usize
                .saturating_add(unrolled_len(then))
                .saturating_add(unrolled_len(otherwise)),
            Node::Repeat {
                max, until, body, ..
            } => (unrolled_len(body).saturating_add(usize::from(until.is_some())))
                .saturating_mul(usize::from(*max)),
        })
    })
}

/// A construct around `inner`, refused if it nests too deeply.
fn block(ctx: &NativeCallContext, what: &str, node: Node, inner: usize) -> RhaiResult<Block> {
    if inner + 1 > caps::NESTING {
        return Err(runtime(
            ctx,
            format!(
                "{what}: constructs nest {} deep here; the limit is {} (when and repeat inside \
                 each other)",
                inner + 1,
                caps::NESTING
            ),
        ));
    }
    // A block is opaque to the sandbox's size limits: bound it here, before it is copied
    // into arrays or other blocks.
    let ops = unrolled_len(std::slice::from_ref(&node));
    if ops > caps::OPS_PER_THROW {
        return Err(runtime(
            ctx,
            format!(
                "{what}: unrolls to {ops} operations (loops at their bound); a throw's limit is {}",
                caps::OPS_PER_THROW
            ),
        ));
    }
    Ok(Block(node))
}

/// A combination, refused if it grows past the engine's bound on a condition's terms (a
/// condition is opaque to the sandbox's size limits: `c = all([c, c])` in a loop doubles).
fn combined(ctx: &NativeCallContext, what: &str, c: Condition) -> RhaiResult<Condition> {
    let terms = c.terms();
    if terms > caps::CONDITION_TERMS {
        return Err(runtime(
            ctx,
            format!(
                "{what}: the condition has {terms} terms; the limit is {}",
                caps::CONDITION_TERMS
            ),
        ));
    }
    Ok(c)
}

fn as_condition(ctx: &NativeCallContext, what: &str, v: Dynamic) -> RhaiResult<Condition> {
    let type_name = v.type_name().to_string();
    if v.is::<Condition>() {
        return Ok(v.cast::<Condition>());
    }
    let hint = if v.is::<Observable>() {
        "; compare it with a bound, e.g. needle_confidence() >= 0.8"
    } else if v.is::<bool>() {
        "; a script's true or false is fixed before the mission starts, a condition is \
         decided when the plan reaches it (e.g. needle_seen())"
    } else {
        ""
    };
    Err(runtime(
        ctx,
        format!(
            "{what}: expected a condition, found {}{hint}",
            friendly_type(&type_name)
        ),
    ))
}

fn conditions(ctx: &NativeCallContext, what: &str, items: Array) -> RhaiResult<Vec<Condition>> {
    items
        .into_iter()
        .map(|c| as_condition(ctx, what, c))
        .collect()
}

fn compare(
    ctx: &NativeCallContext,
    q: Observable,
    cmp: Cmp,
    unit: Unit,
    bound: f64,
    shown: String,
) -> RhaiResult<Condition> {
    let want = q.0.unit();
    let name = q.0.describe();
    if want != unit && !(want == Unit::Number && unit == Unit::Count) {
        return Err(runtime(
            ctx,
            format!(
                "{name} {} {shown}: {name} must be compared with {}",
                cmp.symbol(),
                want.expected()
            ),
        ));
    }
    if matches!(cmp, Cmp::Eq | Cmp::Ne) && want != Unit::Count {
        return Err(runtime(
            ctx,
            format!(
                "{name} {} {shown}: only whole-number quantities can be compared with == or !=; \
                 use <, <=, > or >=",
                cmp.symbol()
            ),
        ));
    }
    if !bound.is_finite() {
        return Err(runtime(
            ctx,
            format!("{name}: the bound {shown} is not finite"),
        ));
    }
    Ok(Condition::Compare {
        quantity: q.0,
        cmp,
        bound,
    })
}

fn register_conditions(engine: &mut rhai::Engine) {
    engine.register_type_with_name::<Condition>("Condition");
    engine.register_type_with_name::<Observable>("Observable");
    engine.register_type_with_name::<Block>("Block");
    engine.register_type_with_name::<Target>("Target");
    engine.register_type_with_name::<Direction>("Direction");
    engine.register_fn("to_string", |c: &mut Condition| c.to_string());
    engine.register_fn("to_debug", |c: &mut Condition| c.to_string());

    macro_rules! observable {
        ($name:literal, $q:expr) => {
            engine.register_fn($name, || Observable($q));
        };
    }
    observable!("needle_confidence", Q::NeedleConfidence);
    observable!("needle_age", Q::NeedleAge);
    observable!("thread_left", Q::ThreadLeft);
    observable!("thread_free", Q::ThreadFree);
    engine.register_fn("thread_clearance", |t: Target| {
        Observable(Q::ThreadClearance { from: t })
    });
    engine.register_fn("thread_wrap", |t: Target| {
        Observable(Q::ThreadWrap { round: t })
    });
    observable!("throw_number", Q::ThrowNumber);
    observable!("interventions_left", Q::InterventionsLeft);
    observable!("retries_used", Q::RetriesUsed);
    engine.register_fn("needle_seen", || Condition::NeedleSeen);
    engine.register_fn("needle_normal_angle", |d: Direction| {
        Observable(Q::NeedleNormalAngle { to: d.0 })
    });
    engine.register_fn("needle_tip_distance", |t: Target| {
        Observable(Q::NeedleEndDistance {
            end: End::Tip,
            to: t,
        })
    });
    engine.register_fn("needle_swage_distance", |t: Target| {
        Observable(Q::NeedleEndDistance {
            end: End::Swage,
            to: t,
        })
    });
    engine.register_fn("right_jaw", || Target::RightJaw);
    engine.register_fn("left_jaw", || Target::LeftJaw);
    engine.register_fn(
        "needle_point",
        |ctx: NativeCallContext, a: Dynamic| -> RhaiResult<Target> {
            let found = describe_value(&a);
            match a.try_cast::<Angle>() {
                Some(Angle(v)) if (0.0..=std::f64::consts::PI).contains(&v) => {
                    Ok(Target::NeedlePoint(v))
                }
                Some(_) => Err(runtime(
                    &ctx,
                    format!(
                        "needle_point: the angle must lie from deg(0) (the tip) to deg(180) (the swage), found {found}"
                    ),
                )),
                None => Err(runtime(
                    &ctx,
                    format!("needle_point: the argument must be an angle, written deg(..), found {found}"),
                )),
            }
        },
    );
    engine.register_fn(
        "point",
        |ctx: NativeCallContext, x: Dynamic, y: Dynamic, z: Dynamic| -> RhaiResult<Target> {
            let mut p = [0.0; 3];
            for (i, v) in [x, y, z].into_iter().enumerate() {
                let found = describe_value(&v);
                p[i] = v.try_cast::<Length>().map(|l| l.0).ok_or_else(|| {
                    runtime(
                        &ctx,
                        format!(
                            "point: coordinate {} must be a length, found {found}",
                            i + 1
                        ),
                    )
                })?;
            }
            Ok(Target::Point(p))
        },
    );
    engine.register_get("entry", |p: &mut WoundPoint| {
        Target::Point([p.entry.x, p.entry.y, p.entry.z])
    });
    engine.register_get("exit", |p: &mut WoundPoint| {
        Target::Point([p.exit.x, p.exit.y, p.exit.z])
    });
    engine.register_fn(
        "direction",
        |ctx: NativeCallContext, x: Dynamic, y: Dynamic, z: Dynamic| -> RhaiResult<Direction> {
            let mut d = [0.0; 3];
            for (i, v) in [x, y, z].into_iter().enumerate() {
                d[i] = v
                    .as_float()
                    .or_else(|_| v.as_int().map(|n| n as f64))
                    .map_err(|_| {
                        runtime(
                            &ctx,
                            format!(
                                "direction: component {} must be a plain number, found {}",
                                i + 1,
                                describe_value(&v)
                            ),
                        )
                    })?;
            }
            let n = (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
            if !(n.is_finite() && n > 1e-9) {
                return Err(runtime(
                    &ctx,
                    "direction: expected a non-zero, finite direction".into(),
                ));
            }
            Ok(Direction([d[0] / n, d[1] / n, d[2] / n]))
        },
    );

    macro_rules! comparisons {
        ($rhs:ty, $unit:expr, $val:expr, $show:expr) => {
            for (op, cmp) in [
                ("<", Cmp::Lt),
                ("<=", Cmp::Le),
                (">", Cmp::Gt),
                (">=", Cmp::Ge),
                ("==", Cmp::Eq),
                ("!=", Cmp::Ne),
            ] {
                engine.register_fn(
                    op,
                    move |ctx: NativeCallContext,
                          q: Observable,
                          b: $rhs|
                          -> RhaiResult<Condition> {
                        compare(&ctx, q, cmp, $unit, $val(&b), $show(&b))
                    },
                );
            }
        };
    }
    comparisons!(f64, Unit::Number, |b: &f64| *b, |b: &f64| b.to_string());
    comparisons!(INT, Unit::Count, |b: &INT| *b as f64, |b: &INT| b
        .to_string());
    comparisons!(
        Length,
        Unit::Length,
        |b: &Length| b.0,
        |b: &Length| format!("{} mm", b.0 * 1e3)
    );
    comparisons!(Angle, Unit::Angle, |b: &Angle| b.0, |b: &Angle| format!(
        "{}°",
        b.0.to_degrees()
    ));
    comparisons!(Time, Unit::Time, |b: &Time| b.0, |b: &Time| format!(
        "{} s",
        b.0
    ));

    let all: fn(Vec<Condition>) -> Condition = |of| Condition::All { of };
    let any: fn(Vec<Condition>) -> Condition = |of| Condition::Any { of };
    for (name, make) in [("all", all), ("any", any)] {
        engine.register_fn(
            name,
            move |ctx: NativeCallContext, items: Array| -> RhaiResult<Condition> {
                combined(&ctx, name, make(conditions(&ctx, name, items)?))
            },
        );
    }
    engine.register_fn(
        "not",
        |ctx: NativeCallContext, c: Dynamic| -> RhaiResult<Condition> {
            let c = Condition::Not {
                of: Box::new(as_condition(&ctx, "not", c)?),
            };
            combined(&ctx, "not", c)
        },
    );

    engine.register_fn(
        "when",
        |ctx: NativeCallContext, cond: Dynamic, steps: Array| -> RhaiResult<Block> {
            let cond = as_condition(&ctx, "when", cond)?;
            let then = nodes(&ctx, "when", steps)?;
            let inner = depth(&then);
            let node = Node::When {
                cond,
                then,
                otherwise: Vec::new(),
                pos: SourcePos::from_rhai(ctx.call_position()),
            };
            block(&ctx, "when", node, inner)
        },
    );
    engine.register_fn(
        "otherwise",
        |ctx: NativeCallContext, b: Block, steps: Array| -> RhaiResult<Block> {
            let Node::When {
                cond,
                then,
                otherwise,
                pos,
            } = b.0
            else {
                return Err(runtime(
                    &ctx,
                    "otherwise: follows a when(..), as in when(c, [..]).otherwise([..])".into(),
                ));
            };
            if !otherwise.is_empty() {
                return Err(runtime(&ctx, "otherwise: this when already has one".into()));
            }
            let otherwise = nodes(&ctx, "otherwise", steps)?;
            let inner = depth(&then).max(depth(&otherwise));
            let node = Node::When {
                cond,
                then,
                otherwise,
                pos,
            };
            block(&ctx, "when", node, inner)
        },
    );
    engine.register_fn(
        "repeat",
        |ctx: NativeCallContext, params: Map, steps: Array| -> RhaiResult<Block> {
            let mut max = None;
            let mut until = None;
            for (key, value) in params {
                match key.as_str() {
                    "max" => {
                        let found = describe_value(&value);
                        let n = value.as_int().map_err(|_| {
                            runtime(
                                &ctx,
                                format!(
                                    "repeat: `max` must be a whole number 1 to {}, found {found}",
                                    caps::REPEAT
                                ),
                            )
                        })?;
                        if n < 1 || n > INT::from(caps::REPEAT) {
                            return Err(runtime(
                                &ctx,
                                format!(
                                    "repeat: max {n} is out of range; expected 1 to {} (the \
                                     engine's hard cap: a plan cannot build an unbounded run)",
                                    caps::REPEAT
                                ),
                            ));
                        }
                        max = u8::try_from(n).ok();
                    }
                    // `until` is a Rhai keyword (do .. until), so the key is `stop_when`.
                    "stop_when" => {
                        until = Some(as_condition(&ctx, "repeat: `stop_when`", value)?);
                    }
                    other => {
                        return Err(runtime(
                            &ctx,
                            format!("repeat: unknown key `{other}`; expected max, stop_when"),
                        ));
                    }
                }
            }
            let Some(max) = max else {
                return Err(runtime(
                    &ctx,
                    format!("repeat: missing `max` (1 to {})", caps::REPEAT),
                ));
            };
            let body = nodes(&ctx, "repeat", steps)?;
            if body.is_empty() {
                return Err(runtime(&ctx, "repeat: expected steps, found none".into()));
            }
            let inner = depth(&body);
            let node = Node::Repeat {
                max,
                until,
                body,
                pos: SourcePos::from_rhai(ctx.call_position()),
            };
            block(&ctx, "repeat", node, inner)
        },
    );
    engine.register_fn(
        "checkpoint",
        |ctx: NativeCallContext, label: ImmutableString| -> RhaiResult<Block> {
            let label = label.trim().to_string();
            if label.is_empty() {
                return Err(runtime(
                    &ctx,
                    "checkpoint: the label must say what the surgeon confirms".into(),
                ));
            }
            Ok(Block(Node::Checkpoint {
                label,
                pos: SourcePos::from_rhai(ctx.call_position()),
            }))
        },
    );
}
