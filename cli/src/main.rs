//! `stitch`: check and run suture plans.
#![allow(clippy::print_stdout)] // a command-line tool prints its results

mod bench_supervision;
#[cfg(feature = "ros2")]
mod console;
mod mock;
mod perceive;
mod perceive_thread;
mod plot;
mod record;
mod replay;
#[cfg(feature = "ros2")]
mod ros2;
mod segmenter;
mod shard;
mod show;
mod sweep;
mod trials;
#[cfg(feature = "console")]
mod web;
#[cfg(feature = "console")]
use web::Feeds as ConsoleFeeds;

use anyhow::Context;
use clap::{Parser, Subcommand, ValueEnum};
use record::is_mcap;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use stitch_cli::inputs::MockConfig;
use stitch_engine::{
    ExploreOptions, Loaded, OutcomeSchedule, ParamValue, Params, PlanErrors, PlanLoader, Report,
    RunOutcome, Runner, ScriptLimits, ScriptedSupervisor, TimedCommand, explore, mermaid, validate,
};
use stitch_primitives::{
    MockPerception, OutcomeModel, RobotPrimitives, ScriptedPrimitives, mock_primitives_observed,
};
use stitch_recorder::Recorder;
use stitch_robot::{SimClock, Wound, WoundSpec};
use stitch_sim::{SceneConfig, SensingConfig};

/// Exit codes, documented in `--help` and `docs/cli.md`.
pub(crate) mod exit {
    /// The plan is valid (check), or the mission completed every throw (run).
    pub const OK: u8 = 0;
    /// Something outside the plan went wrong: a file could not be read or written.
    pub const ERROR: u8 = 1;
    // 2 is clap's: the command line itself is wrong.
    /// The plan is invalid: a script, unit, range, order or budget error. Nothing ran.
    pub const INVALID_PLAN: u8 = 3;
    /// The mission ran and failed with one of the paper's error classes.
    pub const MISSION_FAILED: u8 = 4;
    /// The mission was aborted by the supervisor (abort, e-stop, or no supervisor).
    pub const MISSION_ABORTED: u8 = 5;
}

const EXIT_CODES: &str = "Exit codes:
  0  the plan is valid (check) / the mission completed every throw (run)
  1  a file could not be read or written
  2  the command line is wrong
  3  the plan is invalid (script, unit, range, order or budget error); nothing ran
  4  the mission failed with one of the paper's error classes (I, E, H, T)
  5  the mission was aborted by the supervisor
  6  perceive: the pipeline gave a typed failure instead of a result
  7  replay: the run diverged from its recording";

