//! The `stitch` binary as a user runs it.

mod support;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn stitch(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("the stitch binary runs")
}

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

use support::tmp;

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

#[test]
fn check_prints_the_plan_tree_and_exits_zero() {
    let out = stitch(&["check", "scripts/stitch.rhai"]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let s = text(&out.stdout);
    assert!(s.contains("mission \"STITCH\""), "{s}");
    assert!(s.contains("throw 6"), "{s}");
    assert!(s.contains("extract         retries 5 (cap 5)"), "{s}");
    assert!(s.contains("valid: 6 throws, nothing ran"), "{s}");
}

#[test]
fn the_same_seed_writes_the_same_journal_and_another_seed_does_not() {
    let (a, b, c) = (tmp("a.jsonl"), tmp("b.jsonl"), tmp("c.jsonl"));
    for (seed, path) in [("1", &a), ("1", &b), ("2", &c)] {
        let out = stitch(&[
            "run",
            "scripts/stitch.rhai",
            "--seed",
            seed,
            "--journal",
            path.to_str().expect("utf-8 path"),
        ]);
        assert!(
            matches!(out.status.code(), Some(0 | 4)),
            "{}",
            text(&out.stderr)
        );
    }
    let (a, b, c) = (
        std::fs::read(a).expect("a"),
        std::fs::read(b).expect("b"),
        std::fs::read(c).expect("c"),
    );
    assert!(!a.is_empty());
    assert_eq!(a, b, "seed 1 twice");
    assert_ne!(a, c, "seed 1 and seed 2");
}

#[test]
fn run_prints_a_timeline_and_the_outcome() {
    let out = stitch(&["run", "scripts/stitch_human.rhai", "--seed", "3"]);
    let s = text(&out.stdout);
    assert!(
        s.starts_with("STITCH + Human on the mock dVRK, seed 3"),
        "{s}"
    );
    assert!(s.contains("throw 1 ("), "{s}");
    assert!(s.contains("outcome: "), "{s}");
    let code = out.status.code();
    if s.contains("outcome: completed") {
        assert_eq!(code, Some(0));
    } else {
        assert_eq!(code, Some(4), "{s}");
    }
}

fn check_error(source: &str) -> (Option<i32>, String, String) {
    let path = tmp(&format!("bad-{}.rhai", source.len()));
    std::fs::write(&path, source).expect("write");
    let p = path.to_str().expect("utf-8");
    let out = stitch(&["run", p]);
    let err = text(&out.stderr);
    (out.status.code(), err, p.to_string())
}

#[test]
fn invalid_plans_get_one_line_with_their_position_and_exit_three_without_running() {
    let good = "insert(), sweep(), extract(), cinch(), handover()";
    for (source, at, says) in [
        ("let t = suture(wound()[0], [insert(),, sweep()]);".to_string(), ":1:", "syntax error"),
        (format!("let t = suture(wound()[0], [\n  {good},\n  stitch_it()]);"), ":3:3:", "unknown function or primitive `stitch_it`"),
        (format!("let t = suture(wound()[0], [\n  insert(#{{ rotation: mm(45) }}), {good}]);"), ":2:3:", "must be an angle"),
        (
            "let t = suture(wound()[0], [insert(), sweep(),\n   extract(#{ retries: 9 }), handover()]);\nmission(#{ name: \"x\", throws: [t] })".to_string(),
            ":2:4:",
            "retries 9 exceeds the engine's hard cap of 5",
        ),
        (
            "let t = suture(wound()[0], [insert(), sweep(),\n   handover(), extract()]);\nmission(#{ name: \"x\", throws: [t] })".to_string(),
            ":2:4:",
            "handover needs the needle in the left jaw",
        ),
    ] {
        let (code, err, file) = check_error(&source);
        assert_eq!(code, Some(3), "{err}");
        assert_eq!(err.lines().count(), 1, "one line: {err}");
        assert!(err.starts_with(&format!("{file}{at}")), "expected {file}{at}…: {err}");
        assert!(err.contains(says), "{err}");
    }
}

#[test]
fn a_replayed_schedule_reproduces_its_outcome() {
    let schedule = tmp("schedule.json");
    std::fs::write(
        &schedule,
        r#"{"outcomes": ["ok", "ok", "thread"], "supervisor": [], "interventions": []}"#,
    )
    .expect("write");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--robot",
        "scripted",
        "--outcomes",
        schedule.to_str().expect("utf-8"),
        "--json",
    ]);
    assert_eq!(out.status.code(), Some(4));
    let v: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json outcome");
    assert_eq!(v["result"], "failed");
    assert_eq!(v["class"], "T");
    assert_eq!(v["primitive"], "extract");
}

