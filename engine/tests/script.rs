//! The Rhai host: plans load from scripts; bad scripts get one-line errors at their position;
//! the sandbox stops runaway scripts.

use std::time::{Duration, Instant};
use stitch_engine::{PlanLoader, ScriptLimits, load_plan, load_plan_str};
use stitch_primitives::StepKind;
use stitch_robot::{Wound, WoundSpec};

fn loader() -> PlanLoader {
    PlanLoader::new(
        &Wound::linear(&WoundSpec::default()).expect("default wound"),
        ScriptLimits::default(),
    )
}

fn scripts() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts")
}

/// The one error a script gets: `file:line:col: message`, on one line.
fn error_of(source: &str) -> String {
    let e = load_plan_str(&loader(), "plan.rhai", source).expect_err("the script is invalid");
    let text = e.to_string();
    assert_eq!(text.lines().count(), 1, "one line: {text}");
    text
}

const GOOD_THROW: &str = "insert(), sweep(), extract(), cinch(), handover(), correct()";

#[test]
fn the_shipped_policies_load_and_validate() {
    for (file, name, throws, steps, interventions) in [
        ("stitch.rhai", "STITCH", 6, 6, 0),
        ("stitch_human.rhai", "STITCH + Human", 6, 6, 2),
        ("sensing_only.rhai", "Sensing Only", 6, 3, 0),
        ("thread_handling.rhai", "Thread Handling", 6, 5, 0),
        // Unrolled: 3 needle queries, the 6 steps, 2 more corrections.
        ("stitch_reactive.rhai", "STITCH Reactive", 6, 11, 0),
        (
            "stitch_reactive_human.rhai",
            "STITCH Reactive + Human",
            6,
            11,
            2,
        ),
    ] {
        let loaded = load_plan(&loader(), &scripts().join(file)).unwrap_or_else(|e| panic!("{e}"));
        let plan = loaded.plan;
        assert_eq!(plan.name, name);
        assert_eq!(plan.throws.len(), throws, "{file}");
        assert!(
            plan.throws.iter().all(|t| t.steps().count() == steps),
            "{file}"
        );
        assert_eq!(plan.interventions, interventions, "{file}");
        // One throw per wound point, in order.
        for (i, t) in plan.throws.iter().enumerate() {
            assert_eq!(t.point.index, i);
        }
    }
}

#[test]
fn units_and_parameters_reach_the_plan_in_si() {
    let src = "let t = suture(wound()[0], [insert(#{ rotation: deg(30), push: mm(3) }), \
               extract(#{ retries: 2, offset: cm(1) + mm(5) }), handover()]);\n\
               mission(#{ name: \"x\", throws: [t] })";
    let plan = load_plan_str(&loader(), "p.rhai", src).expect("valid").plan;
    let steps: Vec<_> = plan.throws[0].steps().map(|(_, s)| s).collect();
    match (&steps[0].kind, &steps[1].kind) {
        (StepKind::Insert(i), StepKind::Extract(e)) => {
            assert!((i.rotation_rad - 30f64.to_radians()).abs() < 1e-12);
            assert!((i.push_m - 0.003).abs() < 1e-12);
            assert_eq!(e.retries, 2);
            assert!((e.offset_m - 0.015).abs() < 1e-12);
        }
        other => panic!("unexpected steps {other:?}"),
    }
    // Positions are the calls' own.
    assert_eq!((steps[0].pos.line, steps[1].pos.line), (1, 1));
    assert!(steps[1].pos.col > steps[0].pos.col);
}

#[test]
fn a_syntax_error_names_its_position() {
    let e = error_of("let x = ;\nmission(#{ throws: [] })");
    assert!(e.starts_with("plan.rhai:1:9: syntax error"), "{e}");
}

#[test]
fn an_unknown_primitive_names_its_position_and_the_known_ones() {
    let e = error_of(&format!(
        "let t = suture(wound()[0], [\n    insert(),\n    stab(),\n    {GOOD_THROW}]);\nmission(#{{ throws: [t] }})"
    ));
    assert!(
        e.starts_with("plan.rhai:3:5: unknown function or primitive `stab`"),
        "{e}"
    );
    assert!(e.contains("insert, sweep, extract"), "{e}");
}

