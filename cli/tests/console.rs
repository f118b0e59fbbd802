//! `stitch run --console`: the web console's guard, a viewer that changes nothing, and the
//! page in a real headless Chromium (docs/console.md).
#![cfg(feature = "console")]

mod support;

use serde_json::Value;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};
use support::{python, root, tmp};

/// A WebSocket viewer of the console's stream.
type Viewer = tungstenite::WebSocket<tungstenite::stream::MaybeTlsStream<TcpStream>>;

/// A `stitch run --console` child, its console's address and token, and what it has
/// written to stderr so far (for a failing test's message).
struct Run {
    child: Child,
    addr: String,
    token: String,
    log: std::sync::Arc<std::sync::Mutex<Vec<String>>>,
}

impl Run {
    fn start(args: &[&str]) -> Self {
        Self::spawn(&[&["run"], args, &["--console", "127.0.0.1:0"]].concat())
    }

    fn spawn(args: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_stitch"))
            .args(args)
            .current_dir(root())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("stitch run starts");
        let stderr = child.stderr.take().expect("stderr");
        let (tx, rx) = std::sync::mpsc::channel();
        let log = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let kept = log.clone();
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                if let Some(url) = line.strip_prefix("console: ") {
                    let _ = tx.send(url.split(' ').next().unwrap_or("").to_string());
                }
                kept.lock().expect("the log").push(line);
            }
        });
        let url = rx
            .recv_timeout(Duration::from_secs(30))
            .expect("stitch prints the console's URL");
        let rest = url.strip_prefix("http://").expect("an http URL");
        let (addr, token) = rest
            .split_once("/#token=")
            .expect("the URL carries the token");
        Self {
            child,
            addr: addr.to_string(),
            token: token.to_string(),
            log,
        }
    }

    /// The last `n` lines the run wrote to stderr, one per line.
    fn log_tail(&self, n: usize) -> String {
        let log = self.log.lock().expect("the log");
        log[log.len().saturating_sub(n)..].join("\n")
    }

    /// A viewer on its console's stream, its token sent.
    fn viewer(&self) -> Viewer {
        let (mut ws, _) =
            tungstenite::connect(format!("ws://{}/api/stream", self.addr)).expect("the stream");
        ws.send(tungstenite::Message::text(format!(
            r#"{{"token":"{}"}}"#,
            self.token
        )))
        .expect("the token");
        ws
    }

    /// The exit code, waiting at most `limit`.
    fn wait(&mut self, limit: Duration) -> i32 {
        let end = Instant::now() + limit;
        loop {
            if let Some(s) = self.child.try_wait().expect("wait") {
                return s.code().expect("an exit code");
            }
            if Instant::now() > end {
                let _ = self.child.kill();
                panic!("stitch run did not end within {limit:?}");
            }
            std::thread::sleep(Duration::from_millis(20));
        }
    }
}

