//! What the tests over ROS 2 share: the `stitch` binary run under a deadline, a `stitch
//! sim-node` and the Cyclone DDS stand-in of the dVRK console as child processes.
// Each test binary uses part of this.
#![allow(dead_code)]

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Child, ChildStdin, Command, Stdio};
use std::sync::mpsc::{Receiver, channel};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// `stitch ARGS` from the repository's root, run to its end.
pub fn stitch_at_root(args: &[&str]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args(args)
        .current_dir(root())
        .output()
        .expect("the stitch binary runs")
}

/// `cluster/ray_trials.py` on a local Ray instance: `shards` shards into `work`, merged into
/// `out`, with `extra` arguments (`--chaos K`, `--sweep FILE` or `-- TRIALS-ARGS`); exit
/// code, stdout, stderr.
pub fn ray_driver(
    shards: u32,
    work: &Path,
    out: &Path,
    extra: &[&str],
) -> (Option<i32>, String, String) {
    let o = Command::new(python())
        .arg(root().join("cluster/ray_trials.py"))
        .args(["--stitch", env!("CARGO_BIN_EXE_stitch")])
        .args(["--shards", &shards.to_string()])
        .args(["--work", work.to_str().expect("utf-8")])
        .args(["--out", out.to_str().expect("utf-8")])
        .args(extra)
        .current_dir(root())
        .output()
        .expect("python runs the Ray driver");
    (o.status.code(), text(&o.stdout), text(&o.stderr))
}

/// Bytes a process wrote, as text.
pub fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

pub fn tmp(name: &str) -> PathBuf {
    test_dir("stitch-cli-test").join(name)
}