#[test]
fn a_wrong_unit_names_the_parameter_and_the_expected_unit() {
    let e = error_of("let t = suture(wound()[0], [insert(), sweep(#{ distance: deg(5) })]);");
    assert!(
        e.starts_with("plan.rhai:1:39: sweep: `distance` must be a length, written mm(..), cm(..) or m(..), found an angle (5°)"),
        "{e}"
    );
    let e = error_of("let s = insert(#{ push: 4 });");
    assert!(
        e.contains("`push` must be a length") && e.contains("found a bare number 4"),
        "{e}"
    );
    let e = error_of("let s = extract(#{ retries: 2.5 });");
    assert!(
        e.starts_with("plan.rhai:1:9: extract: `retries` must be a whole number, found 2.5"),
        "{e}"
    );
}

#[test]
fn a_needle_point_takes_an_angle_from_tip_to_swage() {
    let e = error_of("let c = needle_tip_distance(needle_point(mm(3))) < mm(2);");
    assert!(
        e.starts_with("plan.rhai:1:29: needle_point: the argument must be an angle, written deg(..), found a length (3 mm)"),
        "{e}"
    );
    let e = error_of("let c = needle_tip_distance(needle_point(deg(200))) < mm(2);");
    assert!(
        e.starts_with("plan.rhai:1:29: needle_point: the angle must lie from deg(0) (the tip) to deg(180) (the swage), found an angle (200°)"),
        "{e}"
    );
    // A handover's thread margin is a length within its range, checked at the call.
    let e = error_of(&format!(
        "let t = suture(wound()[0], [{GOOD_THROW}, handover(#{{ thread_margin: deg(3) }})]);"
    ));
    assert!(
        e.contains("handover: `thread_margin` must be a length"),
        "{e}"
    );
    let e = error_of(
        "let h = handover(#{ thread_margin: cm(2) });\nmission(#{ name: \"x\", throws: [suture(wound()[0], [insert(), extract(), h])] })",
    );
    assert!(
        e.starts_with("plan.rhai:1:9: throw 1: handover: thread_margin = 20.00 mm is out of range; expected 0.0 mm to 10.0 mm"),
        "{e}"
    );
}

#[test]
fn a_negative_count_is_refused_at_its_call_not_read_as_zero() {
    // `samples: 0` means "insert open loop on the last correction's grasp": a negative
    // count read as zero would pass validation and change what the robot does.
    let e = error_of("let s = insert(#{ samples: -1 });");
    assert!(
        e.starts_with(
            "plan.rhai:1:9: insert: `samples` is a count and cannot be negative, found -1"
        ),
        "{e}"
    );
    let e = error_of("let s = extract(#{ retries: -3 });");
    assert!(
        e.contains("`retries` is a count and cannot be negative, found -3"),
        "{e}"
    );
}

#[test]
fn extract_with_nine_retries_is_refused_at_its_call() {
    let e = error_of(
        "let t = suture(wound()[0], [insert(), sweep(),\n  extract(#{ retries: 9 }), handover()]);\nmission(#{ name: \"x\", throws: [t] })",
    );
    assert!(
        e.starts_with(
            "plan.rhai:2:3: throw 1: extract: retries 9 exceeds the engine's hard cap of 5"
        ),
        "{e}"
    );
}

#[test]
fn handover_before_extract_is_refused_at_the_handover() {
    let e = error_of(
        "let t = suture(wound()[0], [\n  insert(),\n  handover(),\n  extract()]);\nmission(#{ name: \"x\", throws: [t] })",
    );
    assert!(
        e.starts_with("plan.rhai:3:3: throw 1: handover needs the needle in the left jaw"),
        "{e}"
    );
}

#[test]
fn the_script_must_return_a_mission() {
    let e = error_of("let x = 1;\nx");
    assert!(
        e.starts_with("plan.rhai:2:1: the script must end with a mission"),
        "{e}"
    );
    assert!(e.ends_with("it returned an integer"), "{e}");
}

#[test]
fn errors_in_script_functions_point_inside_the_function() {
    let e = error_of("fn bad() {\n  insert(#{ spin: deg(3) })\n}\nlet s = bad();");
    assert!(
        e.starts_with("plan.rhai:2:3: insert: unknown parameter `spin`; expected rotation, push"),
        "{e}"
    );
    assert!(e.contains("(in `bad` called at 4:9)"), "{e}");
}

#[test]
fn undefined_variables_are_refused_before_running() {
    let e = error_of(
        "let t = suture(wound()[0], [insert()]);\nmission(#{ name: \"x\", throws: [t, u] })",
    );
    assert!(
        e.starts_with("plan.rhai:2:35: syntax error: Undefined variable: u"),
        "{e}"
    );
}