#[test]
fn an_e_stop_in_a_schedule_exits_five() {
    let schedule = tmp("estop.json");
    std::fs::write(
        &schedule,
        r#"{"supervisor": [{"at": 2, "command": "e-stop"}]}"#,
    )
    .expect("write");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--robot",
        "scripted",
        "--outcomes",
        schedule.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(5), "{}", text(&out.stdout));
    assert!(text(&out.stdout).contains("arms held"));
}

#[test]
fn a_missing_plan_file_exits_one_with_the_reason() {
    let out = stitch(&["check", "scripts/no_such_plan.rhai"]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("cannot read the plan"),
        "{}",
        text(&out.stderr)
    );
}

#[test]
fn explore_checks_every_property_of_the_stitch_plan() {
    let out = stitch(&["check", "scripts/stitch.rhai", "--explore"]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let s = text(&out.stdout);
    assert!(s.starts_with("explored scripts/stitch.rhai: "), "{s}");
    assert!(s.contains("ok   no motion after abort or e-stop"), "{s}");
    assert!(
        s.contains("ok   every path ends in completed, failed or aborted"),
        "{s}"
    );
    assert!(!s.contains("FAIL"), "{s}");
}

#[test]
fn explore_rejects_an_unsafe_order_with_the_path_and_a_replayable_schedule() {
    let cx = tmp("cx.json");
    let out = stitch(&[
        "check",
        "engine/tests/counterexamples/no_handover.rhai",
        "--explore",
        "--counterexample",
        cx.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(3));
    let s = text(&out.stdout);
    assert!(
        s.contains("FAIL never insert unless the inserting jaw holds the needle"),
        "{s}"
    );
    assert!(s.contains("5. in inserting(t2 s1 r0): ok"), "{s}");
    assert!(text(&out.stderr).contains("throw 2: insert needs the needle in the right"));
    let replay = stitch(&[
        "run",
        "engine/tests/counterexamples/no_handover.rhai",
        "--robot",
        "scripted",
        "--outcomes",
        cx.to_str().expect("utf-8"),
        "--skip-validation",
    ]);
    assert_eq!(replay.status.code(), Some(5), "{}", text(&replay.stdout));
    let r = text(&replay.stdout);
    assert!(r.contains("replaying"), "{r}");
    assert!(r.contains("aborted (Abort) before throw 2 step 2"), "{r}");
}

#[test]
fn the_mock_configuration_documented_in_docs_parses_and_runs() {
    let doc = std::fs::read_to_string(root().join("docs/mock-dvrk.md")).expect("docs/mock-dvrk.md");
    let start = doc.find("```toml\n").expect("a toml block") + "```toml\n".len();
    let end = start + doc[start..].find("```").expect("its end");
    let config = tmp("mock.toml");
    std::fs::write(&config, &doc[start..end]).expect("write");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--mock-config",
        config.to_str().expect("utf-8"),
    ]);
    assert!(
        matches!(out.status.code(), Some(0 | 4)),
        "{}",
        text(&out.stderr)
    );
    // The same seed with the defaults gives the same run: the documented values are the defaults.
    let defaults = stitch(&["run", "scripts/stitch.rhai"]);
    assert_eq!(text(&out.stdout), text(&defaults.stdout));
}

