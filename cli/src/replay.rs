//! Reading recorded runs as a person does: `stitch journal show` (the timeline `stitch run`
//! printed, from the file alone, finished or cut short) and `stitch replay` (the run again
//! from its recorded plan, configuration and seed, compared message by message).

use crate::record::{self, OUTCOMES};
use crate::{MockConfig, PerceptionKind, RobotKind, exit, show};
use anyhow::Context;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use stitch_dvrk::msg::{JointState, OperatingState, PoseStamped};
use stitch_engine::{Loaded, OutcomeSchedule, PlanLoader, Rebuilt, ScriptLimits, validate};
use stitch_recorder::{Recorded, RunInfo};
use stitch_robot::{Wound, WoundSpec};

/// A recording and what its `stitch_run` metadata says.
struct Recording {
    file: PathBuf,
    got: Recorded,
    meta: BTreeMap<String, String>,
}

impl Recording {
    fn read(file: &Path) -> anyhow::Result<Self> {
        let got = stitch_recorder::read(file)?;
        let meta = got
            .metadata
            .iter()
            .find(|(name, _)| name == "stitch_run")
            .map(|(_, m)| m.clone())
            .with_context(|| {
                format!(
                    "{}: no stitch_run metadata (not a file `stitch run --journal` wrote)",
                    file.display()
                )
            })?;
        Ok(Self {
            file: file.to_path_buf(),
            got,
            meta,
        })
    }

    fn get(&self, key: &str) -> anyhow::Result<&str> {
        self.meta.get(key).map(String::as_str).with_context(|| {
            format!(
                "{}: the stitch_run metadata has no `{key}` (recorded by an older stitch?)",
                self.file.display()
            )
        })
    }

    fn attachment(&self, name: &str) -> anyhow::Result<Option<String>> {
        self.got
            .attachments
            .iter()
            .find(|(n, _, _)| n == name)
            .map(|(_, _, data)| {
                String::from_utf8(data.clone()).with_context(|| {
                    format!("{}: attachment {name}: not UTF-8", self.file.display())
                })
            })
            .transpose()
    }

    fn steps_per_throw(&self) -> Option<Vec<usize>> {
        let text = self.meta.get("steps_per_throw")?;
        if text.is_empty() {
            return Some(Vec::new());
        }
        text.split(',').map(|n| n.parse().ok()).collect()
    }

    fn robot(&self) -> anyhow::Result<RobotKind> {
        match self.get("robot")? {
            "mock" => Ok(RobotKind::Mock),
            "scripted" => Ok(RobotKind::Scripted),
            "ros2" => Ok(RobotKind::Ros2),
            other => anyhow::bail!(
                "{}: recorded on an unknown robot `{other}`",
                self.file.display()
            ),
        }
    }

    fn seed(&self) -> anyhow::Result<Option<u64>> {
        let text = self.get("seed")?;
        if text.is_empty() {
            return Ok(None);
        }
        text.parse()
            .map(Some)
            .with_context(|| format!("{}: seed `{text}`", self.file.display()))
    }
}

/// `stitch journal show FILE [--json]`.
pub fn show(file: &Path, json: bool) -> anyhow::Result<u8> {
    let rec = Recording::read(file)?;
    let run = Rebuilt::from_journal(&rec.got.records, rec.steps_per_throw().as_deref())
        .map_err(|e| anyhow::anyhow!("{}: {e}", file.display()))?;
    if !rec.got.complete {
        eprintln!(
            "{}: unfinished (the run did not end cleanly): read up to its last closed chunk, {} \
             records, the last at {:.3} s",
            file.display(),
            rec.got.records.len(),
            run.duration_s
        );
    }
    let mut out = std::io::stdout().lock();
    use std::io::Write;
    if json {
        serde_json::to_writer_pretty(&mut out, &run)?;
        writeln!(out)?;
        return Ok(exit::OK);
    }
    let robot = rec.robot()?;
    let source = match rec.seed()? {
        Some(seed) => format!("seed {seed}"),
        None => format!("replaying {}", OUTCOMES),
    };
    let clock = if robot == RobotKind::Ros2 {
        "wall time"
    } else {
        "simulated time"
    };
    write!(
        out,
        "{}",
        show::timeline_of(&run, &source, crate::robot_name(robot), clock)
    )?;
    Ok(exit::OK)
}

/// `stitch replay`.
#[derive(Debug, clap::Args)]
pub struct ReplayArgs {
    /// A run recorded with `stitch run --journal FILE.mcap` on the mock or the scripted
    /// robot.
    pub file: PathBuf,
    /// Keep the replay's own recording here (default: a temporary file, removed).
    #[arg(long)]
    pub out: Option<PathBuf>,
}

/// Exit status of a replay that diverged from its recording.
pub const DIVERGED: u8 = 7;