/// Autonomous suturing missions on the dVRK, under a surgeon's supervision.
#[derive(Debug, Parser)]
#[command(name = "stitch", version, after_help = EXIT_CODES)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Validate a plan script and print it as a tree. Nothing moves.
    #[command(after_help = EXIT_CODES)]
    Check {
        /// The plan script (Rhai), e.g. scripts/stitch.rhai.
        plan: PathBuf,
        /// Also explore every outcome branch of the plan through the engine's state machine
        /// and check its safety properties; print the shortest counterexample of any that
        /// fails. An invalid plan is explored too, to show the paths its problems bite on.
        #[arg(long)]
        explore: bool,
        /// Supervisor commands (pause, take-over, abort, ...) allowed on one explored path.
        #[arg(long, default_value_t = ExploreOptions::default().max_commands, requires = "explore")]
        max_commands: u8,
        /// Write each counterexample's outcome schedule here (FILE, or FILE-2.json, ... for
        /// more than one), to replay with `stitch run PLAN --outcomes FILE`.
        #[arg(long, requires = "explore")]
        counterexample: Option<PathBuf>,
        /// Write the explored state diagram (Mermaid) into this Markdown file, between the
        /// lines `<!-- BEGIN GENERATED STATE DIAGRAM -->` and `<!-- END GENERATED STATE
        /// DIAGRAM -->`.
        #[arg(long, requires = "explore")]
        diagram: Option<PathBuf>,
        #[command(flatten)]
        wound: WoundArgs,
        #[command(flatten)]
        params: ParamArgs,
    },
    /// Validate and run a plan; print a per-throw timeline and the final outcome.
    #[command(after_help = EXIT_CODES)]
    Run {
        /// The plan script (Rhai), e.g. scripts/stitch.rhai.
        plan: PathBuf,
        /// The seed that decides every random draw of a simulated run.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Which robot executes the plan.
        #[arg(long, value_enum, default_value_t = RobotKind::Mock)]
        robot: RobotKind,
        /// How the mock estimates the needle pose: its noise model (the paper's estimator),
        /// the truth, the stereo pipeline on rendered pairs, or the noise model fitted to that
        /// pipeline.
        #[arg(long, value_enum, default_value_t = PerceptionKind::Model)]
        perception: PerceptionKind,
        /// With --perception pipeline: the pipeline's segmenter, classical (colour rules),
        /// onnx (the built-in U-Net; a stitch built with --features onnx), onnx-fast (the
        /// built-in U-Net from half resolution) or onnx:FILE (a model keeping the contract in
        /// docs/perception.md).
        #[arg(long, default_value = "classical")]
        segmenter: segmenter::SegmenterChoice,
        /// The mock's scene, models and faults (TOML; see docs/mock-dvrk.md). Without it,
        /// the defaults.
        #[arg(long)]
        mock_config: Option<PathBuf>,
        /// Write the journal here: FILE.mcap streams it while the run goes (crash-safe,
        /// ROS 2 tools read it; docs/journal.md), any other name gets JSON Lines at the end.
        #[arg(long)]
        journal: Option<PathBuf>,
        /// With --journal FILE.mcap and --perception pipeline: record the camera's stereo
        /// pairs (JPEG) at most this often, Hz; 0: none.
        #[arg(long, default_value_t = 0.0, value_name = "HZ")]
        record_frames: f64,
        /// Replay an outcome schedule (JSON) instead of drawing outcomes from the seed
        /// (scripted robot only).
        #[arg(long)]
        outcomes: Option<PathBuf>,
        /// The supervisor's commands (JSON list of `{"at_s": 12.5, "command": "pause"}` or
        /// `{"at": 3, "command": "abort"}`: at a time on the run's clock, mid-step included,
        /// or before the attempt once that many have started; see docs/cli.md). Mock,
        /// seeded scripted and --robot ros2 against the sim-node.
        #[arg(long, value_name = "FILE")]
        commands: Option<PathBuf>,
        /// Run the mock's (or the scripted robot's) simulated clock at this many times the
        /// wall clock's speed (1.0: real time, so a person can watch and command the run);
        /// default: as fast as it can. The journal is the same at any pace.
        #[arg(long, value_name = "X")]
        pace: Option<f64>,
        /// Serve the live web console at ADDR [default: 127.0.0.1:8080; port 0: any free
        /// one]: the run as it goes and the supervisor's buttons, guarded by a token printed
        /// at start (docs/console.md). Mock and --robot ros2 (the sim-node, or a real dVRK
        /// beside the terminal); the mock's clock then runs at --pace 1.0 unless told
        /// otherwise.
        #[arg(long, value_name = "ADDR", num_args = 0..=1, default_missing_value = "127.0.0.1:8080")]
        console: Option<std::net::SocketAddr>,
        /// Let --console listen on an address other than loopback (a warning says who can
        /// then reach it).
        #[arg(long, requires = "console")]
        console_remote: bool,
        /// Print the final outcome as JSON instead of the timeline.
        #[arg(long)]
        json: bool,
        /// The dVRK backend's settings (TOML: arms, timeouts, tolerances, stale bound, speed
        /// ratio; see docs/dvrk.md) for --robot ros2.
        #[arg(long)]
        dvrk_config: Option<PathBuf>,
        /// The ROS 2 domain for --robot ros2 (0 to 232) [default: $ROS_DOMAIN_ID, else 0].
        #[arg(long)]
        domain_id: Option<String>,
        /// --robot ros2 on a real dVRK: no simulator's side channel, so no scoring and no
        /// simulated recovery; needs --perception pipeline (the stereo camera's topics) and
        /// camera.camera_to_robot in --dvrk-config; the surgeon at this terminal supervises
        /// (commands on standard input; see docs/dvrk.md).
        #[arg(long)]
        no_simulator: bool,
        /// Run the plan even if validation refuses it, to replay a counterexample that
        /// `stitch check --explore` found for an invalid plan. Scripted robot only: nothing
        /// moves. The validation errors are still printed.
        #[arg(long)]
        skip_validation: bool,
        #[command(flatten)]
        wound: WoundArgs,
        #[command(flatten)]
        params: ParamArgs,
    },
    /// The stereo needle pipeline on a pair of images: the pose, the disparity, or a
    /// rendered pair to try them on.
    Perceive {
        #[command(subcommand)]
        command: perceive::PerceiveCommand,
    },
    /// Run the policies over seeded trials on the mock and write the paper's Table I, every
    /// trial's record and journal, and the Fig. 4 histogram (see docs/experiments.md).
    #[command(after_help = EXIT_CODES)]
    Trials(trials::TrialsArgs),
    /// A parameter sweep over the mock's configuration: each point a trials run (sharded
    /// as `trials --shard`), a table of every point's metrics and a plot of the chosen
    /// metric against each parameter (see docs/experiments.md, "Sweeps").
    #[command(after_help = EXIT_CODES)]
    Sweep(sweep::SweepArgs),
    /// Serve the mock dVRK over ROS 2 on the dVRK's CRTK topics (two PSMs and their jaws),
    /// for `stitch run --robot ros2` on one machine (see docs/dvrk.md). Runs until killed.
    #[cfg(feature = "ros2")]
    SimNode(ros2::SimNodeArgs),
    /// Recorded runs (`stitch run --journal FILE.mcap`): show, export, recover (see
    /// docs/journal.md).
    Journal {
        #[command(subcommand)]
        command: record::JournalCommand,
    },
    /// Play a recorded run (`stitch run --journal FILE.mcap`) in the web console: its plan,
    /// states, throws, events and camera frames, with a timeline to scrub (see
    /// docs/console.md). Serves until interrupted (Ctrl-C).
    #[cfg(feature = "console")]
    Console {
        /// The recording (MCAP), finished or not.
        file: PathBuf,
        /// Where to serve the page [port 0: any free one].
        #[arg(long, default_value = "127.0.0.1:8080")]
        addr: std::net::SocketAddr,
        /// Let it listen on an address other than loopback.
        #[arg(long)]
        remote: bool,
    },
    /// Run a recorded mock or scripted run again from its own recorded plan, configuration
    /// and seed, and say "identical" or where it first diverges (see docs/journal.md).
    #[command(after_help = EXIT_CODES)]
    Replay(replay::ReplayArgs),
    /// Benchmarks: `stitch bench perception`, `stitch bench segmentation`, `stitch bench
    /// thread`, `stitch bench supervision`, `stitch bench ros2`.
    Bench {
        #[command(subcommand)]
        command: perceive::BenchCommand,
    },
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum PerceptionKind {
    /// The mock's noise model: truth plus position-dependent noise and dropouts.
    Model,
    /// The true needle pose, never dropping out.
    Perfect,
    /// The stereo pipeline on pairs rendered from the mock's scene (see docs/perception.md).
    Pipeline,
    /// The noise model fitted to the stereo pipeline's measured errors (fast).
    Fitted,
}

