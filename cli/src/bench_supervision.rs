//! `stitch bench supervision`: how long a supervisor's command takes to make the arms hold,
//! from its arrival (sent from another thread, as a person's keystroke or a console's button
//! is) to the arms' `hold` being commanded, while a mission runs: on the mock at `--pace 1.0`
//! in process, and over ROS 2 against an in-process `stitch sim-node` (where also to the
//! sim-node's arms receiving the hold).

use crate::{MockConfig, Supervision};
use anyhow::Context;
use rand::{Rng, SeedableRng};
use std::io::Write;
use std::sync::mpsc::Sender;
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use stitch_engine::{Loaded, SupervisorCommand};
use stitch_primitives::{MockPerception, Rig};
use stitch_robot::{Arm, MoveHandle, Pose, RobotError, SpeedLimits};
use stitch_sim::SensingConfig;

/// `stitch bench supervision`.
#[derive(Debug, clap::Args)]
pub struct BenchSupervisionArgs {
    /// Pauses sent per robot (each is resumed 30 ms later); those sent while an arm
    /// moves are the measured ones.
    #[arg(long, default_value_t = 120)]
    pub commands: usize,
    /// Also over ROS 2, against an in-process sim-node (a stitch built with --features ros2).
    #[arg(long)]
    pub ros2: bool,
    /// Seed of the mission and of the times the commands are sent.
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
    #[cfg(feature = "ros2")]
    #[command(flatten)]
    pub ros: crate::ros2::Ros2Args,
}

/// What one robot's measurement found.
#[derive(Debug, serde::Serialize)]
struct Row {
    robot: String,
    sent: usize,
    /// Pauses sent while an arm moved (the measured ones).
    during_motion: usize,
    median_ms: f64,
    p99_ms: f64,
    max_ms: f64,
    /// Over ROS 2: to the sim-node's arm receiving the hold.
    #[serde(skip_serializing_if = "Option::is_none")]
    reached_median_ms: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    reached_p99_ms: Option<f64>,
    /// Pauses sent while no arm moved (an estimator cycle, between steps): they take effect
    /// when it ends.
    not_moving: usize,
    not_moving_median_ms: f64,
}

/// The last motion each watched arm was told to make.
type Motions = Arc<Mutex<Vec<Arc<Mutex<Option<MoveHandle>>>>>>;

/// Whether any watched arm is moving now.
fn moving(motions: &Motions) -> bool {
    motions
        .lock()
        .unwrap_or_else(PoisonError::into_inner)
        .iter()
        .any(|m| {
            m.lock()
                .unwrap_or_else(PoisonError::into_inner)
                .as_ref()
                .is_some_and(MoveHandle::is_busy)
        })
}

/// An arm that notes when it is told to hold, and keeps its last motion for the sender to
/// see whether it moves.
struct Watched {
    arm: Arc<dyn Arm>,
    last: Arc<Mutex<Option<MoveHandle>>>,
    holds: Arc<Mutex<Vec<Instant>>>,
}

impl Arm for Watched {
    fn name(&self) -> &str {
        self.arm.name()
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        self.arm.measured_cp()
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        self.arm.setpoint_cp()
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        let h = self.arm.move_cp(goal)?;
        *self.last.lock().unwrap_or_else(PoisonError::into_inner) = Some(h.clone());
        Ok(h)
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        self.arm.servo_cp(goal)
    }
    fn hold(&self) -> Result<(), RobotError> {
        self.holds
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Instant::now());
        self.arm.hold()
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        self.arm.set_max_speed(limits)
    }
}

/// Sends `n` pauses, each 150 ms to 400 ms after the last resume (seeded), each resumed
/// 30 ms later, then an abort; notes when each pause was sent and whether an arm was moving
/// then.
fn sender(
    tx: Sender<SupervisorCommand>,
    n: usize,
    seed: u64,
    sent: Arc<Mutex<Vec<(Instant, bool)>>>,
    motions: Motions,
) -> std::thread::JoinHandle<()> {
    std::thread::spawn(move || {
        let mut rng = rand_chacha::ChaCha8Rng::seed_from_u64(seed);
        // Let the mission start moving.
        std::thread::sleep(Duration::from_millis(500));
        for _ in 0..n {
            std::thread::sleep(Duration::from_millis(rng.random_range(150..400)));
            let was_moving = moving(&motions);
            sent.lock()
                .unwrap_or_else(PoisonError::into_inner)
                .push((Instant::now(), was_moving));
            if tx.send(SupervisorCommand::Pause).is_err() {
                return;
            }
            std::thread::sleep(Duration::from_millis(30));
            if tx.send(SupervisorCommand::Resume).is_err() {
                return;
            }
        }
        let _ = tx.send(SupervisorCommand::Abort);
    })
}