#[test]
fn a_bad_mock_configuration_says_where() {
    let config = tmp("bad.toml");
    for (toml, says) in [
        ("[scene.thread]\nfriction = -1.5\n", "thread.friction"),
        ("[scene]\nnot_a_key = 1\n", "not_a_key"),
    ] {
        std::fs::write(&config, toml).expect("write");
        let path = config.to_str().expect("utf-8");
        let out = stitch(&["run", "scripts/stitch.rhai", "--mock-config", path]);
        assert_eq!(out.status.code(), Some(1));
        assert!(text(&out.stderr).contains(says), "{}", text(&out.stderr));
    }
}

#[test]
fn the_mock_is_the_default_and_prints_hole_errors_and_thread_left() {
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--seed",
        "3",
        "--perception",
        "perfect",
    ]);
    let s = text(&out.stdout);
    assert!(s.starts_with("STITCH on the mock dVRK, seed 3"), "{s}");
    assert!(
        s.contains("entry error") && s.contains("exit error") && s.contains("thread left"),
        "{s}"
    );
}

#[test]
fn on_the_mock_the_supervisor_recovers_and_the_failed_step_runs_again() {
    let out = stitch(&["run", "scripts/stitch_human.rhai", "--seed", "6"]);
    let s = text(&out.stdout);
    assert!(
        s.contains("human intervention: recovered; the step runs again"),
        "{s}"
    );
    assert!(
        s.contains("interventions 2 of 2") || s.contains("interventions 1 of 2"),
        "{s}"
    );
}

#[test]
fn commands_at_simulated_times_land_mid_step_and_the_timeline_prints_as_the_run_goes() {
    let commands = tmp("commands.json");
    std::fs::write(
        &commands,
        r#"[{"at_s": 5.0, "command": "pause"}, {"at_s": 8.0, "command": "resume"},
            {"at_s": 30.0, "command": "abort"}]"#,
    )
    .expect("commands");
    let journal = tmp("commands.jsonl");
    let started = std::time::Instant::now();
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--commands",
        commands.to_str().expect("utf-8"),
        "--pace",
        "100",
        "--journal",
        journal.to_str().expect("utf-8"),
    ]);
    // 30 simulated seconds at 100 times the wall clock's speed: at least 0.3 s.
    assert!(started.elapsed() >= std::time::Duration::from_millis(300));
    assert_eq!(out.status.code(), Some(5), "{}", text(&out.stderr));
    let (stdout, stderr) = (text(&out.stdout), text(&out.stderr));
    assert!(stdout.contains("INTERRUPTED by the supervisor"), "{stdout}");
    // Each step's line, printed on standard error as it ended.
    assert!(stderr.contains("throw 1     0.0 s  insert"), "{stderr}");
    assert!(stderr.contains("INTERRUPTED"), "{stderr}");
    let journal = std::fs::read_to_string(&journal).expect("journal");
    let pause = journal
        .lines()
        .find(|l| l.contains(r#""command":"pause""#))
        .expect("the pause is journaled");
    assert!(
        pause.contains(r#""t_s":5.0"#) && pause.contains(r#""during":{"throw":0,"step":0"#),
        "{pause}"
    );
    assert!(
        journal.contains(r#""state":"paused(t1 s1 r0 mid-step)""#),
        "{journal}"
    );
}

#[test]
fn a_recorded_run_with_commands_replays_identically() {
    let commands = tmp("replay-commands.json");
    std::fs::write(
        &commands,
        r#"[{"at_s": 20.0, "command": "take-over"}, {"at_s": 26.0, "command": "hand-back"},
            {"at_s": 90.0, "command": "e-stop"}]"#,
    )
    .expect("commands");
    let mcap = tmp("replay-commands.mcap");
    let out = stitch(&[
        "run",
        "scripts/stitch_human.rhai",
        "--commands",
        commands.to_str().expect("utf-8"),
        "--journal",
        mcap.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(5), "{}", text(&out.stderr));
    let out = stitch(&["replay", mcap.to_str().expect("utf-8")]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}{}",
        text(&out.stdout),
        text(&out.stderr)
    );
    assert!(
        text(&out.stdout).starts_with("identical"),
        "{}",
        text(&out.stdout)
    );
}

#[test]
fn bad_commands_and_paces_are_refused_with_the_reason() {
    let bad = tmp("bad-commands.json");
    std::fs::write(&bad, "[{\"at_s\": 1.0,\n \"command\": \"halt\"}]").expect("file");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--commands",
        bad.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(1));
    let err = text(&out.stderr);
    assert!(
        err.contains("bad-commands.json:2:") && err.contains("halt"),
        "{err}"
    );
    let negative = tmp("negative-commands.json");
    std::fs::write(&negative, r#"[{"at_s": -1.0, "command": "pause"}]"#).expect("file");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--commands",
        negative.to_str().expect("utf-8"),
    ]);
    assert!(
        text(&out.stderr).contains("at_s must be a time ≥ 0 s"),
        "{}",
        text(&out.stderr)
    );
    let out = stitch(&["run", "scripts/stitch.rhai", "--pace", "0"]);
    assert!(
        text(&out.stderr).contains("--pace 0: expected a positive number"),
        "{}",
        text(&out.stderr)
    );
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--robot",
        "ros2",
        "--pace",
        "1",
    ]);
    assert!(
        text(&out.stderr).contains("over ROS 2 the clock is the wall's"),
        "{}",
        text(&out.stderr)
    );
}

