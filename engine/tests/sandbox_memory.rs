//! Hostile scripts and memory: each script that tries to exhaust memory (doubling strings,
//! nested arrays, maps of arrays, closures capturing arrays, deep recursion, string building)
//! is stopped by the sandbox with a clear error, and the resident memory it added while
//! running stays under [`BOUND_BYTES`]: the peak (`VmHWM`, reset before each script) less
//! what was resident before. This file holds one test, so nothing else runs beside it.

use stitch_engine::{PlanLoader, ScriptLimits, load_plan_str};
use stitch_robot::{Wound, WoundSpec};

/// The most resident memory a hostile script may add to the process while it runs, bytes:
/// the sandbox's size limits (4,096-byte strings; 1,024-element arrays; 64-entry maps, each
/// value checked whole) allow about 65,000 elements in one value, a few MB.
const BOUND_BYTES: u64 = 8 << 20;

/// A `/proc/self/status` field, bytes (Linux; the kernel reports kB).
fn status_bytes(field: &str) -> u64 {
    let status = std::fs::read_to_string("/proc/self/status").expect("/proc/self/status");
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))
        .and_then(|v| v.split_whitespace().next()?.parse::<u64>().ok())
        .expect("the field")
        * 1024
}

/// Reset the process's peak resident memory to what it uses now (Linux's `clear_refs` 5).
fn reset_peak() {
    std::fs::write("/proc/self/clear_refs", "5").expect("/proc/self/clear_refs");
}

#[test]
fn hostile_scripts_are_stopped_under_the_memory_bound() {
    let wound = Wound::linear(&WoundSpec::default()).expect("wound");
    let loader = PlanLoader::new(&wound, ScriptLimits::default());
    let mut report = Vec::new();
    for (what, script) in [
        ("doubling a string", "let s = \"x\";\nloop { s += s; }"),
        (
            "building a string",
            "let s = \"\";\nfor i in 0..100000 { s += `${i},`; }",
        ),
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
            "let a = [];\nfor i in 0..1000 { a.push(i); }\nlet fs = [];\nfor i in 0..1000 { fs.push(|| a); }\n\
             let all = [];\nfor f in fs { all.push(f.call()); }",
        ),
        ("deep recursion", "fn f(n) { f(n + 1) }\nf(0)"),
        (
            "recursion carrying arrays",
            "fn f(a) { let b = a; b.push(1); f(b) }\nlet a = [];\nfor i in 0..1000 { a.push(i); }\nf(a)",
        ),
    ] {
        reset_peak();
        let before = status_bytes("VmRSS");
        let e = load_plan_str(&loader, "hostile.rhai", script)
            .expect_err("stopped")
            .to_string();
        let reached = status_bytes("VmHWM").saturating_sub(before);
        assert!(
            e.contains("stopped by the sandbox")
                || e.contains("too large")
                || e.contains("too deep"),
            "{what}: {e}"
        );
        assert!(
            reached < BOUND_BYTES,
            "{what}: resident memory grew by {reached} bytes (bound {BOUND_BYTES}): {e}"
        );
        report.push(format!("{what}: {:.2} MB", reached as f64 / 1e6));
    }
    eprintln!("resident memory added: {}", report.join("; "));
}
