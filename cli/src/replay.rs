//! Reading recorded runs as a person does: `stitch journal show` (the timeline `stitch run`
//! printed, from the file alone, finished or cut short) and `stitch replay` (the run again
//! from its recorded plan, configuration and seed, compared message by message).

use crate::record::{self, OUTCOMES};
use crate::{MockConfig, PerceptionKind, RobotKind, exit, show};
use anyhow::Context;
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Duration;
use stitch_dvrk::msg::{JointState, OperatingState, PoseStamped};
use stitch_engine::{
    CheckpointRequest, Entry, InterventionRequest, InterventionResult, Loaded, Moment, NextPoll,
    OutcomeSchedule, PlanLoader, Rebuilt, Record, Runner, ScriptLimits, Supervisor,
    SupervisorCommand, TimedCommand, validate,
};
use stitch_primitives::{
    Control, Failure, FailureKind, Measurements, Observation, ObserveRequest, PrimitiveError,
    Primitives, StepControl, StepOutcome, StepRequest,
};
use stitch_recorder::{Recorded, RunInfo};
use stitch_robot::{SimClock, Wound, WoundSpec};

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
    /// A run recorded with `stitch run --journal FILE.mcap`: on the mock or the scripted
    /// robot to run it again; on any robot with --plan.
    pub file: PathBuf,
    /// Keep the replay's own recording here (default: a temporary file, removed).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Instead, run this other plan on the outcomes the file recorded (any robot, a dVRK's
    /// run included): each of its step attempts gets the next recorded outcome of a step of
    /// that kind, each intervention the next recorded result, and the supervisor's commands
    /// come when they came; prints its timeline and its first decision that differs from
    /// the recorded run's. Nothing moves.
    #[arg(long, value_name = "OTHER.rhai")]
    pub plan: Option<PathBuf>,
}

/// Exit status of a replay that diverged from its recording.
pub const DIVERGED: u8 = 7;

