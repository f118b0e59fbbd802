//! The Rhai host: a sandboxed engine that evaluates a plan script once and returns a typed
//! [`Plan`].
//!
//! The sandbox starts from `Engine::new_raw()` and opts into only what plans need: arithmetic,
//! logic, strings, arrays, maps, maths and iterators. No `import` (the `no_module` feature),
//! no `eval`, no `sleep` or `exit` (the language-core package is left out), no time. Limits
//! on operations, call depth, expression depth and string/array/map sizes, strict variables,
//! and a wall-clock deadline checked through `on_progress`.

use crate::plan::{Plan, PlanError, SourcePos, Step, Throw};
use rhai::packages::{
    ArithmeticPackage, BasicArrayPackage, BasicIteratorPackage, BasicMapPackage, BasicMathPackage,
    BasicStringPackage, LogicPackage, Package,
};
use rhai::{Array, Dynamic, EvalAltResult, INT, Map, NativeCallContext, Position};
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

/// What scripts may call, with usage, for error messages and the scripting reference.
pub const API: &[(&str, &str)] = &[
    ("mm", "mm(number) → length in millimetres"),
    ("cm", "cm(number) → length in centimetres"),
    ("m", "m(number) → length in metres"),
    ("deg", "deg(number) → angle in degrees"),
    ("rad", "rad(number) → angle in radians"),
    ("wound", "wound() → the wound's points, in suturing order"),
    ("suture", "suture(wound_point, [steps]) → one suture throw"),
    (
        "mission",
        "mission(#{ name: \"..\", interventions: 0..2, throws: [..] }) → the plan",
    ),
    (
        "insert",
        "insert() or insert(#{ rotation: deg(..), push: mm(..), standoff: cm(..) })",
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
];

/// Evaluates plan scripts in the sandbox.
#[derive(Debug)]
pub struct PlanLoader {
    engine: rhai::Engine,
    started: Arc<Mutex<Instant>>,
    printed: Arc<Mutex<Vec<String>>>,
}

/// A plan and what its script printed while building it.
#[derive(Clone, Debug, PartialEq)]
pub struct Loaded {
    /// The plan, not yet validated.
    pub plan: Plan,
    /// Lines the script printed with `print`/`debug`.
    pub printed: Vec<String>,
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

        register_units(&mut engine);
        register_plan_api(&mut engine, wound.clone());
        Self {
            engine,
            started,
            printed,
        }
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
        Ok(Loaded { plan, printed })
    }
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
            t.steps.len()
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
            let steps = steps
                .into_iter()
                .enumerate()
                .map(|(i, s)| {
                    let type_name = s.type_name().to_string();
                    s.try_cast::<Step>().ok_or_else(|| {
                        runtime(
                            &ctx,
                            format!(
                                "suture: element {} of the step list is {}; expected a primitive \
                                 such as insert() or extract(#{{ retries: 5 }})",
                                i + 1,
                                friendly_type(&type_name)
                            ),
                        )
                    })
                })
                .collect::<RhaiResult<Vec<_>>>()?;
            Ok(Throw {
                point,
                steps,
                pos: SourcePos::from_rhai(ctx.call_position()),
            })
        },
    );

    engine.register_fn("mission", |ctx: NativeCallContext, map: Map| -> RhaiResult<Plan> {
        let mut plan = Plan {
            name: String::new(),
            file: String::new(),
            interventions: 0,
            throws: Vec::new(),
            pos: SourcePos::from_rhai(ctx.call_position()),
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
                other => {
                    return Err(runtime(
                        &ctx,
                        format!("mission: unknown key `{other}`; expected name, interventions, throws"),
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