fn quantile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// Run a mission through `run` with pauses fed to it, and measure each pause's latency to
/// the first hold commanded after it.
fn measure(
    robot: &str,
    args: &BenchSupervisionArgs,
    run: impl FnOnce(&Supervision) -> anyhow::Result<stitch_engine::Report>,
    reached: Option<Arc<Mutex<Vec<Instant>>>>,
) -> anyhow::Result<Row> {
    let (tx, rx) = std::sync::mpsc::channel();
    let sent = Arc::new(Mutex::new(Vec::new()));
    let holds = Arc::new(Mutex::new(Vec::new()));
    let motions: Motions = Arc::default();
    let (watch, registry) = (Arc::clone(&holds), Arc::clone(&motions));
    let wrap = move |a: Arc<dyn Arm>| -> Arc<dyn Arm> {
        let last = Arc::new(Mutex::new(None));
        registry
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .push(Arc::clone(&last));
        Arc::new(Watched {
            arm: a,
            last,
            holds: Arc::clone(&watch),
        })
    };
    let supervision = Supervision {
        pace: Some(1.0),
        feed: std::cell::RefCell::new(Some(rx)),
        rig: std::cell::RefCell::new(Some(Box::new(move |rig: Rig| Rig {
            right: wrap(rig.right),
            left: wrap(rig.left),
            ..rig
        }))),
        ..Supervision::default()
    };
    let feeder = sender(tx, args.commands, args.seed, Arc::clone(&sent), motions);
    let report = run(&supervision)?;
    let _ = feeder.join();
    let sent = sent.lock().unwrap_or_else(PoisonError::into_inner).clone();
    let holds = holds.lock().unwrap_or_else(PoisonError::into_inner).clone();
    let reached = reached.map(|r| r.lock().unwrap_or_else(PoisonError::into_inner).clone());
    let (mut moving, mut still, mut to_robot) = (Vec::new(), Vec::new(), Vec::new());
    for (i, (t0, was_moving)) in sent.iter().copied().enumerate() {
        let t0 = &t0;
        let next = sent.get(i + 1).map(|(t, _)| *t);
        let before_next = |t: &Instant| *t >= *t0 && next.is_none_or(|n| *t < n);
        // The first hold commanded after the pause was sent (both arms are told; the first).
        let Some(t) = holds.iter().find(|t| before_next(t)).copied() else {
            continue;
        };
        let ms = (t - *t0).as_secs_f64() * 1e3;
        if was_moving {
            moving.push(ms);
            if let Some(r) = reached
                .as_ref()
                .and_then(|r| r.iter().find(|t| before_next(t)))
            {
                to_robot.push((*r - *t0).as_secs_f64() * 1e3);
            }
        } else {
            still.push(ms);
        }
    }
    for v in [&mut moving, &mut still, &mut to_robot] {
        v.sort_by(f64::total_cmp);
    }
    eprintln!(
        "{robot}: {} pauses sent, run {:?}",
        sent.len(),
        report.outcome
    );
    Ok(Row {
        robot: robot.into(),
        sent: sent.len(),
        during_motion: moving.len(),
        median_ms: quantile(&moving, 0.5),
        p99_ms: quantile(&moving, 0.99),
        max_ms: moving.last().copied().unwrap_or(f64::NAN),
        reached_median_ms: (!to_robot.is_empty()).then(|| quantile(&to_robot, 0.5)),
        reached_p99_ms: (!to_robot.is_empty()).then(|| quantile(&to_robot, 0.99)),
        not_moving: still.len(),
        not_moving_median_ms: quantile(&still, 0.5),
    })
}

/// The mission the benchmark runs: STITCH on the mock's default scene, the noise-model
/// estimator; long enough at real time for every command.
fn mission() -> anyhow::Result<(Loaded, MockConfig)> {
    let mock = MockConfig::default();
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/stitch.rhai");
    let text = include_str!("../../scripts/stitch.rhai");
    let wound = stitch_robot::Wound::linear(&mock.scene.wound).context("wound")?;
    let loader = stitch_engine::PlanLoader::new(&wound, stitch_engine::ScriptLimits::default());
    let loaded = stitch_engine::load_plan_str(&loader, &path.display().to_string(), text)
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    Ok((loaded, mock))
}