#[test]
fn an_endless_loop_is_stopped_within_a_second() {
    let t0 = Instant::now();
    let e = error_of("let i = 0;\nloop { i += 1; }");
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "took {:?}",
        t0.elapsed()
    );
    assert!(
        e.contains("stopped by the sandbox: too many operations"),
        "{e}"
    );
}

#[test]
fn a_deep_recursion_is_stopped_within_a_second() {
    let t0 = Instant::now();
    let e = error_of("fn down(n) { down(n + 1) }\ndown(0)");
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "took {:?}",
        t0.elapsed()
    );
    assert!(
        e.contains("stopped by the sandbox: calls nested too deeply"),
        "{e}"
    );
}

#[test]
fn the_deadline_stops_a_script_that_stays_under_the_operation_limit() {
    let limits = ScriptLimits {
        max_operations: 0, // unlimited: only the deadline can stop it
        deadline: Duration::from_millis(100),
        ..ScriptLimits::default()
    };
    let loader = PlanLoader::new(
        &Wound::linear(&WoundSpec::default()).expect("wound"),
        limits,
    );
    let t0 = Instant::now();
    let e = load_plan_str(&loader, "plan.rhai", "let i = 0;\nwhile true { i += 1; }")
        .expect_err("stopped");
    assert!(
        t0.elapsed() < Duration::from_secs(1),
        "took {:?}",
        t0.elapsed()
    );
    assert!(
        e.to_string()
            .contains("ran past the sandbox deadline of 100 ms"),
        "{e}"
    );
}

#[test]
fn the_sandbox_offers_no_eval_and_no_sleep() {
    let e = error_of("eval(\"1\")");
    assert!(e.contains("eval"), "{e}");
    let e = error_of("sleep(10)");
    assert!(e.contains("unknown function or primitive `sleep`"), "{e}");
}

#[test]
fn oversized_arrays_are_stopped() {
    let e = error_of("let a = [];\nfor i in 0..5000 { a.push(i); }");
    assert!(e.contains("stopped by the sandbox"), "{e}");
}

/// The scripting reference in docs/scripting.md is what the sandbox registers.
#[test]
fn the_scripting_reference_in_the_docs_is_generated_from_the_registered_api() {
    use stitch_engine::{REFERENCE_BEGIN, REFERENCE_END, reference_markdown};
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs/scripting.md");
    let doc = std::fs::read_to_string(&path).expect("docs/scripting.md");
    let (Some(a), Some(b)) = (doc.find(REFERENCE_BEGIN), doc.find(REFERENCE_END)) else {
        panic!("docs/scripting.md lacks the {REFERENCE_BEGIN} / {REFERENCE_END} lines");
    };
    let fresh = format!("{REFERENCE_BEGIN}\n{}{REFERENCE_END}", reference_markdown());
    let current = &doc[a..b + REFERENCE_END.len()];
    if current != fresh {
        if std::env::var_os("STITCH_UPDATE_DOCS").is_some() {
            let updated = doc.replacen(current, &fresh, 1);
            std::fs::write(&path, updated).expect("write docs/scripting.md");
        } else {
            panic!(
                "docs/scripting.md's reference is stale; rerun with STITCH_UPDATE_DOCS=1 to \
                 regenerate it"
            );
        }
    }
    // Every registered function is in it.
    for (name, _) in stitch_engine::API {
        assert!(fresh.contains(&format!("| `{name}` |")), "{name}");
    }
}