impl PerceptionKind {
    /// The kind named `name` on the command line.
    pub(crate) fn from_name(name: &str) -> Option<Self> {
        [Self::Model, Self::Perfect, Self::Pipeline, Self::Fitted]
            .into_iter()
            .find(|k| k.name() == name)
    }

    /// Its name on the command line.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Model => "model",
            Self::Perfect => "perfect",
            Self::Pipeline => "pipeline",
            Self::Fitted => "fitted",
        }
    }

    /// By its name on the command line.
    pub(crate) fn named(name: &str) -> Option<Self> {
        [Self::Model, Self::Perfect, Self::Pipeline, Self::Fitted]
            .into_iter()
            .find(|k| k.name() == name)
    }

    /// The mock's perception of this kind, configured by `mock`, the pipeline's segmenter
    /// `segmenter` (loaded here; only the pipeline has one).
    pub(crate) fn of(
        self,
        mock: &MockConfig,
        segmenter: &segmenter::SegmenterChoice,
    ) -> anyhow::Result<MockPerception> {
        if self != Self::Pipeline && *segmenter != segmenter::SegmenterChoice::Classical {
            anyhow::bail!(
                "--segmenter {segmenter}: only the stereo pipeline segments images; add \
                 --perception pipeline"
            );
        }
        Ok(match self {
            Self::Model => MockPerception::Model(mock.sensing),
            Self::Perfect => MockPerception::Model(SensingConfig::perfect()),
            Self::Pipeline => {
                MockPerception::Pipeline(Box::new(mock.camera.clone()), segmenter.load_learned()?)
            }
            Self::Fitted => MockPerception::Model(SensingConfig::fitted_to_pipeline()),
        })
    }
}

#[derive(Debug, clap::Args)]
struct WoundArgs {
    /// Number of wound points `wound()` returns to the script [default: 6, or the mock
    /// configuration's].
    #[arg(long)]
    wound_points: Option<usize>,
    /// Spacing between wound points along +y, in millimetres [default: 8, or the mock
    /// configuration's].
    #[arg(long)]
    wound_spacing_mm: Option<f64>,
}

impl WoundArgs {
    /// `base` with these flags applied.
    fn apply(&self, mut base: WoundSpec) -> WoundSpec {
        if let Some(n) = self.wound_points {
            base.count = n;
        }
        if let Some(mm) = self.wound_spacing_mm {
            base.spacing_m = mm * 1e-3;
        }
        base
    }
}

/// `--param NAME=VALUE`: values for the plan's `param(name, default)` calls.
#[derive(Debug, Default, clap::Args)]
pub(crate) struct ParamArgs {
    /// Set the plan's parameter NAME (its `param("NAME", default)`) to VALUE, read as the
    /// default's type (integer, number, true/false or text); repeat for more. A parameter
    /// the plan does not declare is refused.
    #[arg(long = "param", value_name = "NAME=VALUE", value_parser = stitch_engine::parse_param_arg)]
    params: Vec<(String, ParamValue)>,
}

impl ParamArgs {
    /// The values by name; a name given twice is refused.
    pub(crate) fn get(&self) -> anyhow::Result<Params> {
        let mut out = Params::new();
        for (k, v) in &self.params {
            if out.insert(k.clone(), v.clone()).is_some() {
                anyhow::bail!("--param {k} is given twice");
            }
        }
        Ok(out)
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub(crate) enum RobotKind {
    /// The embedded mock dVRK: two kinematic PSMs, the needle, the tissue phantom, the
    /// thread, perception noise and injected faults, all seeded.
    Mock,
    /// Outcomes drawn from a seeded distribution (or replayed from --outcomes); moves
    /// nothing and simulates no geometry.
    Scripted,
    /// A dVRK over ROS 2 (CRTK topics): `stitch sim-node` on this or another machine (see
    /// docs/dvrk.md).
    Ros2,
}

impl RobotKind {
    /// Its name on the command line.
    pub(crate) fn name(self) -> &'static str {
        match self {
            Self::Mock => "mock",
            Self::Scripted => "scripted",
            Self::Ros2 => "ros2",
        }
    }
}

/// mimalloc, not the system allocator: glibc's malloc gave the renderer's per-frame image
/// buffers (megabytes each) back to the kernel and faulted them in again on the next frame,
/// more so with the recorder's writer thread running: a pipeline mission took 257,000 page
/// faults and 1.78 s with `--journal FILE.mcap` against 67,000 and 1.37 s without
/// (`perf stat -r 5`). glibc's thresholds can only be fixed with `mallopt` (unsafe, which
/// this workspace forbids) or an environment variable. Measured in docs/journal.md ("Cost").
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(code) => ExitCode::from(code),
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::from(exit::ERROR)
        }
    }
}