/// `stitch bench supervision`.
pub fn bench(args: BenchSupervisionArgs) -> anyhow::Result<u8> {
    if !(1..=10_000).contains(&args.commands) {
        anyhow::bail!("--commands {}: expected 1 to 10000", args.commands);
    }
    let (loaded, mock) = mission()?;
    let perception = MockPerception::Model(SensingConfig::default());
    let mut rows = vec![measure(
        "mock, in process, --pace 1.0",
        &args,
        |s| crate::run_mock(&loaded, &mock.scene, perception.clone(), args.seed, None, s),
        None,
    )?];
    if args.ros2 {
        rows.push(ros2_row(&args, &loaded, &mock)?);
    }
    let mut out = std::io::stdout().lock();
    if args.json {
        serde_json::to_writer_pretty(&mut out, &rows)?;
        writeln!(out)?;
        return Ok(crate::exit::OK);
    }
    writeln!(
        out,
        "supervisor command → both arms told to hold, while an arm moves ({} pauses per robot, \
         sent from another thread 150–400 ms apart, seed {})",
        args.commands, args.seed
    )?;
    writeln!(
        out,
        "{:<38} {:>6} {:>10} {:>9} {:>9} {:>14} {:>12}",
        "robot", "moving", "median ms", "p99 ms", "max ms", "→ robot p99 ms", "still (med)"
    )?;
    for r in &rows {
        writeln!(
            out,
            "{:<38} {:>6} {:>10.2} {:>9.2} {:>9.2} {:>14} {:>5} ({:.0} ms)",
            r.robot,
            r.during_motion,
            r.median_ms,
            r.p99_ms,
            r.max_ms,
            r.reached_p99_ms
                .map_or("-".to_string(), |v| format!("{v:.2}")),
            r.not_moving,
            r.not_moving_median_ms
        )?;
    }
    writeln!(
        out,
        "still: pauses sent while no arm moved (an estimator cycle, 1.5 s on the mock's \
         noise model); they hold when it ends."
    )?;
    Ok(crate::exit::OK)
}

#[cfg(feature = "ros2")]
fn ros2_row(
    args: &BenchSupervisionArgs,
    loaded: &Loaded,
    mock: &MockConfig,
) -> anyhow::Result<Row> {
    use std::sync::atomic::AtomicBool;
    use stitch_dvrk::arm::DvrkConfig;
    use stitch_dvrk::sim_node::SimNodeOptions;
    let ros = args.ros.options()?;
    let stop = Arc::new(AtomicBool::new(false));
    // When the sim-node's arm receives a hold during a motion.
    let reached = Arc::new(Mutex::new(Vec::new()));
    let node = {
        let (stop, reached) = (Arc::clone(&stop), Arc::clone(&reached));
        std::thread::spawn(move || {
            // Motions at wall-clock speed, as on a dVRK, so pauses land in them.
            let options = SimNodeOptions {
                ros,
                time_scale: 1.0,
                ..SimNodeOptions::default()
            };
            stitch_dvrk::sim_node::serve(&options, &stop, &mut |line| {
                if line.starts_with("sim-node: hold /") && line.contains("during motion") {
                    reached
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .push(Instant::now());
                }
            })
        })
    };
    let config = DvrkConfig::default();
    let row = measure(
        "ROS 2, against an in-process sim-node",
        args,
        |s| {
            crate::ros2::run_ros2(
                loaded,
                &mock.scene,
                MockPerception::Model(SensingConfig::default()),
                args.seed,
                crate::ros2::Connection {
                    ros: &ros,
                    config: &config,
                    recorder: None,
                    supervision: s,
                },
            )
        },
        Some(reached),
    );
    stop.store(true, std::sync::atomic::Ordering::SeqCst);
    let _ = node.join();
    row
}

#[cfg(not(feature = "ros2"))]
fn ros2_row(_: &BenchSupervisionArgs, _: &Loaded, _: &MockConfig) -> anyhow::Result<Row> {
    anyhow::bail!(
        "--ros2: this stitch was built without the `ros2` feature; rebuild with \
         `cargo build --release --features ros2`"
    )
}