#[test]
fn conditions_and_constructs_are_checked_where_the_script_builds_them() {
    let steps = "insert(), sweep(), extract(), cinch(), handover()";
    let throw = |pre: &str| {
        format!(
            "let t = suture(wound()[0], [{pre}, {steps}]);\nmission(#{{ name: \"x\", throws: [t] }})"
        )
    };
    let e = error_of(&throw("repeat(#{ max: 9 }, [estimate_needle()])"));
    assert!(
        e.contains("repeat: max 9 is out of range; expected 1 to 5 (the engine's hard cap"),
        "{e}"
    );
    let e = error_of(&throw("when(true, [estimate_needle()])"));
    assert!(
        e.contains(
            "when: expected a condition, found a boolean; a script's true or false is fixed"
        ),
        "{e}"
    );
    let e = error_of(&throw("when(needle_confidence(), [estimate_needle()])"));
    assert!(e.contains("compare it with a bound"), "{e}");
    let e = error_of(&throw(
        "when(needle_confidence() < mm(3), [estimate_needle()])",
    ));
    assert!(
        e.contains(
            "needle_confidence() < 3 mm: needle_confidence() must be compared with a number"
        ),
        "{e}"
    );
    let e = error_of(&throw("when(needle_age() == s(2), [estimate_needle()])"));
    assert!(
        e.contains("only whole-number quantities can be compared with =="),
        "{e}"
    );
    let e = error_of(&throw("when(thread_left() < cm(5), [estimate_needle()])"));
    assert!(
        e.contains("reads thread_left(), which needs the mission's thread length"),
        "{e}"
    );
    let nested = "when(needle_seen(), [when(needle_seen(), [when(needle_seen(), [when(needle_seen(), [estimate_needle()])])])])";
    let e = error_of(&throw(nested));
    assert!(
        e.contains("constructs nest 4 deep here; the limit is 3"),
        "{e}"
    );
    assert!(e.starts_with("plan.rhai:1:"), "{e}");
}

/// Constructs and conditions are opaque to the sandbox's size limits, so the engine bounds
/// them: a script that doubles a condition or nests big blocks in a loop stops with a clear
/// error, fast, instead of exhausting memory.
#[test]
fn hostile_scripts_cannot_grow_conditions_or_blocks_without_bound() {
    let doubling = "let c = needle_seen();\nfor i in 0..200 { c = all([c, c]); }\n\
                    mission(#{ name: \"x\", throws: [] })";
    let t0 = Instant::now();
    let e = error_of(doubling);
    assert!(
        e.contains("all: the condition has 127 terms; the limit is 64"),
        "{e}"
    );
    assert!(t0.elapsed() < Duration::from_secs(1));
    let nesting = "let a = [];\nfor i in 0..1000 { a.push(estimate_needle()); }\n\
                   let b = [];\nfor i in 0..1000 { b.push(repeat(#{ max: 5 }, a)); }\n\
                   mission(#{ name: \"x\", throws: [] })";
    let t0 = Instant::now();
    let e = error_of(nesting);
    assert!(
        e.contains(
            "repeat: unrolls to 5000 operations (loops at their bound); a throw's limit is 256"
        ),
        "{e}"
    );
    assert!(t0.elapsed() < Duration::from_secs(1));
}

/// Data that grows by doubling or nesting is stopped by the sandbox's size limits, fast. Rhai
/// checks the whole of each value stored (nested arrays and maps included), so one map can
/// hold at most 64 values of 1,024 elements each, and storing that map anywhere is refused:
/// about 65,000 elements at most, a few MB.
#[test]
fn doubling_strings_and_nesting_arrays_and_maps_are_stopped_within_a_second() {
    for (what, script) in [
        ("string", "let s = \"x\";\nloop { s += s; }"),
        (
            "nested arrays",
            "let a = [];\nfor i in 0..1000 { a.push(i); }\nlet b = [];\nfor i in 0..1000 { b.push(a); }",
        ),
        (
            "a map of arrays",
            "let a = [];\nfor i in 0..1000 { a.push(i); }\nlet m = #{};\nfor i in 0..60 { m[`k${i}`] = a; }\n\
             let m2 = #{};\nfor i in 0..60 { m2[`k${i}`] = m; }",
        ),
        (
            "closures capturing arrays",
            "let a = [];\nfor i in 0..1000 { a.push(i); }\nlet fs = [];\nfor i in 0..1000 { fs.push(|| a); }\nlet all = [];\nfor f in fs { all.push(f.call()); }",
        ),
    ] {
        let t0 = Instant::now();
        let e = error_of(script);
        assert!(
            t0.elapsed() < Duration::from_secs(1),
            "{what}: took {:?}",
            t0.elapsed()
        );
        assert!(
            e.contains("stopped by the sandbox") || e.contains("too large"),
            "{what}: {e}"
        );
    }
}

/// A plan with parameters: the throw count, an insertion angle in degrees, whether to sweep
/// and the mission's name.
const PARAMS_PLAN: &str = "fn one(point) {\n\
    let steps = [insert(#{ rotation: deg(param(\"rotation_deg\", 45.0)) })];\n\
    if param(\"sweep\", true) { steps.push(sweep()); }\n\
    steps.push(extract()); steps.push(handover());\n\
    suture(point, steps)\n\
}\n\
let throws = [];\n\
for i in 0..param(\"throws\", 3) { throws.push(one(wound()[i])); }\n\
mission(#{ name: param(\"label\", \"P\"), throws: throws })";