impl Drop for Run {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// One HTTP/1.1 request by hand (the test checks the headers a browser cannot forge, so it
/// writes them itself); the status and body.
fn request(
    addr: &str,
    method: &str,
    path: &str,
    headers: &[(&str, &str)],
    body: &str,
) -> (u16, String) {
    let mut s = TcpStream::connect(addr).expect("connect to the console");
    s.set_read_timeout(Some(Duration::from_secs(10)))
        .expect("timeout");
    let mut req = format!(
        "{method} {path} HTTP/1.1\r\nContent-Length: {}\r\n",
        body.len()
    );
    if !headers
        .iter()
        .any(|(k, _)| k.eq_ignore_ascii_case("connection"))
    {
        req.push_str("Connection: close\r\n");
    }
    if !headers.iter().any(|(k, _)| k.eq_ignore_ascii_case("host")) {
        req.push_str(&format!("Host: {addr}\r\n"));
    }
    for (k, v) in headers {
        req.push_str(&format!("{k}: {v}\r\n"));
    }
    req.push_str("\r\n");
    req.push_str(body);
    s.write_all(req.as_bytes()).expect("send");
    let mut out = String::new();
    let _ = s.read_to_string(&mut out);
    let status = out
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .unwrap_or_else(|| panic!("no HTTP status in {out:?}"));
    let body = out
        .split_once("\r\n\r\n")
        .map_or("", |(_, b)| b)
        .to_string();
    (status, body)
}

fn journal(path: &std::path::Path) -> Vec<Value> {
    std::fs::read_to_string(path)
        .expect("the journal")
        .lines()
        .map(|l| serde_json::from_str(l).expect("a journal line"))
        .collect()
}

#[test]
fn commands_without_the_token_from_elsewhere_or_not_in_control_are_refused_and_journaled() {
    let j = tmp("console-guard.jsonl");
    let mut run = Run::start(&[
        "scripts/stitch.rhai",
        "--journal",
        j.to_str().expect("path"),
    ]);
    let (addr, bearer) = (run.addr.clone(), format!("Bearer {}", run.token));
    let pause = r#"{"command":"pause"}"#;
    let evil_host = format!("evil.example:{}", addr.rsplit(':').next().expect("port"));
    type Case<'a> = (&'a [(&'a str, &'a str)], u16, &'a str);
    let cases: [Case; 5] = [
        (&[], 401, "no token"),
        (
            &[("Authorization", "Bearer 0123456789abcdef0123456789abcdef")],
            401,
            "wrong token",
        ),
        (
            &[
                ("Authorization", &bearer),
                ("Origin", "http://evil.example"),
            ],
            403,
            "Origin",
        ),
        (
            &[("Authorization", &bearer), ("Host", &evil_host)],
            403,
            "Host",
        ),
        (
            &[("Authorization", &bearer)],
            409,
            "no viewer is in control",
        ),
    ];
    for (headers, status, why) in cases {
        let (got, body) = request(&addr, "POST", "/api/command", headers, pause);
        assert_eq!(got, status, "{why}: {body}");
        assert!(body.contains(why), "{why}: {body}");
    }
    // A stream opened from another site's page is refused before it is a WebSocket.
    let (got, _) = request(
        &addr,
        "GET",
        "/api/stream",
        &[
            ("Origin", "http://evil.example"),
            ("Upgrade", "websocket"),
            ("Connection", "Upgrade"),
            ("Sec-WebSocket-Version", "13"),
            ("Sec-WebSocket-Key", "dGhlIHNhbXBsZSBub25jZQ=="),
        ],
        "",
    );
    assert_eq!(got, 403);
    // Not a command at all.
    let (got, _) = request(
        &addr,
        "POST",
        "/api/command",
        &[("Authorization", &bearer)],
        r#"{"command":"dance"}"#,
    );
    assert_eq!(got, 400);
    // Take control, pause, abort.
    let (got, body) = request(
        &addr,
        "POST",
        "/api/control",
        &[("Authorization", &bearer)],
        "",
    );
    assert_eq!(got, 200, "{body}");
    let v: Value = serde_json::from_str(&body).expect("json");
    let viewer = v["control"].as_u64().expect("a viewer id");
    // Another viewer takes control: the first one's commands are refused, until it takes
    // control back; an e-stop never is (not sent here: it would end the run).
    let (_, body) = request(
        &addr,
        "POST",
        "/api/control",
        &[("Authorization", &bearer)],
        "",
    );
    let other = serde_json::from_str::<Value>(&body).expect("json")["control"]
        .as_u64()
        .expect("a viewer id");
    assert_ne!(other, viewer);
    let (got, body) = request(
        &addr,
        "POST",
        "/api/command",
        &[("Authorization", &bearer)],
        &format!(r#"{{"command":"pause","viewer":{viewer}}}"#),
    );
    assert_eq!(got, 409, "{body}");
    assert!(
        body.contains(&format!("viewer {other} is in control")),
        "{body}"
    );
    let (got, _) = request(
        &addr,
        "POST",
        "/api/control",
        &[("Authorization", &bearer)],
        &format!(r#"{{"viewer":{viewer}}}"#),
    );
    assert_eq!(got, 200);
    for c in ["pause", "abort"] {
        let (got, body) = request(
            &addr,
            "POST",
            "/api/command",
            &[("Authorization", &bearer)],
            &format!(r#"{{"command":"{c}","viewer":{viewer}}}"#),
        );
        assert_eq!(got, 200, "{c}: {body}");
    }
    assert_eq!(
        run.wait(Duration::from_secs(60)),
        5,
        "the run ends aborted (exit 5)"
    );
    let records = journal(&j);
    let refused: Vec<&Value> = records.iter().filter(|r| r["event"] == "refused").collect();
    let whys: Vec<&str> = refused
        .iter()
        .map(|r| r["why"].as_str().unwrap_or(""))
        .collect();
    assert_eq!(refused.len(), 8, "every refusal journaled: {whys:?}");
    for (i, part) in [
        "no token",
        "wrong token",
        "Origin",
        "Host",
        "no viewer is in control",
        "Origin",
        "unknown command",
        "is in control",
    ]
    .iter()
    .enumerate()
    {
        assert!(whys[i].contains(part), "refusal {i}: {:?}", whys[i]);
    }
    assert_eq!(refused[5]["command"], "watch");
    assert_eq!(refused[6]["command"], "dance");
    let from = format!("console viewer {viewer} ");
    for (i, r) in refused.iter().enumerate() {
        let who = r["from"].as_str().unwrap_or("");
        // Who asked: the peer, and the viewer where the request named one.
        let expected = if i == 7 {
            from.as_str()
        } else {
            "console 127.0.0.1:"
        };
        assert!(who.starts_with(expected), "refusal {i} from {who:?}");
    }
    let pause = records
        .iter()
        .find(|r| r["event"] == "supervisor" && r["command"] == "pause")
        .expect("the pause journaled");
    assert!(
        pause["from"].as_str().unwrap_or("").starts_with(&from),
        "{pause}"
    );
    assert_eq!(pause["acted"], true);
    let last = records.last().expect("records");
    assert_eq!(last["event"], "finished");
    assert_eq!(last["outcome"]["result"], "aborted");
    assert!(
        records
            .iter()
            .any(|r| r["event"] == "hold" && r.get("error").is_none())
    );
}

/// A viewer that watches half a mission, camera frames included, and goes away, and another
/// that never reads: the journal is the one a run without a console writes, byte for byte,
/// and the run ends.
#[test]
fn a_viewer_connected_then_dropped_changes_nothing_in_the_journal() {
    let (with, without) = (tmp("console-viewer.jsonl"), tmp("console-none.jsonl"));
    let args = ["scripts/stitch_human.rhai", "--seed", "4", "--pace", "40"];
    let status = Command::new(env!("CARGO_BIN_EXE_stitch"))
        .arg("run")
        .args(args)
        .args(["--journal", without.to_str().expect("path")])
        .current_dir(root())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("stitch run");
    let mut run = Run::start(&[&args[..], &["--journal", with.to_str().expect("path")]].concat());
    // A viewer that never reads a thing after its token: its socket fills; nothing waits.
    let stuck = run.viewer();
    let mut ws = run.viewer();
    let (mut events, mut frames) = (0, 0);
    let mut saw_hello = false;
    let next = tungstenite::Message::text(r#"{"type":"frame"}"#);
    while events < 30 || frames < 3 {
        let m = ws.read().expect("a message");
        if let tungstenite::Message::Binary(jpeg) = &m {
            assert!(jpeg.starts_with(&[0xff, 0xd8]), "a JPEG frame");
            frames += 1;
            ws.send(next.clone()).expect("the next frame");
            continue;
        }
        let v: Value = serde_json::from_str(m.to_text().expect("text")).expect("json");
        match v["type"].as_str() {
            Some("hello") => {
                saw_hello = true;
                assert_eq!(v["camera"], true, "the mock's camera is shown");
                ws.send(next.clone()).expect("a frame");
            }
            Some("frame") => assert!(
                v["overlay"]["jaws"]
                    .as_array()
                    .is_some_and(|j| j.len() == 2)
            ),
            // Not drawn yet (the run is starting): ask again.
            Some("no-frame") => ws.send(next.clone()).expect("a frame"),
            Some("events") => events += v["events"].as_array().map_or(0, Vec::len),
            Some("refused") => panic!("refused: {v}"),
            _ => {}
        }
    }
    assert!(saw_hello);
    // Gone mid-run, without a word.
    drop(ws);
    let code = run.wait(Duration::from_secs(120));
    drop(stuck);
    assert_eq!(Some(code), status.code(), "the same outcome");
    let (a, b) = (
        std::fs::read_to_string(&with).expect("journal"),
        std::fs::read_to_string(&without).expect("journal"),
    );
    assert!(a.lines().count() > 30, "a whole mission");
    assert_eq!(a, b, "a viewer changed the journal");
}

/// The page in Debian's Chromium, driven by Selenium through chromedriver
/// (tests/python/console_browser.py): the state changes live; pause mid-step holds the arms
/// and is journaled as the console's; resume; abort ends the run aborted with the arms held;
/// a screenshot of the page mid-mission.
#[test]
fn the_page_in_a_real_browser_pauses_resumes_and_aborts_a_mission() {
    let (chromium, driver) = ("/usr/bin/chromium", "/usr/bin/chromedriver");
    if !(std::path::Path::new(chromium).exists() && std::path::Path::new(driver).exists()) {
        assert!(
            std::env::var_os("CI").is_none(),
            "CI: {chromium} and {driver} are missing (.ci/run installs them)"
        );
        eprintln!(
            "SKIPPED: no {chromium} / {driver} here (apt-get install chromium chromium-driver; \
             .ci/run does)"
        );
        return;
    }
    let py = python();
    let j = tmp("console-browser.jsonl");
    let shot = std::env::var_os("STITCH_CONSOLE_SCREENSHOT")
        .map_or_else(|| tmp("console.png"), std::path::PathBuf::from);
    let mut run = Run::start(&[
        "scripts/stitch_human.rhai",
        "--pace",
        "1.0",
        "--journal",
        j.to_str().expect("path"),
    ]);
    let out = Command::new(py)
        .arg(root().join("tests/python/console_browser.py"))
        .args([
            &format!("http://{}/#token={}", run.addr, run.token),
            shot.to_str().expect("path"),
            chromium,
            driver,
        ])
        .output()
        .expect("python runs the browser test");
    let said = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "the browser test failed:\n{said}");
    assert_eq!(
        run.wait(Duration::from_secs(60)),
        5,
        "aborted (exit 5):\n{said}"
    );
    let records = journal(&j);
    let i = records
        .iter()
        .position(|r| r["event"] == "supervisor" && r["command"] == "pause")
        .expect("the pause journaled");
    let pause = &records[i];
    assert!(
        pause["from"]
            .as_str()
            .unwrap_or("")
            .starts_with("console viewer"),
        "{pause}"
    );
    assert!(
        pause.get("during").is_some(),
        "the pause landed mid-step: {pause}"
    );
    assert_eq!(pause["acted"], true);
    // The engine held: a confirmed hold right after the pause, into `paused(... mid-step)` or,
    // where the pause landed after the step committed (a needle in tissue), `paused(...
    // committed)`: both are mid-step; which one depends on the wall clock.
    let after = &records[i + 1..];
    let next: Vec<String> = after.iter().take(4).map(ToString::to_string).collect();
    assert!(
        after.iter().take(4).any(|r| {
            let to = r["to"].as_str().unwrap_or("");
            r["event"] == "transition"
                && to.starts_with("paused")
                && (to.contains("mid-step") || to.contains("committed"))
        }),
        "no mid-step pause after {pause}: {next:#?}"
    );
    assert!(
        after
            .iter()
            .take(4)
            .any(|r| r["event"] == "hold" && r.get("error").is_none()),
        "no confirmed hold after {pause}: {next:#?}"
    );
    assert!(
        after
            .iter()
            .any(|r| r["event"] == "supervisor" && r["command"] == "resume" && r["acted"] == true)
    );
    let last = records.last().expect("records");
    assert_eq!(last["event"], "finished");
    assert_eq!(last["outcome"]["result"], "aborted");
    let abort = records
        .iter()
        .rposition(|r| r["event"] == "supervisor" && r["command"] == "abort")
        .expect("the abort journaled");
    assert!(
        records[abort..]
            .iter()
            .any(|r| r["event"] == "hold" && r.get("error").is_none())
    );
    let png = std::fs::read(&shot).expect("the screenshot");
    assert!(
        png.starts_with(b"\x89PNG") && png.len() > 10_000,
        "a screenshot of the page"
    );
}

/// `stitch console FILE.mcap`: the recorded run's plan and every record of its journal, its
/// length for the timeline, its camera frames with what the recorder drew on them; no
/// commands.
#[test]
fn a_recording_plays_in_the_console_with_its_whole_journal_and_no_commands() {
    let file = tmp("console-recorded.mcap");
    let status = Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args(["run", "scripts/stitch.rhai", "--seed", "2"])
        .args([
            "--perception",
            "pipeline",
            "--record-frames",
            "1",
            "--journal",
        ])
        .arg(&file)
        .current_dir(root())
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .expect("stitch run");
    assert!(status.code().is_some());
    let out = Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args(["journal", "export", "--jsonl"])
        .arg(&file)
        .output()
        .expect("stitch journal export");
    let exported: Vec<Value> = String::from_utf8_lossy(&out.stdout)
        .lines()
        .map(|l| serde_json::from_str(l).expect("json"))
        .collect();
    assert!(exported.len() > 20);
    let run = Run::spawn(&[
        "console",
        file.to_str().expect("path"),
        "--addr",
        "127.0.0.1:0",
    ]);
    let mut ws = run.viewer();
    let mut events = Vec::new();
    let (mut frame, mut drawn) = (None, None);
    while events.len() < exported.len() || frame.is_none() {
        let m = ws.read().expect("a message");
        if let tungstenite::Message::Binary(jpeg) = &m {
            frame = Some(image::load_from_memory(jpeg).expect("a JPEG"));
            continue;
        }
        let v: Value = serde_json::from_str(m.to_text().expect("text")).expect("json");
        match v["type"].as_str() {
            Some("hello") => {
                assert_eq!(v["plan"]["name"], "STITCH");
                let end = exported.last().expect("records")["t_s"].as_f64();
                assert_eq!(v["replay"]["duration_s"].as_f64(), end);
                assert_eq!(v["replay"]["complete"], true);
                assert_eq!(v["camera"], true, "the recording has frames");
                // The frame half way through the run.
                let at = end.unwrap_or(0.0) / 2.0;
                ws.send(tungstenite::Message::text(format!(
                    r#"{{"type":"frame","t_s":{at}}}"#
                )))
                .expect("ask");
            }
            Some("events") => events.extend(v["events"].as_array().expect("events").clone()),
            Some("frame") => drawn = Some(v["overlay"]["drawn"].clone()),
            _ => {}
        }
    }
    assert_eq!(events, exported, "every record, in order");
    let frame = frame.expect("a frame");
    assert_eq!(
        (frame.width(), frame.height()),
        (1280, 960),
        "the recorded frame, whole"
    );
    let drawn = drawn.expect("the frame's overlay");
    let arc = drawn["lines"][0]["points"].as_array().map_or(0, Vec::len);
    assert!(arc > 10, "the recorded estimate's arc drawn: {drawn}");
    let (got, body) = request(
        &run.addr,
        "POST",
        "/api/command",
        &[("Authorization", &format!("Bearer {}", run.token))],
        r#"{"command":"pause","viewer":1}"#,
    );
    assert_eq!(got, 409, "{body}");
    assert!(body.contains("a recorded run takes no commands"), "{body}");
}

/// Over ROS 2 with the stereo pipeline, the console shows the left images the pipeline
/// captured from the camera topics (the sim-node's), with the estimate drawn over them.
#[cfg(feature = "ros2")]
#[test]
fn over_ros2_the_console_shows_the_pairs_the_pipeline_captured() {
    let _one = support::serial();
    let d = (10 + (std::process::id() % 20) * 10 + 7).to_string();
    let _node = support::SimNode::start(&d, &["--time-scale", "10"]);
    let mut run = Run::start(&[
        "scripts/stitch.rhai",
        "--robot",
        "ros2",
        "--domain-id",
        &d,
        "--perception",
        "pipeline",
    ]);
    let mut ws = run.viewer();
    let next = tungstenite::Message::text(r#"{"type":"frame"}"#);
    let (mut frames, mut with_estimate) = (0, 0);
    let mut ended = None;
    while frames < 2 || with_estimate < 1 {
        let m = match ws.read() {
            Ok(m) => m,
            Err(e) => {
                ended = Some(e);
                break;
            }
        };
        if let tungstenite::Message::Binary(jpeg) = &m {
            let img = image::load_from_memory(jpeg).expect("a JPEG");
            assert_eq!(
                (img.width(), img.height()),
                (640, 480),
                "half the camera's size"
            );
            frames += 1;
            ws.send(next.clone()).expect("the next frame");
            continue;
        }
        let Ok(text) = m.to_text() else { continue };
        let Ok(v) = serde_json::from_str::<Value>(text) else {
            continue;
        };
        match v["type"].as_str() {
            Some("hello") => {
                assert_eq!(v["camera"], true);
                ws.send(next.clone()).expect("a frame");
            }
            Some("frame") => {
                let o = &v["overlay"];
                let jaws = o["jaws"].as_array().map_or(0, Vec::len);
                assert_eq!(jaws, 2, "both arms' measured poses drawn: {o}");
                with_estimate += usize::from(o["needle"].as_array().is_some_and(|a| a.len() > 10));
            }
            Some("no-frame") => ws.send(next.clone()).expect("a frame"),
            _ => {}
        }
    }
    if frames < 2 || with_estimate < 1 {
        let status = run.child.try_wait().ok().flatten();
        panic!(
            "{frames} frames, {with_estimate} with an estimate; the stream ended with {ended:?}; \
             the run's exit status so far {status:?}; its stderr's last lines:\n{}",
            run.log_tail(40)
        );
    }
    drop(ws);
    let _ = run.wait(Duration::from_secs(120));
}