fn run(cli: Cli) -> anyhow::Result<u8> {
    match cli.command {
        Command::Perceive { command } => perceive::perceive(command),
        Command::Bench { command } => match command {
            #[cfg(feature = "ros2")]
            perceive::BenchCommand::Ros2(args) => ros2::bench(args),
            perceive::BenchCommand::Supervision(args) => bench_supervision::bench(args),
            perceive::BenchCommand::Thread(args) => perceive_thread::bench(args),
            other => perceive::bench(other),
        },
        Command::Trials(args) => trials::trials(args),
        Command::Sweep(args) => sweep::sweep(args),
        Command::Journal { command } => record::journal(command),
        Command::Replay(args) => replay::replay(&args),
        #[cfg(feature = "ros2")]
        Command::SimNode(args) => ros2::sim_node(args),
        Command::Check {
            plan,
            explore: false,
            wound,
            params,
            ..
        } => {
            let given = params.get()?;
            let Some(loaded) = load(&plan, &wound.apply(WoundSpec::default()), &given, true)?
            else {
                return Ok(exit::INVALID_PLAN);
            };
            print!("{}", show::plan_tree(&loaded.plan));
            print!("{}", show::params(&loaded));
            println!("valid: {} throws, nothing ran", loaded.plan.throws.len());
            Ok(exit::OK)
        }
        Command::Check {
            plan,
            explore: true,
            max_commands,
            counterexample,
            diagram,
            wound,
            params,
        } => {
            let given = params.get()?;
            let (loaded, errors) =
                evaluate(&plan, &wound.apply(WoundSpec::default()), &given, true)?;
            if let Some(errors) = &errors {
                eprintln!("{errors}");
            }
            let Some(loaded) = loaded else {
                return Ok(exit::INVALID_PLAN);
            };
            let options = ExploreOptions {
                max_commands,
                ..ExploreOptions::default()
            };
            let found = explore(Arc::new(loaded.plan.clone()), options.clone());
            print!(
                "{}",
                show::exploration(&plan, &found, &options, errors.is_none())
            );
            let mut n = 0;
            for verdict in found.verdicts.iter().filter(|v| !v.holds) {
                if let (Some(path), Some(schedule)) = (&counterexample, &verdict.schedule) {
                    n += 1;
                    let path = if n == 1 {
                        path.clone()
                    } else {
                        path.with_file_name(format!(
                            "{}-{n}.json",
                            path.file_stem().unwrap_or_default().to_string_lossy()
                        ))
                    };
                    std::fs::write(&path, serde_json::to_string_pretty(schedule)? + "\n")
                        .with_context(|| format!("cannot write {}", path.display()))?;
                    println!(
                        "wrote the counterexample for \"{}\" to {}",
                        verdict.says,
                        path.display()
                    );
                }
            }
            if let Some(file) = diagram {
                write_diagram(&file, &mermaid(&found.edges))?;
                println!("wrote the state diagram into {}", file.display());
            }
            Ok(if errors.is_none() && found.all_hold() {
                exit::OK
            } else {
                exit::INVALID_PLAN
            })
        }
        #[cfg(feature = "console")]
        Command::Console { file, addr, remote } => {
            let playback = replay::playback(&file)?;
            let complete = playback.complete;
            let console = web::Console::replay(addr, remote, playback)?;
            if !complete {
                eprintln!(
                    "{}: unfinished (a crash or a kill?): played up to its last closed chunk",
                    file.display()
                );
            }
            eprintln!("console: {} (Ctrl-C to stop)", console.url());
            loop {
                std::thread::park();
            }
        }
        Command::Run {
            plan,
            seed,
            robot,
            journal,
            record_frames,
            outcomes,
            commands,
            pace,
            console,
            console_remote,
            json,
            skip_validation,
            wound,
            params,
            perception,
            segmenter,
            mock_config,
            dvrk_config,
            domain_id,
            no_simulator,
        } => {
            if outcomes.is_some() && robot != RobotKind::Scripted {
                anyhow::bail!(
                    "--outcomes replays a schedule on the scripted robot: add --robot scripted"
                );
            }
            if commands.is_some() && outcomes.is_some() {
                anyhow::bail!(
                    "--commands and --outcomes: an outcome schedule has its own supervisor \
                     commands (its \"supervisor\" list); use one"
                );
            }
            if commands.is_some() && no_simulator {
                anyhow::bail!(
                    "--commands on a real dVRK: the surgeon at this terminal supervises; type \
                     the commands (docs/dvrk.md)"
                );
            }
            if console.is_some() {
                if robot == RobotKind::Scripted {
                    anyhow::bail!(
                        "--console commands arms (--robot mock or ros2); the scripted robot \
                         has none"
                    );
                }
                if commands.is_some() {
                    anyhow::bail!(
                        "--console and --commands: the console's person commands; use one"
                    );
                }
                if !cfg!(feature = "console") {
                    anyhow::bail!(
                        "--console: this stitch was built without the `console` feature; \
                         rebuild with `cargo build --release --features console`"
                    );
                }
            }
            // A run a person watches goes at the wall clock's pace unless told otherwise.
            let pace = pace.or((console.is_some() && robot == RobotKind::Mock).then_some(1.0));
            if let Some(p) = pace {
                if robot == RobotKind::Ros2 {
                    anyhow::bail!(
                        "--pace sets a simulated clock's speed; over ROS 2 the clock is the wall's"
                    );
                }
                if !(p.is_finite() && p > 0.0) {
                    anyhow::bail!("--pace {p}: expected a positive number (1.0: real time)");
                }
            }
            let supervision = Supervision {
                pace,
                commands: commands
                    .as_deref()
                    .map(read_commands)
                    .transpose()?
                    .unwrap_or_default(),
                live: !json,
                ..Supervision::default()
            };
            let mut mock = read_mock_config(mock_config.as_deref())?;
            mock.scene.wound = wound.apply(mock.scene.wound.clone());
            let spec = mock.scene.wound.clone();
            let given = params.get()?;
            let loaded = if skip_validation && robot == RobotKind::Scripted {
                let (loaded, errors) = evaluate(&plan, &spec, &given, true)?;
                if let Some(errors) = errors {
                    eprintln!("{errors}");
                    eprintln!("running anyway (--skip-validation, scripted robot: nothing moves)");
                }
                loaded
            } else {
                load(&plan, &spec, &given, true)?
            };
            let Some(loaded) = loaded else {
                return Ok(exit::INVALID_PLAN);
            };
            if robot != RobotKind::Ros2
                && (dvrk_config.is_some() || domain_id.is_some() || no_simulator)
            {
                anyhow::bail!("--dvrk-config, --domain-id and --no-simulator are for --robot ros2");
            }
            let recorder = match journal.as_deref().filter(|p| is_mcap(p)) {
                Some(path) => {
                    let info = record::run_info(&record::RunSettings {
                        plan: &plan,
                        seed: (outcomes.is_none()).then_some(seed),
                        robot: robot.name(),
                        mock_config: mock_config.as_deref(),
                        outcomes: outcomes.as_deref(),
                        commands: commands.as_deref(),
                        perception: perception.name(),
                        segmenter: &segmenter,
                        wound: &spec,
                        loaded: &loaded,
                        frames_hz: record_frames,
                    })?;
                    Some(record::start(
                        path,
                        &info,
                        robot == RobotKind::Ros2,
                        record_frames,
                    )?)
                }
                None if record_frames != 0.0 => {
                    anyhow::bail!(
                        "--record-frames records into an MCAP journal: add --journal FILE.mcap"
                    )
                }
                None => None,
            };
            let rec = recorder.as_ref();
            #[cfg(feature = "console")]
            let console = match console {
                Some(addr) => {
                    let plan = Arc::new(loaded.plan.clone());
                    // On a real dVRK the console's person also answers requests for help.
                    let (console, feeds) =
                        web::Console::start(addr, console_remote, &plan, no_simulator)?;
                    if robot == RobotKind::Mock {
                        *supervision.view.borrow_mut() =
                            Some(console.mock_view(mock.camera.clone()));
                    } else if perception == PerceptionKind::Pipeline {
                        *supervision.camera.borrow_mut() =
                            Some(console.camera_view(mock.scene.needle));
                    }
                    eprintln!(
                        "console: {} (the token after #token= guards every command; keep it \
                         to yourself)",
                        console.url()
                    );
                    *supervision.console.borrow_mut() = Some(feeds);
                    *supervision.watch.borrow_mut() = Some(console.sink());
                    Some(console)
                }
                None => None,
            };
            #[cfg(not(feature = "console"))]
            let _ = (console, console_remote);
            let report = match robot {
                RobotKind::Scripted => {
                    let schedule = outcomes.as_deref().map(OutcomeSchedule::read).transpose()?;
                    run_scripted(&loaded, seed, schedule, rec, &supervision)?
                }
                RobotKind::Ros2 | RobotKind::Mock => {
                    let perception = perception.of(&mock, &segmenter)?;
                    if robot == RobotKind::Ros2 {
                        let on = Ros2Run {
                            recorder: rec,
                            dvrk_config,
                            domain_id,
                            simulator: !no_simulator,
                            supervision: &supervision,
                        };
                        run_ros2(&loaded, &mock.scene, perception, seed, on)?
                    } else {
                        run_mock(&loaded, &mock.scene, perception, seed, rec, &supervision)?
                    }
                }
            };
            // Viewers read the end; the server stops.
            #[cfg(feature = "console")]
            drop(console);
            // A recording that failed does not hide how the run went: the timeline first.
            let mut recorded = Ok(());
            if let Some(recorder) = recorder {
                recorded = record::finish(recorder);
            } else if let Some(path) = journal {
                let file = std::fs::File::create(&path)
                    .with_context(|| format!("cannot write the journal to {}", path.display()))?;
                report
                    .journal
                    .write_jsonl(std::io::BufWriter::new(file))
                    .with_context(|| format!("cannot write the journal to {}", path.display()))?;
            }
            let source = match &outcomes {
                Some(file) => format!("replaying {}", file.display()),
                None => format!("seed {seed}"),
            };
            let mut out = std::io::stdout().lock();
            if json {
                serde_json::to_writer_pretty(&mut out, &report.outcome)?;
                writeln!(out)?;
            } else {
                write!(
                    out,
                    "{}",
                    show::timeline(
                        &loaded.plan,
                        &report,
                        &source,
                        robot_name(robot),
                        if robot == RobotKind::Ros2 {
                            "wall time"
                        } else {
                            "simulated time"
                        }
                    )
                )?;
            }
            recorded?;
            Ok(match report.outcome {
                RunOutcome::Completed => exit::OK,
                RunOutcome::Failed { .. } => exit::MISSION_FAILED,
                RunOutcome::Aborted { .. } => exit::MISSION_ABORTED,
            })
        }
    }
}