/// This test process's own directory under the system's temporary one, `PREFIX-PID`,
/// created. The first call for a prefix removes the directories of earlier test processes
/// that are gone (their files stay for a look until the next run, not for ever: a full run
/// writes a few hundred megabytes of journals and shards).
pub fn test_dir(prefix: &str) -> PathBuf {
    static SWEPT: Mutex<Vec<String>> = Mutex::new(Vec::new());
    let tmp = std::env::temp_dir();
    let mut swept = SWEPT.lock().unwrap_or_else(|e| e.into_inner());
    if !swept.iter().any(|p| p == prefix) {
        swept.push(prefix.to_string());
        remove_stale(&tmp, prefix);
    }
    let dir = tmp.join(format!("{prefix}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).expect("temp dir");
    dir
}

/// Remove `PREFIX-PID` under `tmp` for every PID that is no longer a process (Linux's
/// /proc says; elsewhere nothing is removed).
fn remove_stale(tmp: &Path, prefix: &str) {
    if !Path::new("/proc/self").exists() {
        return;
    }
    let Ok(entries) = std::fs::read_dir(tmp) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name
            .to_str()
            .and_then(|n| n.strip_prefix(prefix)?.strip_prefix('-'))
            .and_then(|pid| pid.parse::<u32>().ok())
        else {
            continue;
        };
        if !Path::new(&format!("/proc/{pid}")).exists() {
            let _ = std::fs::remove_dir_all(e.path());
        }
    }
}

/// One test at a time: each runs two processes whose timing bounds (a 0.25 s stale bound, a
/// 1 s busy rise) are a real dVRK's, not a loaded 2-core machine's with nine at once.
static ONE_AT_A_TIME: Mutex<()> = Mutex::new(());

pub fn serial() -> std::sync::MutexGuard<'static, ()> {
    ONE_AT_A_TIME
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A running `stitch sim-node`, killed when dropped; its log lines collected.
pub struct SimNode {
    child: Child,
    log: Arc<Mutex<String>>,
}

impl SimNode {
    pub fn start(domain: &str, args: &[&str]) -> Self {
        let mut child = Command::new(env!("CARGO_BIN_EXE_stitch"))
            .args(["sim-node", "--domain-id", domain])
            .args(args)
            .current_dir(root())
            .stdout(Stdio::null())
            .stderr(Stdio::piped())
            .spawn()
            .expect("stitch sim-node starts");
        let log = Arc::new(Mutex::new(String::new()));
        let (sink, stderr) = (Arc::clone(&log), child.stderr.take().expect("stderr"));
        std::thread::spawn(move || {
            for line in BufReader::new(stderr).lines().map_while(Result::ok) {
                let mut l = sink.lock().expect("log");
                l.push_str(&line);
                l.push('\n');
            }
        });
        let node = Self { child, log };
        node.wait_for("sim-node: ready", Duration::from_secs(30));
        node
    }

    pub fn log(&self) -> String {
        self.log.lock().expect("log").clone()
    }

    /// Its process id (for its memory, threads and open files in `/proc`).
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    pub fn wait_for(&self, text: &str, timeout: Duration) {
        let deadline = Instant::now() + timeout;
        while !self.log().contains(text) {
            assert!(
                Instant::now() < deadline,
                "sim-node did not say {text:?} within {timeout:?}:\n{}",
                self.log()
            );
            std::thread::sleep(Duration::from_millis(10));
        }
    }

    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

impl Drop for SimNode {
    fn drop(&mut self) {
        self.kill();
    }
}

impl SimNode {
    /// Whether the sim-node was told to hold both arms within 5 s; its log if not.
    pub fn held_both(&self) -> Result<(), String> {
        let deadline = Instant::now() + Duration::from_secs(5);
        loop {
            let log = self.log();
            if log.contains("hold /PSM1") && log.contains("hold /PSM2") {
                return Ok(());
            }
            if Instant::now() > deadline {
                return Err(log);
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

/// What a `stitch run` printed and wrote.
pub struct Ran {
    pub code: Option<i32>,
    pub out: String,
    pub journal: String,
    /// Its peak resident memory, kB, as last read from `/proc` while it ran (Linux).
    pub peak_rss_kb: Option<u64>,
}

/// A `/proc/<pid>/status` field in kB (`VmRSS`, `VmHWM`) or a count (`Threads`).
pub fn proc_status(pid: u32, field: &str) -> Option<u64> {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    status
        .lines()
        .find_map(|l| l.strip_prefix(field)?.strip_prefix(':'))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

/// How many files a process has open.
pub fn open_files(pid: u32) -> Option<usize> {
    Some(std::fs::read_dir(format!("/proc/{pid}/fd")).ok()?.count())
}

/// `stitch run`, killed (and the test failed) past `timeout`; nothing on its standard input.
pub fn run(args: &[&str], journal: &Path, timeout: Duration) -> Ran {
    run_typed(args, journal, timeout, "")
}

/// [`run`], with `typed` on its standard input (then end of input).
pub fn run_typed(args: &[&str], journal: &Path, timeout: Duration, typed: &str) -> Ran {
    let (out_path, err_path) = (
        journal.with_extension("stdout"),
        journal.with_extension("stderr"),
    );
    let mut child = Command::new(env!("CARGO_BIN_EXE_stitch"))
        .arg("run")
        .args(args)
        .args(["--journal", journal.to_str().expect("utf-8")])
        .current_dir(root())
        .stdin(Stdio::piped())
        .stdout(std::fs::File::create(&out_path).expect("stdout file"))
        .stderr(std::fs::File::create(&err_path).expect("stderr file"))
        .spawn()
        .expect("stitch run starts");
    {
        use std::io::Write;
        let mut stdin = child.stdin.take().expect("stdin");
        // A run that already ended (bad arguments) reads nothing: not an error here.
        let _ = stdin.write_all(typed.as_bytes());
    }
    let deadline = Instant::now() + timeout;
    let mut peak_rss_kb = None;
    let status = loop {
        peak_rss_kb = proc_status(child.id(), "VmHWM").or(peak_rss_kb);
        if let Some(s) = child.try_wait().expect("wait") {
            break s;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            panic!(
                "stitch run {args:?} did not end within {timeout:?}:\n{}",
                std::fs::read_to_string(&err_path).unwrap_or_default()
            );
        }
        std::thread::sleep(Duration::from_millis(20));
    };
    Ran {
        code: status.code(),
        out: format!(
            "{}{}",
            std::fs::read_to_string(&out_path).unwrap_or_default(),
            std::fs::read_to_string(&err_path).unwrap_or_default()
        ),
        journal: std::fs::read_to_string(journal).unwrap_or_default(),
        peak_rss_kb,
    }
}

/// The tests' Python (a venv from tests/python/requirements.txt, made once by setup.sh).
pub fn python() -> PathBuf {
    let out = Command::new("bash")
        .arg(root().join("tests/python/setup.sh"))
        .stderr(Stdio::inherit())
        .output()
        .expect("bash runs tests/python/setup.sh");
    assert!(
        out.status.success(),
        "tests/python/setup.sh failed: the tests' Python packages need python3 with venv and \
         PyPI reachable (see docs/dvrk.md)"
    );
    PathBuf::from(
        String::from_utf8_lossy(&out.stdout)
            .trim()
            .lines()
            .last()
            .expect("a path"),
    )
}

/// A running stand-in, killed when dropped; driven by lines on its standard input.
pub struct StandIn {
    child: Child,
    stdin: ChildStdin,
    lines: Receiver<String>,
}

impl StandIn {
    pub fn start(domain: u16, args: &[&str]) -> Self {
        let mut child = Command::new(python())
            .arg(root().join("dvrk/standin/dvrk_standin.py"))
            .args(["--domain-id", &domain.to_string()])
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::inherit())
            .spawn()
            .expect("the stand-in starts");
        let stdin = child.stdin.take().expect("stdin");
        let stdout = child.stdout.take().expect("stdout");
        let (tx, lines) = channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines().map_while(Result::ok) {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        let mut s = Self {
            child,
            stdin,
            lines,
        };
        assert_eq!(s.line(Duration::from_secs(60)), "ready");
        s
    }

    pub fn line(&mut self, timeout: Duration) -> String {
        self.lines
            .recv_timeout(timeout)
            .expect("the stand-in answers within its timeout")
    }

    pub fn ask(&mut self, command: &str) -> String {
        writeln!(self.stdin, "{command}").expect("the stand-in reads");
        self.stdin.flush().expect("flush");
        self.line(Duration::from_secs(10))
    }

    pub fn status(&mut self) -> serde_json::Value {
        serde_json::from_str(&self.ask("status")).expect("status is JSON")
    }
}

impl Drop for StandIn {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// A `--dvrk-config` with `settings` (TOML lines of `[camera]`) and the hand-eye pose the
/// sim-node's log gives for its camera, as a lab writes its measured one.
pub fn hand_eye_config(node: &SimNode, k: u16, settings: &str) -> PathBuf {
    node.wait_for("camera_to_robot = ", Duration::from_secs(5));
    let log = node.log();
    let at = log.find("camera_to_robot = ").expect("the hand-eye line");
    let line = log[at..].lines().next().expect("a line");
    let config = tmp(&format!("real-{k}.toml"));
    // These runs share two cores with a sim-node streaming 3.7 MB pairs at 15 Hz and with
    // the other tests: a looser stale bound than a lab's 0.25 s, so a loaded test machine
    // is not taken for a silent dVRK (staleness has tests of its own).
    std::fs::write(
        &config,
        format!("stale_after_s = 1.0\n[camera]\n{settings}{line}\n"),
    )
    .expect("config");
    config
}

/// `stitch run` STITCH on a real dVRK (`--no-simulator`, the stereo pipeline) on domain `d`
/// with settings `config`.
pub fn real_args<'a>(d: &'a str, config: &'a Path) -> Vec<&'a str> {
    vec![
        "scripts/stitch.rhai",
        "--robot",
        "ros2",
        "--no-simulator",
        "--perception",
        "pipeline",
        "--domain-id",
        d,
        "--dvrk-config",
        config.to_str().expect("utf-8"),
    ]
}