/// `stitch replay FILE`: run the recorded plan again on the recorded robot, configuration
/// and seed, recording it, and compare the two files message by message.
pub fn replay(args: &ReplayArgs) -> anyhow::Result<u8> {
    let rec = Recording::read(&args.file)?;
    let robot = rec.robot()?;
    if robot == RobotKind::Ros2 {
        anyhow::bail!(
            "{}: recorded on a dVRK over ROS 2; only mock and scripted runs replay (the robot's \
             world is not in the file)",
            args.file.display()
        );
    }
    let plan_file = rec.get("plan_file")?.to_string();
    let plan_text = rec
        .attachment("plan.rhai")?
        .with_context(|| format!("{}: no plan.rhai attachment", args.file.display()))?;
    let wound: WoundSpec = serde_json::from_str(rec.get("wound")?)
        .with_context(|| format!("{}: the recorded wound", args.file.display()))?;
    let mut mock: MockConfig = match rec.attachment("mock.toml")? {
        Some(text) => toml::from_str(&text)
            .with_context(|| format!("{}: the recorded mock.toml", args.file.display()))?,
        None => MockConfig::default(),
    };
    mock.scene.wound = wound.clone();
    let perception = PerceptionKind::named(rec.get("perception")?).with_context(|| {
        format!(
            "{}: unknown perception `{}`",
            args.file.display(),
            rec.meta["perception"]
        )
    })?;
    let frames_hz: f64 = rec
        .get("record_frames_hz")?
        .parse()
        .with_context(|| format!("{}: record_frames_hz", args.file.display()))?;
    let schedule = rec
        .attachment(OUTCOMES)?
        .map(|text| OutcomeSchedule::from_json(OUTCOMES, &text))
        .transpose()?;
    let seed = rec.seed()?;
    let loaded = load(&plan_file, &plan_text, &wound)?;
    let out = args.out.clone().unwrap_or_else(|| {
        std::env::temp_dir().join(format!("stitch-replay-{}.mcap", std::process::id()))
    });
    let info = RunInfo {
        program: format!("stitch {}", env!("CARGO_PKG_VERSION")),
        plan_file,
        plan_text,
        seed,
        robot: robot.name().into(),
        mock_config: rec.attachment("mock.toml")?,
        settings: rec
            .meta
            .iter()
            .filter(|(k, _)| {
                !matches!(
                    k.as_str(),
                    "program" | "plan_file" | "plan_sha256" | "seed" | "robot" | "frame_period_s"
                )
            })
            .map(|(k, v)| (k.clone(), v.clone()))
            .collect(),
        files: Vec::new(),
    };
    let recorder = record::start(&out, &info, false, frames_hz)?;
    let seed_value = seed.unwrap_or(0);
    let run = match robot {
        RobotKind::Scripted => crate::run_scripted(&loaded, seed_value, schedule, Some(&recorder)),
        _ => crate::run_mock(
            &loaded,
            &mock.scene,
            perception.of(&mock),
            seed_value,
            Some(&recorder),
        ),
    };
    let finished = record::finish(recorder);
    run?;
    finished?;
    let again = stitch_recorder::read(&out)?;
    if args.out.is_none() {
        let _ = std::fs::remove_file(&out);
    }
    let verdict = compare(&rec.got, &again);
    print!("{verdict}");
    Ok(if verdict.starts_with("identical") {
        exit::OK
    } else {
        DIVERGED
    })
}

fn load(file: &str, text: &str, wound: &WoundSpec) -> anyhow::Result<Loaded> {
    let w = Wound::linear(wound).context("the recorded wound")?;
    let loader = PlanLoader::new(&w, ScriptLimits::default());
    let loaded = loader
        .eval_str(file, text)
        .map_err(|e| anyhow::anyhow!("the recorded plan: {e}"))?;
    validate(&loaded.plan).map_err(|e| anyhow::anyhow!("the recorded plan: {e}"))?;
    Ok(loaded)
}