/// The mock configuration file, or the defaults without one.
/// A mock configuration from its text.
pub(crate) fn read_mock_text(text: &str) -> anyhow::Result<MockConfig> {
    stitch_cli::inputs::mock_config(text)
}

pub(crate) fn read_mock_config(path: Option<&Path>) -> anyhow::Result<MockConfig> {
    let Some(path) = path else {
        return Ok(MockConfig::default());
    };
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    stitch_cli::inputs::mock_config(&text)
        .with_context(|| format!("invalid mock configuration {}", path.display()))
}

pub(crate) fn robot_name(robot: RobotKind) -> &'static str {
    match robot {
        RobotKind::Mock => "the mock dVRK",
        RobotKind::Scripted => "the scripted robot",
        RobotKind::Ros2 => "the dVRK over ROS 2",
    }
}

/// Where and how `--robot ros2` runs.
#[cfg_attr(not(feature = "ros2"), allow(dead_code))] // refused without the feature
struct Ros2Run<'a> {
    /// The flight recorder, if the run is recorded.
    recorder: Option<&'a Recorder>,
    dvrk_config: Option<PathBuf>,
    domain_id: Option<String>,
    /// Against `stitch sim-node`, with its side channel (else a real dVRK).
    simulator: bool,
    /// Commands and the live timeline.
    supervision: &'a Supervision,
}