#[test]
fn the_supervision_benchmark_measures_pauses_during_motions() {
    let out = stitch(&["bench", "supervision", "--commands", "8", "--json"]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let rows: serde_json::Value = serde_json::from_slice(&out.stdout).expect("json");
    let mock = &rows[0];
    assert_eq!(mock["sent"], 8);
    assert!(
        mock["during_motion"].as_u64().is_some_and(|n| n > 0),
        "{mock}"
    );
    // A bound that holds on any machine; the benchmark's own numbers go in the docs.
    assert!(
        mock["p99_ms"]
            .as_f64()
            .is_some_and(|ms| ms > 0.0 && ms < 1000.0),
        "{mock}"
    );
}

#[test]
fn plan_parameters_are_shown_checked_and_refused_with_the_reason() {
    let out = stitch(&[
        "check",
        "scripts/stitch_thread.rhai",
        "--param",
        "max_sweeps=3",
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let s = text(&out.stdout);
    assert!(
        s.contains("param max_sweeps = 3  (given; default 2)"),
        "{s}"
    );
    assert!(s.contains("param clearance_mm = 4.0  (default)"), "{s}");
    assert!(
        s.contains("repeat at most 3 times"),
        "the value reached the plan: {s}"
    );
    for (args, code, why) in [
        (
            vec![
                "check",
                "scripts/stitch_thread.rhai",
                "--param",
                "max_sweep=3",
            ],
            1,
            "--param max_sweep: scripts/stitch_thread.rhai declares no such parameter (its parameters: clearance_mm, max_sweeps)",
        ),
        (
            vec!["run", "scripts/stitch.rhai", "--param", "max_sweeps=3"],
            1,
            "declares no such parameter (it has no param(\"name\", default) calls)",
        ),
        (
            vec![
                "run",
                "scripts/stitch_thread.rhai",
                "--param",
                "max_sweeps=2.5",
            ],
            3,
            "scripts/stitch_thread.rhai:26:",
        ),
        (
            vec![
                "check",
                "scripts/stitch_thread.rhai",
                "--param",
                "max_sweeps=3",
                "--param",
                "max_sweeps=4",
            ],
            1,
            "--param max_sweeps is given twice",
        ),
        (
            vec![
                "check",
                "scripts/stitch_thread.rhai",
                "--param",
                "max_sweeps",
            ],
            2,
            "expected NAME=VALUE",
        ),
    ] {
        let out = stitch(&args);
        let said = text(&out.stderr);
        assert_eq!(out.status.code(), Some(code), "{args:?}: {said}");
        assert!(said.contains(why), "{args:?}: expected {why:?} in {said}");
    }
}