/// `stitch replay FILE`: run the recorded plan again on the recorded robot, configuration
/// and seed, recording it, and compare the two files message by message.
pub fn replay(args: &ReplayArgs) -> anyhow::Result<u8> {
    let rec = Recording::read(&args.file)?;
    let robot = rec.robot()?;
    if let Some(other) = &args.plan {
        return what_if(&rec, other);
    }
    if robot == RobotKind::Ros2 {
        anyhow::bail!(
            "{}: recorded on a dVRK over ROS 2: the robot's world is not in the file, so the run \
             cannot be run again; `--plan OTHER.rhai` runs another plan on its recorded outcomes",
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
    // Recordings made before --segmenter existed used the classical one.
    let segmenter: crate::segmenter::SegmenterChoice = match rec.meta.get("segmenter") {
        Some(s) => s.parse().map_err(|e: String| {
            anyhow::anyhow!("{}: the recorded segmenter: {e}", args.file.display())
        })?,
        None => crate::segmenter::SegmenterChoice::Classical,
    };
    let frames_hz: f64 = rec
        .get("record_frames_hz")?
        .parse()
        .with_context(|| format!("{}: record_frames_hz", args.file.display()))?;
    let schedule = rec
        .attachment(OUTCOMES)?
        .map(|text| OutcomeSchedule::from_json(OUTCOMES, &text))
        .transpose()?;
    let seed = rec.seed()?;
    let params = recorded_params(&rec)?;
    let loaded = load(&plan_file, &plan_text, &wound, &params)?;
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
        // The recorder writes its own keys (program, plan hash, seed, ...) over these.
        settings: rec.meta.clone(),
        files: Vec::new(),
    };
    let recorder = record::start(&out, &info, false, frames_hz)?;
    let seed_value = seed.unwrap_or(0);
    // The supervisor's recorded command schedule, given again at the same times.
    let supervision = crate::Supervision {
        commands: rec
            .attachment(record::COMMANDS)?
            .map(|text| crate::commands_from_json(record::COMMANDS, &text))
            .transpose()?
            .unwrap_or_default(),
        ..crate::Supervision::default()
    };
    let run = match robot {
        RobotKind::Scripted => {
            crate::run_scripted(&loaded, seed_value, schedule, Some(&recorder), &supervision)
        }
        _ => crate::run_mock(
            &loaded,
            &mock.scene,
            perception.of(&mock, &segmenter)?,
            seed_value,
            Some(&recorder),
            &supervision,
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

/// The values of the plan's parameters the recording was made with (none before they
/// existed).
fn recorded_params(rec: &Recording) -> anyhow::Result<stitch_engine::Params> {
    rec.meta.get("params").map_or_else(
        || Ok(stitch_engine::Params::new()),
        |text| {
            serde_json::from_str(text)
                .with_context(|| format!("{}: the recorded params", rec.file.display()))
        },
    )
}

fn load(
    file: &str,
    text: &str,
    wound: &WoundSpec,
    params: &stitch_engine::Params,
) -> anyhow::Result<Loaded> {
    let w = Wound::linear(wound).context("the recorded wound")?;
    let loader = PlanLoader::new(&w, ScriptLimits::default()).with_params(params.clone());
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
        "stitch_msgs/msg/ThreadTrace" => {
            d::<stitch_recorder::ThreadTrace>(bytes, "stitch_msgs/msg/ThreadTrace").map(|t| {
                if t.ok {
                    format!(
                        "step `{}`: {} points, {:.1} mm long, {} hidden spans",
                        t.step,
                        t.points.len(),
                        t.length_m * 1e3,
                        t.hidden_from_m.len()
                    )
                } else {
                    format!("step `{}`: no trace, {}", t.step, t.failure)
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

/// Where a what-if run went past what the recording holds.
#[derive(Clone, Debug, Default)]
struct RanOut {
    /// The attempt (counted from 0 over the run) that had no recorded outcome, and why.
    at: Option<(usize, String)>,
}

impl RanOut {
    /// Note the first place the run went past the recording.
    fn first(cell: &std::cell::RefCell<RanOut>, at: usize, why: impl FnOnce() -> String) {
        let mut r = cell.borrow_mut();
        if r.at.is_none() {
            r.at = Some((at, why()));
        }
    }
}

/// Primitives that answer each attempt with the next outcome the recording holds for a step
/// of its kind, taking as long as that attempt took; nothing moves.
struct RecordedOutcomes {
    by_kind: BTreeMap<String, std::collections::VecDeque<(StepOutcome, f64)>>,
    clock: SimClock,
    attempts: usize,
    ran_out: std::rc::Rc<std::cell::RefCell<RanOut>>,
    /// Each condition's value, `None` where the robot could not observe it.
    conditions: std::collections::VecDeque<Option<bool>>,
}

impl Primitives for RecordedOutcomes {
    /// The attempt takes its recorded time in the slices the control asks for, so recorded
    /// mid-step commands land again at their times.
    fn run(&mut self, req: &StepRequest<'_>, control: &mut dyn StepControl) -> StepOutcome {
        let i = self.attempts;
        self.attempts += 1;
        let name = req.kind.name();
        match self.by_kind.get_mut(name).and_then(|q| q.pop_front()) {
            Some((outcome, duration_s)) => {
                let total = Duration::from_secs_f64(duration_s.max(0.0));
                let mut done = Duration::ZERO;
                while done < total {
                    let slice = control
                        .slice()
                        .map_or(total - done, |s| s.min(total - done));
                    self.clock.advance(slice);
                    done += slice;
                    if control.check(&mut || Ok(())) == Control::Stop {
                        return StepOutcome::Interrupted {
                            committed: false,
                            measured: Measurements::default(),
                        };
                    }
                }
                outcome
            }
            None => {
                RanOut::first(&self.ran_out, i, || {
                    format!(
                        "throw {} step {} ({name}) asks for more `{name}` outcomes than the \
                         recording holds",
                        req.throw + 1,
                        req.step + 1
                    )
                });
                StepOutcome::Failed(Failure {
                    kind: FailureKind::ArmFault {
                        message: "no recorded outcome (what-if replay)".into(),
                    },
                    measured: Measurements::default(),
                })
            }
        }
    }

    /// The recording's condition values, in the order they were decided (a what-if plan with
    /// other conditions decides its own in that order); past them, the replay stops.
    fn observe(&mut self, req: &ObserveRequest<'_>) -> Observation {
        match self.conditions.pop_front() {
            Some(Some(v)) => Observation {
                scripted: Some(v),
                ..Observation::default()
            },
            Some(None) => Observation {
                faults: vec!["the recording could not observe this condition".into()],
                ..Observation::default()
            },
            None => {
                RanOut::first(&self.ran_out, self.attempts, || {
                    format!(
                        "throw {} decides more conditions than the recording holds",
                        req.throw + 1
                    )
                });
                Observation {
                    scripted: Some(false),
                    ..Observation::default()
                }
            }
        }
    }

    fn hold_all(&mut self) -> Result<(), PrimitiveError> {
        Ok(())
    }
}

/// The recorded supervisor: its commands when they came (by attempts started), its
/// interventions' results in order; once the run is past the recording, an abort.
struct RecordedSupervisor {
    commands: std::collections::VecDeque<TimedCommand>,
    interventions: std::collections::VecDeque<InterventionResult>,
    checkpoints: std::collections::VecDeque<SupervisorCommand>,
    ran_out: std::rc::Rc<std::cell::RefCell<RanOut>>,
    attempts: usize,
}

impl Supervisor for RecordedSupervisor {
    fn poll(&mut self, at: &Moment) -> Option<SupervisorCommand> {
        self.attempts = at.attempts;
        if self.ran_out.borrow().at.is_some() {
            return Some(SupervisorCommand::Abort);
        }
        let due = self.commands.front().is_some_and(|c| match c.at_s {
            // A command that landed mid-step lands again at its time.
            Some(t) => t <= at.now.as_secs_f64(),
            None => c.at <= at.attempts && !at.mid_step,
        });
        if due {
            self.commands.pop_front().map(|c| c.command)
        } else {
            None
        }
    }

    fn next_poll(&self, at: &Moment) -> Option<NextPoll> {
        let t = self.commands.front()?.at_s?;
        Some(NextPoll::In(
            Duration::from_secs_f64(t.max(0.0)).saturating_sub(at.now),
        ))
    }

    fn source(&self) -> &str {
        "recording"
    }

    fn wait(&mut self) -> Option<SupervisorCommand> {
        if self.ran_out.borrow().at.is_some() {
            return Some(SupervisorCommand::Abort);
        }
        self.commands.pop_front().map(|c| c.command)
    }

    fn checkpoint(&mut self, request: &CheckpointRequest) -> Option<SupervisorCommand> {
        if self.ran_out.borrow().at.is_some() {
            return Some(SupervisorCommand::Abort);
        }
        match self.checkpoints.pop_front() {
            Some(c) => Some(c),
            None => {
                RanOut::first(&self.ran_out, self.attempts, || {
                    format!(
                        "throw {} reaches a checkpoint (\"{}\") the recording does not hold",
                        request.throw + 1,
                        request.label
                    )
                });
                Some(SupervisorCommand::Abort)
            }
        }
    }

    fn intervene(&mut self, request: &InterventionRequest) -> InterventionResult {
        match self.interventions.pop_front() {
            Some(r) => r,
            None => {
                RanOut::first(&self.ran_out, self.attempts, || {
                    format!(
                        "throw {} step {} asks for an intervention the recording does not hold",
                        request.throw + 1,
                        request.step + 1
                    )
                });
                InterventionResult::Recovered
            }
        }
    }
}

/// A journal's decisions: what the machine chose, without times.
fn decisions(records: &[Record]) -> Vec<(f64, String)> {
    records
        .iter()
        .filter(|r| {
            matches!(
                r.entry,
                Entry::Transition { .. }
                    | Entry::Retry { .. }
                    | Entry::InterventionRequested { .. }
                    | Entry::InterventionEnded { .. }
                    | Entry::Finished { .. }
            )
        })
        .map(|r| {
            let mut v = serde_json::to_value(&r.entry).unwrap_or_default();
            if let Some(m) = v.as_object_mut() {
                m.remove("t_s");
            }
            (r.t_s, v.to_string())
        })
        .collect()
}

/// `stitch replay FILE --plan OTHER.rhai`.
fn what_if(rec: &Recording, other: &Path) -> anyhow::Result<u8> {
    let records = &rec.got.records;
    let mut by_kind: BTreeMap<String, std::collections::VecDeque<(StepOutcome, f64)>> =
        BTreeMap::new();
    let mut commands = std::collections::VecDeque::new();
    let mut interventions = std::collections::VecDeque::new();
    let mut conditions = std::collections::VecDeque::new();
    let mut checkpoints = std::collections::VecDeque::new();
    let mut at_checkpoint = false;
    let (mut started, mut started_at) = (0usize, 0.0);
    for r in records {
        match &r.entry {
            Entry::Condition { value, .. } => conditions.push_back(Some(*value)),
            Entry::Unobserved { .. } => conditions.push_back(None),
            Entry::Checkpoint { .. } => at_checkpoint = true,
            // The answer to a checkpoint is the next command.
            Entry::Supervisor { command, .. } if at_checkpoint => {
                at_checkpoint = false;
                checkpoints.push_back(*command);
            }
            Entry::StepStart { .. } => {
                started += 1;
                started_at = r.t_s;
            }
            // An attempt the supervisor interrupted is interrupted again by its command.
            Entry::StepEnd {
                outcome: StepOutcome::Interrupted { .. },
                ..
            } => {}
            Entry::StepEnd {
                primitive, outcome, ..
            } => by_kind
                .entry(primitive.clone())
                .or_default()
                .push_back((outcome.clone(), r.t_s - started_at)),
            Entry::InterventionEnded { result, .. } => interventions.push_back(*result),
            Entry::Supervisor {
                command,
                during: Some(_),
                ..
            } => commands.push_back(TimedCommand::at_time(r.t_s, *command)),
            Entry::Supervisor { command, .. } => {
                commands.push_back(TimedCommand::before(started, *command));
            }
            _ => {}
        }
    }
    let wound: WoundSpec = match rec.meta.get("wound") {
        Some(w) => serde_json::from_str(w)
            .with_context(|| format!("{}: the recorded wound", rec.file.display()))?,
        None => WoundSpec::default(),
    };
    let text = std::fs::read_to_string(other)
        .with_context(|| format!("cannot read the plan {}", other.display()))?;
    let loaded = load(
        &other.display().to_string(),
        &text,
        &wound,
        &recorded_params(rec)?,
    )?;
    let clock = SimClock::new();
    let ran_out = std::rc::Rc::new(std::cell::RefCell::new(RanOut::default()));
    let mut primitives = RecordedOutcomes {
        by_kind,
        clock: clock.clone(),
        attempts: 0,
        ran_out: std::rc::Rc::clone(&ran_out),
        conditions,
    };
    let mut supervisor = RecordedSupervisor {
        commands,
        interventions,
        checkpoints,
        ran_out: std::rc::Rc::clone(&ran_out),
        attempts: 0,
    };
    let plan = std::sync::Arc::new(loaded.plan.clone());
    let report = Runner::new(
        plan,
        &mut primitives,
        &mut supervisor,
        std::sync::Arc::new(clock),
        None,
    )
    .run();
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{} on the outcomes recorded in {} ({} run of {}):",
        other.display(),
        rec.file.display(),
        rec.meta.get("robot").map_or("a", String::as_str),
        rec.meta.get("plan_file").map_or("?", String::as_str)
    );
    let ran_out = ran_out.borrow().at.clone();
    // The other run's records before the attempt the recording could not answer.
    let cut = ran_out.as_ref().map(|(i, _)| {
        report
            .journal
            .records()
            .iter()
            .filter(|r| matches!(r.entry, Entry::StepStart { .. }))
            .nth(*i)
            .map_or(usize::MAX, |r| r.seq as usize)
    });
    let theirs = &report.journal.records()[..cut
        .unwrap_or(usize::MAX)
        .min(report.journal.records().len())];
    out.push_str(&show::timeline(
        &loaded.plan,
        &report,
        "nothing moves",
        "the recorded outcomes",
        "recorded time",
    ));
    if let Some((_, why)) = &ran_out {
        let _ = writeln!(
            out,
            "beyond the recording: {why}; the other plan's run stops there (aborted), and only \
             its decisions before it are compared"
        );
    }
    let (a, b) = (decisions(records), decisions(theirs));
    let first = a.iter().zip(&b).position(|(x, y)| x.1 != y.1);
    match first {
        Some(i) => {
            let _ = writeln!(out, "decisions: the first {i} as recorded; then");
            let _ = writeln!(out, "  recorded:   {:>8.1} s {}", a[i].0, a[i].1);
            let _ = writeln!(out, "  other plan: {:>8.1} s {}", b[i].0, b[i].1);
        }
        None if a.len() == b.len() => {
            let _ = writeln!(out, "decisions: all {} as recorded", a.len());
        }
        None => {
            let n = a.len().min(b.len());
            let (longer, more) = if a.len() > n {
                ("the recorded run", &a[n])
            } else {
                ("the other plan", &b[n])
            };
            let _ = writeln!(
                out,
                "decisions: the first {n} as recorded; then only {longer} goes on: {:.1} s {}",
                more.0, more.1
            );
        }
    }
    print!("{out}");
    Ok(if first.is_none() && a.len() == b.len() {
        exit::OK
    } else {
        DIVERGED
    })
}

#[cfg(feature = "console")]
/// What `stitch console FILE` plays: a recording's journal, its plan and its left camera's
/// frames (log time ns, JPEG), if it recorded any.
pub(crate) struct Playback {
    /// The engine's journal.
    pub records: Vec<Record>,
    /// The plan it ran, evaluated again from the recorded script.
    pub plan: stitch_engine::Plan,
    /// The left camera's recorded frames, in time order.
    pub frames: Vec<(u64, Vec<u8>)>,
    /// What the recorder drew on the left image (the estimate, the truth), by log time, in
    /// time order.
    pub annotations: Vec<(u64, stitch_recorder::ImageAnnotations)>,
    /// Whether the file was finished (else read up to its last closed chunk).
    pub complete: bool,
}

#[cfg(feature = "console")]
/// Read `file` for playing it in the console.
pub(crate) fn playback(file: &Path) -> anyhow::Result<Playback> {
    let rec = Recording::read(file)?;
    let plan_file = rec.get("plan_file")?.to_string();
    let plan_text = rec
        .attachment("plan.rhai")?
        .with_context(|| format!("{}: no plan.rhai attachment", file.display()))?;
    let wound: WoundSpec = serde_json::from_str(rec.get("wound")?)
        .with_context(|| format!("{}: the recorded wound", file.display()))?;
    let plan = load(&plan_file, &plan_text, &wound, &recorded_params(&rec)?)?.plan;
    let left: Vec<u16> = rec
        .got
        .channels
        .iter()
        .filter(|(_, c)| c.topic == stitch_recorder::FRAME_TOPICS[0])
        .map(|(id, _)| *id)
        .collect();
    let drawn: Vec<u16> = rec
        .got
        .channels
        .iter()
        .filter(|(_, c)| c.topic == "/stitch/camera/left/annotations")
        .map(|(id, _)| *id)
        .collect();
    let (mut frames, mut annotations) = (Vec::new(), Vec::new());
    for (channel, t, bytes) in &rec.got.messages {
        if drawn.contains(channel) {
            let a: stitch_recorder::ImageAnnotations =
                stitch_dvrk::decode(bytes, stitch_recorder::IMAGE_ANNOTATIONS.name).map_err(
                    |e| anyhow::anyhow!("{}: a left image annotation: {e}", file.display()),
                )?;
            annotations.push((*t, a));
        }
        if left.contains(channel) {
            let image: stitch_recorder::CompressedImage =
                stitch_dvrk::decode(bytes, stitch_recorder::COMPRESSED_IMAGE.name)
                    .map_err(|e| anyhow::anyhow!("{}: a left camera frame: {e}", file.display()))?;
            frames.push((*t, image.data));
        }
    }
    frames.sort_by_key(|(t, _)| *t);
    annotations.sort_by_key(|(t, _)| *t);
    Ok(Playback {
        records: rec.got.records.clone(),
        plan,
        frames,
        annotations,
        complete: rec.got.complete,
    })
}