/// How a run is supervised and shown, beyond its robot.
#[derive(Default)]
pub(crate) struct Supervision {
    /// The simulated clock's pace (`--pace`); `None`: as fast as it can.
    pub pace: Option<f64>,
    /// The supervisor's commands (`--commands`).
    pub commands: Vec<TimedCommand>,
    /// Print each step as it ends, on standard error.
    pub live: bool,
    /// Commands given live from another thread (`stitch bench supervision`), instead of
    /// `commands`; taken by the run.
    pub feed:
        std::cell::RefCell<Option<std::sync::mpsc::Receiver<stitch_engine::SupervisorCommand>>>,
    /// The web console's commands and refusals (`--console`); taken by the run.
    #[cfg(feature = "console")]
    pub console: std::cell::RefCell<Option<ConsoleFeeds>>,
    /// The web console's view of the mock's camera (`--console` on the mock).
    #[cfg(feature = "console")]
    pub view: std::cell::RefCell<Option<web::MockView>>,
    /// The web console's view of a streamed camera (`--console` over ROS 2 with the pipeline).
    #[cfg(feature = "console")]
    pub camera: std::cell::RefCell<Option<web::CameraView>>,
    /// Where else each journal record goes as it is journaled (the web console's viewers).
    pub watch: std::cell::RefCell<Option<stitch_engine::JournalSink>>,
    /// Wraps the rig's arms and jaws before the run (a benchmark's watch on the holds).
    #[allow(clippy::type_complexity)]
    pub rig: std::cell::RefCell<
        Option<Box<dyn FnOnce(stitch_primitives::Rig) -> stitch_primitives::Rig>>,
    >,
}

impl std::fmt::Debug for Supervision {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Supervision")
            .field("pace", &self.pace)
            .field("commands", &self.commands)
            .field("live", &self.live)
            .finish_non_exhaustive()
    }
}

impl Supervision {
    /// The simulated clock for this run.
    pub fn clock(&self) -> SimClock {
        self.pace.map_or_else(SimClock::new, SimClock::paced)
    }

    /// `primitives` with the rig wrapped, where asked.
    pub fn rig(&self, primitives: RobotPrimitives) -> RobotPrimitives {
        match self.rig.borrow_mut().take() {
            Some(f) => primitives.map_rig(f),
            None => primitives,
        }
    }

