//! The flight recorder: `stitch run --journal FILE.mcap` streams the run to an MCAP file; the
//! same seed gives the same bytes; the export is the JSON Lines journal; a file cut short
//! (as a kill leaves it) is read up to its last closed chunk and recovered whole; readers
//! this project did not write (Python `mcap` + `mcap-ros2-support`, `rosbags`) decode every
//! message on every channel.

mod support;

use std::path::{Path, PathBuf};
use std::process::Command;
use support::{python, root, tmp};

fn stitch(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("stitch runs")
}

fn record(name: &str, extra: &[&str]) -> PathBuf {
    record_plan(name, "scripts/stitch_human.rhai", extra)
}

fn record_plan(name: &str, plan: &str, extra: &[&str]) -> PathBuf {
    let path = tmp(name);
    let out = stitch(
        &[
            &["run", plan, "--journal"][..],
            &[path.to_str().expect("utf-8")],
            extra,
        ]
        .concat(),
    );
    assert!(
        matches!(out.status.code(), Some(0 | 4)),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    path
}

fn export(path: &Path) -> String {
    let out = stitch(&[
        "journal",
        "export",
        path.to_str().expect("utf-8"),
        "--jsonl",
    ]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).expect("utf-8")
}

/// Foxglove's and Lichtblick's own readers (`@mcap/core`'s indexed reader, every message
/// decoded by `@foxglove/rosmsg2-serialization`; tests/node/read_mcap.js) over `files`: one
/// JSON line per file, after asserting each opened and agreed with its summary.
fn foxglove_reads(files: &[&Path]) -> Vec<serde_json::Value> {
    let setup = Command::new("bash")
        .arg(root().join("tests/node/setup.sh"))
        .output()
        .expect("bash runs tests/node/setup.sh");
    assert!(
        setup.status.success(),
        "tests/node/setup.sh failed (needs node and npm, and the npm registry): {}",
        String::from_utf8_lossy(&setup.stderr)
    );
    let modules = String::from_utf8_lossy(&setup.stdout).trim().to_string();
    let out = Command::new("node")
        .arg(root().join("tests/node/read_mcap.js"))
        .args(files)
        .env("NODE_PATH", modules)
        .output()
        .expect("node runs");
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{said}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    let lines: Vec<serde_json::Value> = said
        .lines()
        .map(|l| serde_json::from_str(l).expect("a JSON line"))
        .collect();
    assert_eq!(lines.len(), files.len(), "{said}");
    lines
}

/// `stitch journal recover FROM --out TO`, which must succeed.
fn recover(from: &Path, to: &Path) {
    let out = stitch(&[
        "journal",
        "recover",
        from.to_str().expect("utf-8"),
        "--out",
        to.to_str().expect("utf-8"),
    ]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn the_same_seed_gives_the_same_file_byte_for_byte_and_another_seed_another() {
    let a = std::fs::read(record("seed1-a.mcap", &["--seed", "1"])).expect("a");
    let b = std::fs::read(record("seed1-b.mcap", &["--seed", "1"])).expect("b");
    let c = std::fs::read(record("seed2.mcap", &["--seed", "2"])).expect("c");
    assert!(
        a == b,
        "seed 1 twice: {} and {} bytes differ",
        a.len(),
        b.len()
    );
    assert!(a != c, "seeds 1 and 2 gave the same file");
}

#[test]
fn the_export_is_the_json_lines_journal_on_the_mock_and_the_scripted_robot() {
    for (name, extra) in [
        ("mock", vec!["--seed", "3"]),
        ("scripted", vec!["--seed", "3", "--robot", "scripted"]),
    ] {
        let mcap = record(&format!("export-{name}.mcap"), &extra);
        let jsonl = record(&format!("export-{name}.jsonl"), &extra);
        let expected = std::fs::read_to_string(jsonl).expect("jsonl");
        assert!(expected.lines().count() > 5, "{expected}");
        assert_eq!(export(&mcap), expected, "{name}");
    }
}

#[test]
fn a_file_cut_short_is_read_to_its_last_closed_chunk_and_recovered_whole() {
    let full = record("whole.mcap", &["--seed", "5"]);
    let bytes = std::fs::read(&full).expect("file");
    let all = export(&full);
    let lines: Vec<&str> = all.lines().collect();
    // Cut where a kill could: a third and half way through the file, mid-record.
    for fraction in [3, 2] {
        let cut = tmp(&format!("cut-{fraction}.mcap"));
        std::fs::write(&cut, &bytes[..bytes.len() / fraction + 7]).expect("cut");
        let got = export(&cut);
        let n = got.lines().count();
        assert!(n > 0 && n < lines.len(), "{n} of {} records", lines.len());
        assert_eq!(got, lines[..n].join("\n") + "\n", "a prefix of the run");
        let fixed = tmp(&format!("cut-{fraction}.recovered.mcap"));
        recover(&cut, &fixed);
        assert_eq!(export(&fixed), got, "the recovered file holds the same");
        let check = Command::new(python())
            .arg(root().join("tests/python/read_mcap.py"))
            .arg(&fixed)
            .output()
            .expect("python runs");
        let said = String::from_utf8_lossy(&check.stdout);
        assert!(check.status.success(), "{said}");
        assert!(
            said.contains("plan.rhai") && said.contains("plan_sha256"),
            "metadata and attachments recovered: {said}"
        );
        // Foxglove opens the recovered file and reads the messages the Python readers do.
        let py: serde_json::Value =
            serde_json::from_str(said.lines().next().expect("a line")).expect("JSON");
        let fox = foxglove_reads(&[&fixed]);
        assert_eq!(fox[0]["foxglove"], py["mcap"], "{fox:?} against {py}");
    }
}

#[test]
fn readers_this_project_did_not_write_decode_every_message() {
    let pipeline = [
        "--seed",
        "1",
        "--perception",
        "pipeline",
        "--record-frames",
        "1",
    ];
    let files = [
        record("py-mock.mcap", &["--seed", "1"]),
        record("py-scripted.mcap", &["--seed", "1", "--robot", "scripted"]),
        record("py-pipeline.mcap", &pipeline),
        record_plan("py-thread.mcap", "scripts/stitch_thread.rhai", &pipeline),
    ];
    let out = Command::new(python())
        .arg(root().join("tests/python/read_mcap.py"))
        .args(&files)
        .output()
        .expect("python runs");
    let said = String::from_utf8_lossy(&out.stdout);
    assert!(
        out.status.success(),
        "{said}\n{}",
        String::from_utf8_lossy(&out.stderr)
    );
    assert_eq!(said.matches(r#""agree": true"#).count(), 4, "{said}");
    // Foxglove's own reader opens each file (a chunk without message indexes, which it
    // refuses, is never written) and decodes the same messages.
    let fox = foxglove_reads(&files.iter().map(PathBuf::as_path).collect::<Vec<_>>());
    for (line, f) in said.lines().zip(&fox) {
        let py: serde_json::Value = serde_json::from_str(line).expect("JSON");
        assert_eq!(f["foxglove"], py["mcap"], "{f} against {py}");
    }
    assert!(said.contains("/stitch/transitions"), "{said}");
    let lines: Vec<&str> = said.lines().collect();
    // What the arms were told and measured, what the estimator said (and the truth beside
    // it), on the mock; camera frames where the estimator looks at images.
    for topic in [
        "/PSM1/move_cp",
        "/PSM2/move_cp",
        "/PSM1/measured_cp",
        "/PSM1/jaw/move_jp",
        "/stitch/needle/estimate",
        "/stitch/needle/truth",
    ] {
        assert!(
            lines[0].contains(&format!("\"{topic}\"")),
            "{topic}: {}",
            lines[0]
        );
        assert!(
            !lines[1].contains(topic),
            "the scripted robot has no arms: {}",
            lines[1]
        );
    }
    for line in &lines {
        assert!(
            line.contains("\"/stitch/steps\""),
            "typed step ends: {line}"
        );
    }
    for topic in FRAME_TOPICS {
        assert!(
            !lines[0].contains(topic),
            "no frames without images: {}",
            lines[0]
        );
        assert!(lines[2].contains(topic), "{topic}: {}", lines[2]);
    }
    // The thread-aware plan's traces, in 3D and on the left image; a plan that never looks
    // at the thread records none.
    for topic in THREAD_TOPICS {
        assert!(
            lines[3].contains(&format!("\"{topic}\"")),
            "{topic}: {}",
            lines[3]
        );
        assert!(!lines[2].contains(topic), "{topic}: {}", lines[2]);
    }
    // Every topic the documented Foxglove layout shows is in a pipeline run's file.
    let layout: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(root().join("docs/foxglove/stitch-layout.json")).expect("layout"),
    )
    .expect("JSON");
    let mut shown = Vec::new();
    for (_, panel) in layout["configById"].as_object().expect("panels") {
        if let Some(topics) = panel["topics"].as_object() {
            shown.extend(topics.keys().cloned());
        }
        if let Some(t) = panel["imageMode"]["imageTopic"].as_str() {
            shown.push(t.to_string());
        }
        if let Some(a) = panel["imageMode"]["annotations"].as_object() {
            shown.extend(a.keys().cloned());
        }
        let mut paths: Vec<&str> = panel["paths"]
            .as_array()
            .map(|p| p.iter().filter_map(|v| v["value"].as_str()).collect())
            .unwrap_or_default();
        paths.extend(panel["topicPath"].as_str());
        for p in paths {
            shown.push(p.split('.').next().expect("a topic").to_string());
        }
    }
    assert!(shown.len() >= 10, "{shown:?}");
    for topic in &shown {
        let quoted = format!("\"{topic}\"");
        let in_file = lines[2].contains(&quoted) || lines[3].contains(&quoted);
        // setpoint_cp is sampled on a robot only; the mock records what flows through.
        assert!(
            in_file || topic.ends_with("/setpoint_cp"),
            "{topic} not recorded: {}",
            lines[2]
        );
    }
    // The recorder's taps change nothing: the pipeline run's journal is the one without it.
    let jsonl = record("py-pipeline.jsonl", &pipeline[..4]);
    assert_eq!(
        export(&files[2]),
        std::fs::read_to_string(jsonl).expect("jsonl")
    );
}

const THREAD_TOPICS: [&str; 3] = [
    "/stitch/thread",
    "/stitch/thread/path",
    "/stitch/camera/left/thread_annotations",
];

const FRAME_TOPICS: [&str; 2] = [
    "/stitch/camera/left/image/compressed",
    "/stitch/camera/right/image/compressed",
];

#[cfg(unix)]
#[test]
fn a_journal_that_cannot_be_written_stops_the_run_before_anything_moves() {
    let path = tmp("full.mcap");
    let _ = std::fs::remove_file(&path);
    std::os::unix::fs::symlink("/dev/full", &path).expect("a link to /dev/full");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--journal",
        path.to_str().expect("utf-8"),
    ]);
    let said = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{said}");
    assert!(said.contains("cannot record the journal to"), "{said}");
    assert!(said.contains("No space left on device"), "{said}");
    assert!(
        out.stdout.is_empty(),
        "nothing ran: {}",
        String::from_utf8_lossy(&out.stdout)
    );
}

/// A disk that fills mid-run (here a file size limit): the recorder says so at once, the run
/// goes on and prints its timeline, the exit says the journal failed, and the file is
/// readable up to where it stopped.
#[cfg(target_os = "linux")]
#[test]
fn a_recording_that_fails_mid_run_says_so_and_the_run_goes_on() {
    let path = tmp("too-big.mcap");
    let _ = std::fs::remove_file(&path);
    let out = Command::new("bash")
        .arg("-c")
        .arg(format!(
            "trap '' XFSZ; ulimit -f 50; exec {} run scripts/stitch_human.rhai --seed 1 \
             --journal {}",
            env!("CARGO_BIN_EXE_stitch"),
            path.display()
        ))
        .current_dir(root())
        .output()
        .expect("bash runs");
    let (said, printed) = (
        String::from_utf8_lossy(&out.stderr),
        String::from_utf8_lossy(&out.stdout),
    );
    assert_eq!(out.status.code(), Some(1), "{said}");
    assert!(
        said.contains("the flight recorder stopped, the run goes on unrecorded"),
        "{said}"
    );
    assert!(said.contains("cannot finish the journal"), "{said}");
    assert!(
        printed.contains("outcome: completed"),
        "the run went on: {printed}"
    );
    let got = stitch_recorder::read(&path).expect("readable");
    assert!(!got.complete && !got.records.is_empty());
}

#[test]
fn journal_show_prints_the_timeline_the_run_printed_from_the_file_alone() {
    for (name, extra) in [
        ("mock", vec!["--seed", "4"]),
        ("scripted", vec!["--seed", "4", "--robot", "scripted"]),
    ] {
        let path = tmp(&format!("show-{name}.mcap"));
        let p = path.to_str().expect("utf-8");
        let ran = stitch(
            &[
                &["run", "scripts/stitch_human.rhai", "--journal", p][..],
                &extra,
            ]
            .concat(),
        );
        let shown = stitch(&["journal", "show", p]);
        assert_eq!(
            shown.status.code(),
            Some(0),
            "{}",
            String::from_utf8_lossy(&shown.stderr)
        );
        let printed = String::from_utf8_lossy(&ran.stdout);
        assert!(printed.contains("throw 1"), "{printed}");
        assert_eq!(String::from_utf8_lossy(&shown.stdout), printed, "{name}");
        let json = stitch(&["journal", "show", p, "--json"]);
        let v: serde_json::Value = serde_json::from_slice(&json.stdout).expect("JSON");
        assert_eq!(
            v["plan"]["throws"].as_u64(),
            Some(v["throws"].as_array().expect("throws").len() as u64)
        );
        assert!(v["outcome"]["result"].is_string(), "{v}");
    }
}

#[test]
fn a_replay_of_a_mock_and_a_scripted_run_is_identical() {
    let schedule = tmp("replay-outcomes.json");
    std::fs::write(
        &schedule,
        r#"{"outcomes": ["ok", "no-progress", "ok", "thread"], "interventions": ["recovered"]}"#,
    )
    .expect("schedule");
    for (name, extra) in [
        ("mock", vec!["--seed", "6", "--wound-points", "3"]),
        ("scripted", vec!["--seed", "6", "--robot", "scripted"]),
        (
            "outcomes",
            vec![
                "--robot",
                "scripted",
                "--outcomes",
                schedule.to_str().expect("utf-8"),
            ],
        ),
    ] {
        let path = record(&format!("replay-{name}.mcap"), &extra);
        let out = stitch(&["replay", path.to_str().expect("utf-8")]);
        let said = String::from_utf8_lossy(&out.stdout);
        assert_eq!(
            out.status.code(),
            Some(0),
            "{name}: {said}{}",
            String::from_utf8_lossy(&out.stderr)
        );
        assert!(said.starts_with("identical: "), "{name}: {said}");
    }
}

#[test]
fn a_replay_points_at_the_one_recorded_value_that_was_altered() {
    let path = record("altered-source.mcap", &["--seed", "4"]);
    let altered = tmp("altered.mcap");
    let mut was = None;
    stitch_recorder::rewrite(&path, &altered, |topic, i, bytes| {
        if topic == "/PSM2/move_cp" && i == 9 {
            let mut p: stitch_dvrk::msg::PoseStamped =
                stitch_dvrk::decode(bytes, "geometry_msgs/msg/PoseStamped").expect("a pose");
            was = Some(p.pose.position.x);
            p.pose.position.x += 0.5e-3;
            *bytes = stitch_dvrk::encode(&p, "geometry_msgs/msg/PoseStamped").expect("encodes");
        }
    })
    .expect("rewritten");
    let was = was.expect("the file has a tenth PSM2 move");
    let out = stitch(&["replay", altered.to_str().expect("utf-8")]);
    let said = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(7), "{said}");
    assert!(said.contains("diverges at message"), "{said}");
    assert!(said.contains("/PSM2/move_cp #9"), "{said}");
    let lines: Vec<&str> = said.lines().collect();
    let x = |line: &str| -> f64 {
        let start = line.find("position (").expect("a position") + "position (".len();
        line[start..]
            .split(',')
            .next()
            .expect("x")
            .trim()
            .parse()
            .expect("mm")
    };
    assert!(
        (x(lines[1]) - (was + 0.5e-3) * 1e3).abs() < 1e-3,
        "recorded, altered: {said}"
    );
    assert!(
        (x(lines[2]) - was * 1e3).abs() < 1e-3,
        "replayed, as it was: {said}"
    );
    // The file it came from still replays identical.
    let out = stitch(&["replay", path.to_str().expect("utf-8")]);
    assert_eq!(
        out.status.code(),
        Some(0),
        "{}",
        String::from_utf8_lossy(&out.stdout)
    );
}

#[test]
fn another_plan_on_a_recorded_runs_outcomes_shows_its_first_different_decision() {
    // Seed 4: STITCH + Human's first insertion misses and a human recovers it.
    let path = record("what-if.mcap", &["--seed", "4"]);
    let p = path.to_str().expect("utf-8");
    let same = stitch(&["replay", p, "--plan", "scripts/stitch_human.rhai"]);
    let said = String::from_utf8_lossy(&same.stdout);
    assert_eq!(same.status.code(), Some(0), "{said}");
    assert!(
        said.contains("as recorded") && said.contains("decisions: all "),
        "{said}"
    );
    assert!(said.contains("human intervention: recovered"), "{said}");
    // STITCH alone has no intervention to ask for: it fails there, and says where.
    let other = stitch(&["replay", p, "--plan", "scripts/stitch.rhai"]);
    let said = String::from_utf8_lossy(&other.stdout);
    assert_eq!(other.status.code(), Some(7), "{said}");
    let lines: Vec<&str> = said.lines().collect();
    let at = lines
        .iter()
        .position(|l| l.starts_with("decisions: the first"))
        .expect("a difference");
    assert!(lines[at + 1].contains("intervention_requested"), "{said}");
    assert!(lines[at + 2].contains(r#""to":"failed("#), "{said}");
    assert!(said.contains("outcome: failed, class I"), "{said}");
}

/// `stitch run --robot ros2` against `stitch sim-node` in real time, killed with SIGKILL in
/// the middle of the first throw: the file, recovered, holds the run to within 250 ms of the
/// kill, every event before its last message, and `stitch journal show` prints them.
#[cfg(feature = "ros2")]
#[test]
fn a_run_over_ros2_killed_mid_throw_keeps_its_journal_to_the_last_quarter_second() {
    use std::process::Stdio;
    use std::time::{Duration, Instant, SystemTime};
    use stitch_engine::Entry;
    let d = (215 + std::process::id() % 10).to_string();
    let _node = support::SimNode::start(&d, &["--time-scale", "1"]);
    let path = tmp("killed-mid-throw.mcap");
    let _ = std::fs::remove_file(&path);
    let p = path.to_str().expect("utf-8");
    let mut child = Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args([
            "run",
            "scripts/stitch_human.rhai",
            "--robot",
            "ros2",
            "--domain-id",
            &d,
        ])
        .args(["--journal", p])
        .current_dir(root())
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(std::fs::File::create(tmp("killed-mid-throw.stderr")).expect("stderr"))
        .spawn()
        .expect("stitch run starts");
    // Mid-throw: the live file shows the first throw's third step under way.
    let deadline = Instant::now() + Duration::from_secs(90);
    loop {
        let third = stitch_recorder::read(&path).ok().is_some_and(|r| {
            r.records.iter().any(|r| {
                matches!(
                    r.entry,
                    Entry::StepStart {
                        throw: 0,
                        step: 2,
                        ..
                    }
                )
            })
        });
        if third {
            break;
        }
        assert!(
            Instant::now() < deadline,
            "the run never reached throw 1 step 3: {}",
            std::fs::read_to_string(tmp("killed-mid-throw.stderr")).unwrap_or_default()
        );
        assert!(
            child.try_wait().expect("wait").is_none(),
            "the run ended early"
        );
        std::thread::sleep(Duration::from_millis(20));
    }
    std::thread::sleep(Duration::from_millis(700));
    let killed_at = SystemTime::now();
    child.kill().expect("SIGKILL");
    let _ = child.wait();
    let unfinished = stitch_recorder::read(&path).expect("readable as it was left");
    assert!(!unfinished.complete, "a killed run's file has no summary");
    let fixed = tmp("killed-mid-throw.recovered.mcap");
    recover(&path, &fixed);
    let got = stitch_recorder::read(&fixed).expect("recovered");
    assert!(got.complete);
    let epoch_ns: u128 = got
        .metadata
        .iter()
        .find(|(name, _)| name == "stitch_clock")
        .and_then(|(_, m)| m.get("epoch_unix_ns")?.parse().ok())
        .expect("a robot's run records its clock's epoch");
    let kill_ns = killed_at
        .duration_since(std::time::UNIX_EPOCH)
        .expect("after 1970")
        .as_nanos()
        - epoch_ns;
    let last_ns = got.messages.iter().map(|m| m.1).max().expect("messages");
    let lost_s = (kill_ns as f64 - last_ns as f64) * 1e-9;
    eprintln!(
        "killed at run time {:.3} s; recovered to {:.3} s: {:.0} ms lost; {} messages, {} events",
        kill_ns as f64 * 1e-9,
        last_ns as f64 * 1e-9,
        lost_s * 1e3,
        got.messages.len(),
        got.records.len()
    );
    assert!(
        (0.0..=0.25).contains(&lost_s),
        "{:.0} ms of the run before the kill lost",
        lost_s * 1e3
    );
    // Events are queued with the telemetry, in order: every one before the last message is
    // in the file, numbered without a gap, the third step's start among them.
    for (i, r) in got.records.iter().enumerate() {
        assert_eq!(r.seq, i as u64, "no event missing");
    }
    assert!(got.records.iter().any(|r| matches!(
        r.entry,
        Entry::StepStart {
            throw: 0,
            step: 2,
            ..
        }
    )));
    let shown = stitch(&["journal", "show", fixed.to_str().expect("utf-8")]);
    let said = String::from_utf8_lossy(&shown.stdout);
    assert_eq!(shown.status.code(), Some(0), "{said}");
    assert!(said.contains("throw 1 (stopped)"), "{said}");
    assert!(
        said.contains("outcome: unknown: the journal stops at"),
        "{said}"
    );
    let steps = got
        .records
        .iter()
        .filter(|r| matches!(r.entry, Entry::StepEnd { .. }))
        .count();
    let attempts = said
        .lines()
        .filter(|l| l.starts_with("  ") && l.contains(" s  "))
        .count();
    assert_eq!(
        attempts,
        steps + 1,
        "every step on the timeline, the last under way: {said}"
    );
    assert!(said.contains("under way where the journal stops"), "{said}");
    // A dVRK's run cannot be run again; the refusal says what can be done with it.
    let again = stitch(&["replay", fixed.to_str().expect("utf-8")]);
    assert_eq!(again.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&again.stderr).contains("--plan OTHER.rhai"));
}

#[test]
fn a_plan_run_with_parameters_records_them_and_replays_with_them() {
    let args = [
        "--seed",
        "3",
        "--wound-points",
        "3",
        "--param",
        "clearance_mm=8",
        "--param",
        "max_sweeps=3",
    ];
    let path = record_plan("params.mcap", "scripts/stitch_thread.rhai", &args);
    // The values are in the run's metadata and in the journal's first record.
    let exported = export(&path);
    let first: serde_json::Value =
        serde_json::from_str(exported.lines().next().expect("a first record")).expect("JSON");
    assert_eq!(
        first["params"],
        serde_json::json!({ "clearance_mm": 8.0, "max_sweeps": 3 }),
        "{first}"
    );
    let rec = stitch_recorder::read(&path).expect("readable");
    let meta = &rec
        .metadata
        .iter()
        .find(|(n, _)| n == "stitch_run")
        .expect("stitch_run")
        .1;
    assert_eq!(meta["params"], r#"{"clearance_mm":8.0,"max_sweeps":3}"#);
    // They decided the run: its conditions compare with 8 mm.
    assert!(exported.contains("> mm(8)"), "{exported}");
    // A replay gives the plan the same values (without them it would decide on 4 mm).
    let out = stitch(&["replay", path.to_str().expect("utf-8")]);
    let said = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(0), "{said}");
    assert!(said.starts_with("identical: "), "{said}");
    // The same run without them is another run.
    let plain = record_plan(
        "params-default.mcap",
        "scripts/stitch_thread.rhai",
        &args[..4],
    );
    assert!(export(&plain).contains("> mm(4)"));
}