/// "identical …" or where the replay first differs from the recording, in file order.
fn compare(recorded: &Recorded, replayed: &Recorded) -> String {
    let topic = |r: &Recorded, id: u16| {
        r.channels
            .get(&id)
            .map_or_else(|| format!("channel {id}"), |c| c.topic.clone())
    };
    let schema = |r: &Recorded, id: u16| {
        r.channels
            .get(&id)
            .and_then(|c| r.schemas.get(&c.schema_id))
            .map_or_else(String::new, |s| s.0.clone())
    };
    let mut per_topic: BTreeMap<String, usize> = BTreeMap::new();
    let n = recorded.messages.len().max(replayed.messages.len());
    for i in 0..n {
        let a = recorded.messages.get(i);
        let b = replayed.messages.get(i);
        let same = match (a, b) {
            (Some(a), Some(b)) => {
                topic(recorded, a.0) == topic(replayed, b.0) && a.1 == b.1 && a.2 == b.2
            }
            _ => false,
        };
        let here = a.map(|a| topic(recorded, a.0)).unwrap_or_default();
        let k = *per_topic.get(&here).unwrap_or(&0);
        if same {
            *per_topic.entry(here).or_default() += 1;
            continue;
        }
        let side = |r: &Recorded, m: Option<&(u16, u64, Vec<u8>)>| match m {
            None => "(nothing: the run ended)".to_string(),
            Some((id, t, bytes)) => format!(
                "{:.6} s {}: {}",
                *t as f64 * 1e-9,
                topic(r, *id),
                describe(&schema(r, *id), bytes)
            ),
        };
        let t = a.or(b).map_or(0.0, |m| m.1 as f64 * 1e-9);
        let mut s = String::new();
        let _ = writeln!(
            s,
            "diverges at message {} of the file (t = {t:.6} s, {} #{k}):",
            i + 1,
            if here.is_empty() {
                b.map(|b| topic(replayed, b.0)).unwrap_or_default()
            } else {
                here
            }
        );
        let _ = writeln!(s, "  recorded: {}", side(recorded, a));
        let _ = writeln!(s, "  replayed: {}", side(replayed, b));
        return s;
    }
    format!(
        "identical: {} messages on {} channels, the same as recorded\n",
        recorded.messages.len(),
        recorded.channels.len()
    )
}

/// A message, decoded, for a person.
fn describe(schema: &str, bytes: &[u8]) -> String {
    fn d<T: serde::de::DeserializeOwned>(bytes: &[u8], name: &'static str) -> Option<T> {
        stitch_dvrk::decode(bytes, name).ok()
    }
    let pose = |p: &stitch_dvrk::msg::Pose| {
        format!(
            "position ({:.4}, {:.4}, {:.4}) mm, orientation ({:.6}, {:.6}, {:.6}, {:.6})",
            p.position.x * 1e3,
            p.position.y * 1e3,
            p.position.z * 1e3,
            p.orientation.x,
            p.orientation.y,
            p.orientation.z,
            p.orientation.w
        )
    };
    let text = match schema {
        "stitch_msgs/msg/Event" => {
            d::<stitch_recorder::Event>(bytes, "stitch_msgs/msg/Event").map(|e| e.record_json)
        }
        "stitch_msgs/msg/Transition" => {
            d::<stitch_recorder::Transition>(bytes, "stitch_msgs/msg/Transition")
                .map(|t| format!("{} → {}", t.from_state, t.to_state))
        }
        "stitch_msgs/msg/StepEnd" => {
            d::<stitch_recorder::StepEnd>(bytes, "stitch_msgs/msg/StepEnd").map(|e| {
                format!(
                    "t{} s{} {} a{}: {}, entry error {} m, exit error {} m",
                    e.throw_index,
                    e.step,
                    e.primitive,
                    e.attempt,
                    if e.ok { "ok".to_string() } else { e.failure },
                    e.entry_error_m,
                    e.exit_error_m
                )
            })
        }
        "geometry_msgs/msg/PoseStamped" => {
            d::<PoseStamped>(bytes, "geometry_msgs/msg/PoseStamped").map(|p| pose(&p.pose))
        }
        "sensor_msgs/msg/JointState" => d::<JointState>(bytes, "sensor_msgs/msg/JointState")
            .map(|j| format!("{:?} at {:?} rad", j.name, j.position)),
        "crtk_msgs/msg/OperatingState" => {
            d::<OperatingState>(bytes, "crtk_msgs/msg/OperatingState")
                .map(|o| format!("{} homed {} busy {}", o.state, o.is_homed, o.is_busy))
        }
        "rcl_interfaces/msg/Log" => d::<stitch_recorder::Log>(bytes, "rcl_interfaces/msg/Log")
            .map(|l| format!("[{}] {}: {}", l.level, l.name, l.msg)),
        "stitch_msgs/msg/NeedleEstimate" => {
            d::<stitch_recorder::NeedleEstimate>(bytes, "stitch_msgs/msg/NeedleEstimate").map(|e| {
                if e.ok {
                    format!(
                        "step `{}`: {}, confidence {:.3}",
                        e.step,
                        pose(&e.pose),
                        e.confidence
                    )
                } else {
                    format!("step `{}`: no estimate, {}", e.step, e.failure)
                }
            })
        }
        "sensor_msgs/msg/CompressedImage" => {
            d::<stitch_recorder::CompressedImage>(bytes, "sensor_msgs/msg/CompressedImage")
                .map(|i| format!("{} image, {} bytes", i.format, i.data.len()))
        }
        _ => None,
    };
    text.unwrap_or_else(|| format!("{schema}, {} bytes (undecodable)", bytes.len()))
}