#[test]
fn params_take_their_defaults_or_the_values_given() {
    use stitch_engine::ParamValue as V;
    let loaded = load_plan_str(&loader(), "p.rhai", PARAMS_PLAN).expect("valid");
    assert_eq!(loaded.plan.throws.len(), 3);
    assert_eq!(loaded.plan.name, "P");
    assert_eq!(loaded.plan.throws[0].steps().count(), 4);
    assert!(
        loaded
            .params
            .values()
            .all(|p| !p.given && p.value == p.default)
    );
    assert_eq!(
        loaded.plan.params.keys().collect::<Vec<_>>(),
        ["label", "rotation_deg", "sweep", "throws"]
    );
    assert!(loaded.unused_params.is_empty());

    // Given as a command line gives them (text), read as each default's type.
    let given = [
        ("throws", "5"),
        ("rotation_deg", "30"),
        ("sweep", "false"),
        ("label", "Q"),
        ("nobody", "1"),
    ]
    .map(|(k, v)| (k.to_string(), V::Text(v.into())))
    .into_iter()
    .collect();
    let loaded = load_plan_str(&loader().with_params(given), "p.rhai", PARAMS_PLAN).expect("valid");
    assert_eq!(loaded.plan.throws.len(), 5);
    assert_eq!(loaded.plan.name, "Q");
    let steps: Vec<_> = loaded.plan.throws[4].steps().map(|(_, s)| s).collect();
    assert_eq!(steps.len(), 3, "no sweep");
    match &steps[0].kind {
        StepKind::Insert(i) => assert!((i.rotation_rad - 30f64.to_radians()).abs() < 1e-12),
        other => panic!("{other:?}"),
    }
    assert_eq!(loaded.plan.params["rotation_deg"], V::Float(30.0));
    assert_eq!(loaded.plan.params["throws"], V::Int(5));
    assert!(loaded.params["sweep"].given);
    assert_eq!(loaded.params["sweep"].default, V::Bool(true));
    // A value nobody asked for is reported, for the caller to refuse.
    assert_eq!(loaded.unused_params, ["nobody"]);

    // The same loader evaluates again with the same values: the same plan.
    let l = loader().with_params([("throws".to_string(), V::Int(2))].into_iter().collect());
    let a = load_plan_str(&l, "p.rhai", PARAMS_PLAN).expect("valid");
    let b = load_plan_str(&l, "p.rhai", PARAMS_PLAN).expect("valid");
    assert_eq!(a, b);
    assert_eq!(a.plan.throws.len(), 2);
}

#[test]
fn a_param_of_the_wrong_type_is_an_error_at_its_call() {
    use stitch_engine::ParamValue as V;
    let bad = |name: &str, v: V| {
        let l = loader().with_params([(name.to_string(), v)].into_iter().collect());
        let e = load_plan_str(&l, "p.rhai", PARAMS_PLAN).expect_err("refused");
        let text = e.to_string();
        assert_eq!(text.lines().count(), 1, "{text}");
        text
    };
    let e = bad("throws", V::Text("2.5".into()));
    assert!(e.starts_with("p.rhai:8:"), "{e}");
    assert!(e.contains("\"throws\"") && e.contains("an integer"), "{e}");
    let e = bad("sweep", V::Text("yes".into()));
    assert!(e.contains("a boolean"), "{e}");
    let e = bad("rotation_deg", V::Text("fast".into()));
    assert!(e.starts_with("p.rhai:2:") && e.contains("a number"), "{e}");
    let e = bad("label", V::Int(3));
    assert!(e.contains("a string"), "{e}");

    // A default that is not a plain value says what param takes.
    let e = error_of("let a = param(\"standoff\", mm(12));\nmission(#{ name: \"x\", throws: [] })");
    assert!(e.contains("param(\"name\", default)"), "{e}");
    // Two defaults for one name, and a name that is not one.
    let e = error_of(
        "let a = param(\"n\", 1);\nlet b = param(\"n\", 2);\nmission(#{ name: \"x\", throws: [] })",
    );
    assert!(
        e.starts_with("plan.rhai:2:") && e.contains("declared before"),
        "{e}"
    );
    let e = error_of("let a = param(\"a.b\", 1);\nmission(#{ name: \"x\", throws: [] })");
    assert!(e.contains("ASCII letters"), "{e}");
}