    /// The simulated surgeon `supervisor`, given this run's commands.
    pub fn supervise(&self, supervisor: mock::MockSupervisor) -> mock::MockSupervisor {
        #[cfg(feature = "console")]
        if let Some(feeds) = self.console.borrow_mut().take() {
            return supervisor.consoled(feeds);
        }
        match self.feed.borrow_mut().take() {
            Some(feed) => supervisor.fed(feed),
            None if !self.commands.is_empty() => supervisor.commanding(self.commands.clone()),
            None => supervisor,
        }
    }

    /// The camera's observer (`frames`, the recorder's if any), showing the web console the
    /// pairs too where it shows a streamed camera.
    #[cfg(feature = "ros2")] // a streamed camera is ROS 2's
    pub fn observe(
        &self,
        frames: Option<stitch_robot::FrameObserver>,
    ) -> Option<stitch_robot::FrameObserver> {
        #[cfg(feature = "console")]
        if let Some(view) = self.camera.borrow().as_ref() {
            return Some(view.observer(frames));
        }
        frames
    }

    /// `rig` with its estimates and arms drawn by the web console, where it shows a streamed
    /// camera.
    #[cfg(feature = "ros2")] // a streamed camera is ROS 2's
    pub fn drawn(&self, rig: stitch_primitives::Rig) -> stitch_primitives::Rig {
        #[cfg(feature = "console")]
        if let Some(view) = self.camera.borrow().as_ref() {
            return view.rig(rig);
        }
        rig
    }

    /// The run's journal sink: the recorder's, the console's, both or none.
    pub fn sink(&self, recorder: Option<&Recorder>) -> Option<stitch_engine::JournalSink> {
        let watch = self.watch.borrow_mut().take();
        match (recorder.map(Recorder::sink), watch) {
            (Some(mut a), Some(mut b)) => Some(Box::new(move |r| {
                a(r);
                b(r);
            })),
            (a, b) => a.or(b),
        }
    }

    /// `runner`, printing each step as it ends where asked.
    pub fn show<'a>(&self, runner: Runner<'a>) -> Runner<'a> {
        if self.live {
            runner.on_attempt(Box::new(|throw, a| {
                eprintln!("{}", show::attempt_line(throw, a));
            }))
        } else {
            runner
        }
    }
}

/// A `--commands` file: a JSON list of timed commands.
pub(crate) fn read_commands(path: &Path) -> anyhow::Result<Vec<TimedCommand>> {
    let text = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the commands {}", path.display()))?;
    commands_from_json(&path.display().to_string(), &text)
}

/// Timed commands from JSON text; errors name the file, line and column.
pub(crate) fn commands_from_json(file: &str, text: &str) -> anyhow::Result<Vec<TimedCommand>> {
    let commands: Vec<TimedCommand> = serde_json::from_str(text).map_err(|e| {
        anyhow::anyhow!(
            "{file}:{}:{}: {}",
            e.line(),
            e.column(),
            e.to_string().split(" at line").next().unwrap_or_default()
        )
    })?;
    for (i, c) in commands.iter().enumerate() {
        if c.at_s.is_some_and(|t| !(t.is_finite() && t >= 0.0)) {
            anyhow::bail!("{file}: command {}: at_s must be a time ≥ 0 s", i + 1);
        }
    }
    Ok(commands)
}

#[cfg(feature = "ros2")]
fn run_ros2(
    loaded: &Loaded,
    scene: &SceneConfig,
    perception: MockPerception,
    seed: u64,
    on: Ros2Run<'_>,
) -> anyhow::Result<Report> {
    let config = ros2::read_dvrk_config(on.dvrk_config.as_deref())?;
    let ros = match on.domain_id {
        Some(d) => stitch_dvrk::ros2::Ros2Options::domain(&d)
            .map_err(|e| anyhow::anyhow!("--domain-id {d}: {e}"))?,
        None => stitch_dvrk::ros2::Ros2Options::from_env().map_err(anyhow::Error::msg)?,
    };
    let connection = ros2::Connection {
        ros: &ros,
        config: &config,
        recorder: on.recorder,
        supervision: on.supervision,
    };
    if on.simulator {
        ros2::run_ros2(loaded, scene, perception, seed, connection)
    } else {
        ros2::run_real(loaded, scene, perception, seed, connection)
    }
}

#[cfg(not(feature = "ros2"))]
fn run_ros2(
    _: &Loaded,
    _: &SceneConfig,
    _: MockPerception,
    _: u64,
    _: Ros2Run<'_>,
) -> anyhow::Result<Report> {
    anyhow::bail!(
        "--robot ros2: this stitch was built without the `ros2` feature; rebuild with \
         `cargo build --release --features ros2`"
    )
}

/// Load and validate with `params` as the values of its `param` calls (with `all_used`, a
/// value the plan does not ask for is an error); print plan errors one per line and return
/// `None` if invalid.
fn load(
    path: &Path,
    wound: &WoundSpec,
    params: &Params,
    all_used: bool,
) -> anyhow::Result<Option<Loaded>> {
    let (loaded, errors) = evaluate(path, wound, params, all_used)?;
    if let Some(errors) = errors {
        eprintln!("{errors}");
        return Ok(None);
    }
    Ok(loaded)
}

/// The parameters a plan declares, for an error message.
pub(crate) fn declared_params(loaded: &Loaded) -> String {
    if loaded.params.is_empty() {
        "it has no param(\"name\", default) calls".into()
    } else {
        format!(
            "its parameters: {}",
            loaded.params.keys().cloned().collect::<Vec<_>>().join(", ")
        )
    }
}

/// The start and end markers of the generated diagram in a Markdown file.
pub const DIAGRAM_BEGIN: &str = "<!-- BEGIN GENERATED STATE DIAGRAM -->";
/// See [`DIAGRAM_BEGIN`].
pub const DIAGRAM_END: &str = "<!-- END GENERATED STATE DIAGRAM -->";

fn write_diagram(file: &Path, diagram: &str) -> anyhow::Result<()> {
    let text =
        std::fs::read_to_string(file).with_context(|| format!("cannot read {}", file.display()))?;
    let (Some(a), Some(b)) = (text.find(DIAGRAM_BEGIN), text.find(DIAGRAM_END)) else {
        anyhow::bail!(
            "{} has no {DIAGRAM_BEGIN} … {DIAGRAM_END} block",
            file.display()
        );
    };
    let block = format!("{DIAGRAM_BEGIN}\n```mermaid\n{diagram}```\n");
    let new = format!("{}{block}{}", &text[..a], &text[b..]);
    std::fs::write(file, new).with_context(|| format!("cannot write {}", file.display()))
}

/// Evaluate the script; validate the plan if it evaluated. Evaluation errors leave no plan.
fn evaluate(
    path: &Path,
    spec: &WoundSpec,
    params: &Params,
    all_used: bool,
) -> anyhow::Result<(Option<Loaded>, Option<PlanErrors>)> {
    let wound =
        Wound::linear(spec).context("invalid wound (--wound-points, --wound-spacing-mm)")?;
    let loader = PlanLoader::new(&wound, ScriptLimits::default()).with_params(params.clone());
    let source = std::fs::read_to_string(path)
        .with_context(|| format!("cannot read the plan {}", path.display()))?;
    let loaded = match loader.eval_str(&path.display().to_string(), &source) {
        Ok(loaded) => loaded,
        Err(e) => return Ok((None, Some(e.into()))),
    };
    for line in &loaded.printed {
        eprintln!("{}: {line}", path.display());
    }
    if all_used && !loaded.unused_params.is_empty() {
        anyhow::bail!(
            "--param {}: {} declares no such parameter ({})",
            loaded.unused_params.join(", "),
            path.display(),
            declared_params(&loaded)
        );
    }
    let errors = validate(&loaded.plan).err();
    Ok((Some(loaded), errors))
}

pub(crate) fn run_mock(
    loaded: &Loaded,
    scene: &SceneConfig,
    perception: MockPerception,
    seed: u64,
    recorder: Option<&Recorder>,
    supervision: &Supervision,
) -> anyhow::Result<Report> {
    let clock = supervision.clock();
    let tap = recorder.map(|r| r.tap(Arc::new(clock.clone())));
    let frames = tap.as_ref().and_then(stitch_recorder::Tap::frames);
    let (primitives, world) =
        mock_primitives_observed(scene, perception, seed, clock.clone(), frames)
            .context("invalid mock configuration")?;
    let primitives = match tap {
        Some(tap) => {
            let truth = world.clone();
            primitives.map_rig(|rig| {
                tap.rig(rig, Some(Box::new(move || Some(truth.needle_truth().pose))))
            })
        }
        None => primitives,
    };
    #[cfg(feature = "console")]
    let primitives = match supervision.view.borrow_mut().take() {
        Some(view) => {
            let watch = view.show(&world)?;
            primitives.map_rig(|rig| watch.rig(rig))
        }
        None => primitives,
    };
    let mut primitives = supervision.rig(primitives);
    let plan = Arc::new(loaded.plan.clone());
    let mut supervisor = supervision.supervise(mock::MockSupervisor::new(world, Arc::clone(&plan)));
    let runner = Runner::new(
        plan,
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        Some(seed),
    )
    .streaming(supervision.sink(recorder));
    Ok(supervision.show(runner).run())
}

pub(crate) fn run_scripted(
    loaded: &Loaded,
    seed: u64,
    outcomes: Option<OutcomeSchedule>,
    recorder: Option<&Recorder>,
    supervision: &Supervision,
) -> anyhow::Result<Report> {
    let clock = supervision.clock();
    let plan = Arc::new(loaded.plan.clone());
    let replaying = outcomes.is_some();
    let (mut primitives, mut supervisor) = match outcomes {
        Some(schedule) => schedule.into_parts(clock.clone()),
        None => (
            ScriptedPrimitives::seeded(seed, OutcomeModel::default(), clock.clone()),
            // Stands in for the supervising surgeon: the --commands given; interventions
            // recover.
            ScriptedSupervisor::new(supervision.commands.clone(), []),
        ),
    };
    let seed = (!replaying).then_some(seed);
    let runner = Runner::new(
        plan,
        &mut primitives,
        &mut supervisor,
        Arc::new(clock),
        seed,
    )
    .streaming(recorder.map(Recorder::sink));
    Ok(supervision.show(runner).run())
}
