//! `stitch run --robot ros2` and `stitch sim-node`: missions over the dVRK's CRTK topics on
//! ROS 2, against a real dVRK or the mock served by `stitch sim-node`.

use crate::console::ConsoleSupervisor;
use anyhow::Context;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;
use stitch_dvrk::arm::{DvrkConfig, Ros2Dvrk};
use stitch_dvrk::camera::{Ros2Camera, Trigger};
use stitch_dvrk::oracle::{Answer, Call, Oracle};
use stitch_dvrk::ros2::Ros2Options;
use stitch_dvrk::sim_node::{SimNodeOptions, WireFault};
use stitch_engine::{Loaded, Report, Runner};
use stitch_eval::percentile;
use stitch_perception::{
    NeedleEstimate, NeedleEstimator, NeedlePipeline, PerceptionError, PipelineEstimator,
    SharedSegmenter,
};
use stitch_primitives::{
    FailureKind, MockPerception, Observer, PassObservation, Rig, RobotPrimitives, mock_layout,
};
use stitch_recorder::Recorder;
use stitch_robot::{Arm, Clock, Jaw, ObservedCamera, StereoCamera, WallClock, WoundPoint};
use stitch_sim::{CameraConfig, SceneConfig, SensingConfig, Streams, Subsystem};

/// Where on ROS 2.
#[derive(Debug, clap::Args)]
pub struct Ros2Args {
    /// The ROS 2 domain (`ROS_DOMAIN_ID`, 0 to 232) [default: $ROS_DOMAIN_ID, else 0].
    #[arg(long, value_parser = parse_domain)]
    pub domain_id: Option<u16>,
}

fn parse_domain(s: &str) -> Result<u16, String> {
    Ros2Options::domain(s).map(|o| o.domain_id)
}

impl Ros2Args {
    /// The options: the flag, else the environment.
    pub fn options(&self) -> anyhow::Result<Ros2Options> {
        match self.domain_id {
            Some(domain_id) => Ok(Ros2Options { domain_id }),
            None => Ros2Options::from_env().map_err(anyhow::Error::msg),
        }
    }
}

/// `stitch sim-node`.
#[derive(Debug, clap::Args)]
pub struct SimNodeArgs {
    #[command(flatten)]
    pub ros: Ros2Args,
    /// The first world's seed (each `stitch run --robot ros2` resets the world to its own).
    #[arg(long, default_value_t = 1)]
    pub seed: u64,
    /// The mock's scene (TOML, as for `stitch run --mock-config`).
    #[arg(long)]
    pub mock_config: Option<PathBuf>,
    /// Simulated seconds per wall second while a motion is reported busy (1: real time).
    #[arg(long, default_value_t = 100.0)]
    pub time_scale: f64,
    /// State publishing rate (measured_cp, setpoint_cp, jaw/measured_js), Hz.
    #[arg(long, default_value_t = 100.0)]
    pub rate_hz: f64,
    /// Misbehave as a dVRK can, at the N-th motion command: arm-error@N (error, then FAULT),
    /// busy-stuck@N, stale-stamps@N, zero-stamps@N (every measurement from then on),
    /// drop-command@N (that one command, as if lost), deaf@N (every motion command from then
    /// on), camera-silent@N (no stereo images from then on), oracle-silent@N (no
    /// side-channel answers from then on). Repeatable.
    #[arg(long = "wire-fault", value_name = "KIND@N")]
    pub wire_faults: Vec<WireFault>,
    /// Stream the stereo camera (--mock-config's) at this rate, Hz, from the start, as a
    /// camera driver does: for `stitch run --robot ros2 --no-simulator` and image tools.
    /// Without it the camera renders a pair per capture trigger only.
    #[arg(long, value_name = "HZ")]
    pub camera_hz: Option<f64>,
    /// Serve the arms' namespaces and the camera's topics this `stitch run --dvrk-config`
    /// file names (the rest of it is the client's).
    #[arg(long)]
    pub dvrk_config: Option<PathBuf>,
}

/// Serve the mock until killed.
pub fn sim_node(args: SimNodeArgs) -> anyhow::Result<u8> {
    let config = crate::read_mock_config(args.mock_config.as_deref())?;
    let names = read_dvrk_config(args.dvrk_config.as_deref())?;
    let options = SimNodeOptions {
        arms: names.arms,
        camera_topics: names.camera,
        ros: args.ros.options()?,
        seed: args.seed,
        scene: config.scene,
        sensing: config.sensing,
        time_scale: args.time_scale,
        rate_hz: args.rate_hz,
        faults: args.wire_faults,
        camera: args.camera_hz.map(|_| config.camera.clone()),
        camera_hz: args.camera_hz,
    };
    let stop = AtomicBool::new(false);
    stitch_dvrk::sim_node::serve(&options, &stop, &mut |line| eprintln!("{line}"))
        .map_err(anyhow::Error::msg)?;
    Ok(crate::exit::OK)
}

/// The dVRK backend's configuration file, or the defaults.
pub fn read_dvrk_config(path: Option<&std::path::Path>) -> anyhow::Result<DvrkConfig> {
    let Some(path) = path else {
        return Ok(DvrkConfig::default());
    };
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    let config = toml::from_str::<DvrkConfig>(&text)
        .with_context(|| format!("invalid dVRK configuration {}", path.display()))?;
    config
        .validate()
        .with_context(|| format!("invalid dVRK configuration {}", path.display()))?;
    Ok(config)
}

/// The simulator's needle estimator, over the side channel.
struct RemoteEstimator(Arc<Oracle>);

impl NeedleEstimator for RemoteEstimator {
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError> {
        match self.0.call(Call::Estimate) {
            Ok(Answer::Estimate(r)) => r.map(|e| NeedleEstimate {
                pose: e.pose,
                confidence: e.confidence,
                stamp: Duration::from_secs_f64(e.stamp_s.max(0.0)),
            }),
            Ok(other) => Err(PerceptionError::Camera {
                message: format!("the simulator answered {other:?} to an estimate"),
            }),
            Err(message) => Err(PerceptionError::Camera { message }),
        }
    }
}

/// The simulator's ground truth, over the side channel. A call it does not answer is reported
/// as an arm fault (the mission cannot go on without knowing the scene).
struct RemoteObserver {
    oracle: Arc<Oracle>,
    lost: Option<String>,
}

impl RemoteObserver {
    fn ask(&mut self, call: Call) -> Option<Answer> {
        match self.oracle.call(call) {
            Ok(a) => Some(a),
            Err(e) => {
                self.lost = Some(e);
                None
            }
        }
    }
}

impl Observer for RemoteObserver {
    fn begin_pass(&mut self) {
        let _ = self.ask(Call::BeginPass);
    }

    fn end_pass(&mut self, point: &WoundPoint) -> PassObservation {
        match self.ask(Call::EndPass {
            point: point.clone(),
        }) {
            Some(Answer::Pass(p)) => PassObservation {
                entry_error_m: p.entry_error_m,
                exit_error_m: p.exit_error_m,
                protrusion_m: p.protrusion_m,
                passed: p.passed,
            },
            other => {
                if let Some(a) = other {
                    self.lost = Some(format!("end of pass: unexpected answer {a:?}"));
                }
                PassObservation {
                    entry_error_m: None,
                    exit_error_m: None,
                    protrusion_m: 0.0,
                    passed: false,
                }
            }
        }
    }

    fn problem(&mut self) -> Option<FailureKind> {
        if let Some(message) = self.lost.take() {
            return Some(FailureKind::ArmFault { message });
        }
        match self.ask(Call::Problem) {
            Some(Answer::Problem(p)) => p,
            Some(other) => Some(FailureKind::ArmFault {
                message: format!("problem: unexpected answer {other:?}"),
            }),
            None => self
                .lost
                .take()
                .map(|message| FailureKind::ArmFault { message }),
        }
    }

    /// An unanswered question counts as "still in" (the safe side: the extraction is not
    /// taken as done), and `problem` then reports the side channel's failure.
    fn needle_in_tissue(&mut self) -> bool {
        match self.ask(Call::NeedleInTissue) {
            Some(Answer::Bool(b)) => b,
            Some(other) => {
                self.lost = Some(format!("needle in tissue: unexpected answer {other:?}"));
                true
            }
            None => true,
        }
    }

    fn cinched(&mut self, beta_m: f64) {
        let _ = self.ask(Call::Cinched { beta_m });
    }

    fn thread_left_m(&mut self) -> f64 {
        match self.ask(Call::ThreadLeft) {
            Some(Answer::Meters(m)) => m,
            Some(other) => {
                self.lost = Some(format!("thread left: unexpected answer {other:?}"));
                f64::NAN
            }
            None => f64::NAN,
        }
    }
}

/// The simulator's camera trigger, over the side channel.
struct SimTrigger(Arc<Oracle>);

impl Trigger for SimTrigger {
    fn fire(&self) -> Result<stitch_dvrk::msg::Time, String> {
        match self.0.call(Call::Capture)? {
            Answer::Frame(stamp) => Ok(stamp),
            other => Err(format!("the simulator answered {other:?} to a capture")),
        }
    }

    fn resend(&self, stamp: stitch_dvrk::msg::Time) -> Result<(), String> {
        self.0.call(Call::Resend { stamp }).map(|_| ())
    }
}

/// The stereo camera over ROS 2 and the pipeline for its pairs, as the in-process mock runs
/// them for `--perception pipeline`: the calibration from `camera_info`, the hand-eye pose
/// from the configuration or else the simulated camera's own, each capture triggered over
/// the simulator's side channel.
fn sim_camera(
    ros: &Ros2Options,
    config: &DvrkConfig,
    camera: &CameraConfig,
    segmenter: Option<SharedSegmenter>,
    scene: &SceneConfig,
    oracle: &Arc<Oracle>,
    clock: Arc<dyn Clock>,
) -> anyhow::Result<(Ros2Camera, NeedlePipeline)> {
    let camera_to_robot = match &config.camera.camera_to_robot {
        Some(h) => h.pose().map_err(anyhow::Error::msg)?,
        None => camera.camera_to_robot(),
    };
    let camera = Ros2Camera::connect(
        ros,
        &config.camera,
        camera_to_robot,
        Some(Box::new(SimTrigger(Arc::clone(oracle)))),
        clock,
        Duration::from_secs_f64(config.connect_timeout_s),
    )
    .context("cannot connect to the stereo camera")?;
    let mut pipeline = NeedlePipeline::classical(camera.calibration().clone(), scene.needle)
        .context("the stereo camera's calibration")?;
    if let Some(s) = segmenter {
        pipeline.segmenter = Box::new(s);
    }
    Ok((camera, pipeline))
}

/// Where and how a run over ROS 2 connects, records and is supervised.
#[derive(Debug, Clone, Copy)]
pub struct Connection<'a> {
    /// The ROS 2 domain and transport.
    pub ros: &'a Ros2Options,
    /// The dVRK backend's settings.
    pub config: &'a DvrkConfig,
    /// The flight recorder, if the run is recorded.
    pub recorder: Option<&'a Recorder>,
    /// Commands and the live timeline.
    pub supervision: &'a crate::Supervision,
}

/// Run `loaded` over ROS 2: connect to the dVRK's arms, and to the simulator's side channel
/// for the observer, the supervisor's recovery motion and, with the noise model, the
/// estimator; with `--perception pipeline`, to the stereo camera's topics.
pub fn run_ros2(
    loaded: &Loaded,
    scene: &SceneConfig,
    perception: MockPerception,
    seed: u64,
    on: Connection<'_>,
) -> anyhow::Result<Report> {
    let Connection {
        ros,
        config,
        recorder,
        supervision,
    } = on;
    let timeout = Duration::from_secs_f64(config.connect_timeout_s);
    let oracle = Oracle::connect(ros, timeout).map_err(|e| {
        anyhow::anyhow!(
            "{e}\nThe scene's scoring, the simulated recovery and the noise-model estimator \
             come from `stitch sim-node`'s side channel. On a real dVRK add --no-simulator \
             (with --perception pipeline and camera.camera_to_robot in --dvrk-config): no \
             scoring, and you supervise at this terminal."
        )
    })?;
    let oracle = Arc::new(oracle);
    let dvrk = connect_arms(ros, config)?;
    // The sim-node streams the arms' state all the time: a call it stops answering fails
    // once that stream is silent, not after the whole timeout. Lenient (nothing moves
    // during a call): a second, or the stale bound if longer.
    let (weak, bound) = (
        Arc::downgrade(&dvrk),
        Duration::from_secs_f64(config.stale_after_s.max(1.0)),
    );
    oracle.watch(Box::new(move || {
        weak.upgrade().map_or(Ok(()), |d| d.alive(bound))
    }));
    let (sensing, camera, segmenter) = match perception {
        MockPerception::Model(sensing) => (sensing, None, None),
        MockPerception::Pipeline(camera, segmenter) => {
            (SensingConfig::default(), Some(camera), segmenter)
        }
    };
    oracle
        .call(Call::Reset {
            seed,
            scene: Box::new(scene.clone()),
            sensing,
            camera: camera.clone(),
        })
        .map_err(anyhow::Error::msg)?;
    dvrk.wait_fresh(timeout)?;
    let clock: Arc<dyn Clock> = Arc::new(WallClock::new());
    let tap = recorder.map(|r| r.tap(Arc::clone(&clock)));
    if let Some(tap) = &tap {
        tap.wall_epoch();
    }
    let frames = tap.as_ref().and_then(stitch_recorder::Tap::frames);
    // The web console's view of the camera, if it shows one.
    let frames = supervision.observe(frames);
    let estimator: Box<dyn NeedleEstimator> = match &camera {
        Some(c) => {
            let (camera, pipeline) =
                sim_camera(ros, config, c, segmenter, scene, &oracle, clock.clone())?;
            Box::new(PipelineEstimator::new(
                ObservedCamera::new(camera, frames),
                pipeline,
                seed,
            ))
        }
        None => Box::new(RemoteEstimator(Arc::clone(&oracle))),
    };
    let observer = RemoteObserver {
        oracle: Arc::clone(&oracle),
        lost: None,
    };
    let rig = rig(
        &dvrk,
        estimator,
        Some(Box::new(observer)),
        scene,
        &sensing,
        seed,
    )?;
    let rig = supervision.drawn(rig);
    let mut primitives = supervision.rig(RobotPrimitives::new(tapped(rig, tap, &dvrk)));
    let plan = Arc::new(loaded.plan.clone());
    let (o, d) = (Arc::clone(&oracle), Arc::clone(&dvrk));
    let supervisor = crate::mock::MockSupervisor::with(
        Box::new(move |needs| {
            o.call(Call::Recover { needs })?;
            d.wait_fresh(timeout).map_err(|e| e.to_string())
        }),
        Arc::clone(&plan),
    );
    let mut supervisor = supervision.supervise(supervisor);
    let runner = Runner::new(plan, &mut primitives, &mut supervisor, clock, Some(seed))
        .streaming(supervision.sink(recorder));
    let outcome = supervision.show(runner).run();
    say_resends(&dvrk);
    Ok(outcome)
}

/// Say how many commands were sent again because the dVRK showed nothing of them within
/// `resend_after_s` (a loaded network or console; each copy the console did get runs again).
fn say_resends(dvrk: &Ros2Dvrk) {
    let n = dvrk.resends();
    if n > 0 {
        eprintln!(
            "dVRK: {n} command{} sent again (no sign of it within resend_after_s)",
            if n == 1 { "" } else { "s" }
        );
    }
}

/// The primitives' robot over ROS 2: the dVRK's first two arms and jaws (right, left), the
/// estimator and observer given, the workspace of `scene`.
fn rig(
    dvrk: &Arc<Ros2Dvrk>,
    estimator: Box<dyn NeedleEstimator>,
    observer: Option<Box<dyn Observer>>,
    scene: &SceneConfig,
    sensing: &SensingConfig,
    seed: u64,
) -> anyhow::Result<Rig> {
    let missing = |i: usize| anyhow::anyhow!("the dVRK configuration names no arm {i}");
    let arm = |i: usize| dvrk.arm(i).ok_or_else(|| missing(i));
    let jaw = |i: usize| dvrk.jaw(i).ok_or_else(|| missing(i));
    Ok(Rig {
        right: Arc::new(arm(0)?),
        left: Arc::new(arm(1)?),
        right_jaw: Arc::new(jaw(0)?),
        left_jaw: Arc::new(jaw(1)?),
        estimator,
        observer,
        needle: scene.needle,
        layout: mock_layout(scene, sensing),
        rng: Streams::new(seed).rng(Subsystem::Primitives),
    })
}

/// On Ctrl-C, send `hold` to every arm, give DDS a moment to deliver it, and end the process
/// (exit 5, aborted). Holds the dVRK weakly: a run that ends normally still drops its bus.
/// Meet the dVRK's arms (Ctrl-C holds them from then on) and say what the console had
/// latched from before this run and was not counted.
fn connect_arms(ros: &Ros2Options, config: &DvrkConfig) -> anyhow::Result<Arc<Ros2Dvrk>> {
    let dvrk = Arc::new(Ros2Dvrk::connect(ros, config).context("cannot connect to the dVRK")?);
    hold_on_interrupt(&dvrk);
    for e in dvrk.ignored_history() {
        eprintln!("dVRK: not counted, from before this run (latched by the console): {e}");
    }
    Ok(dvrk)
}

fn hold_on_interrupt(dvrk: &Arc<Ros2Dvrk>) {
    let weak = Arc::downgrade(dvrk);
    let set = ctrlc::set_handler(move || {
        if let Some(d) = weak.upgrade() {
            let failed = d.hold_all();
            std::thread::sleep(stitch_dvrk::ros2::HOLD_LINGER);
            if failed.is_empty() {
                eprintln!(
                    "interrupted: hold sent to both arms; the run ends (no JSON Lines journal; \
                     an MCAP journal holds the run to its last closed chunk)"
                );
            } else {
                eprintln!(
                    "interrupted: HOLD FAILED: {}; use the dVRK console's e-stop; the run ends",
                    failed.join("; ")
                );
            }
        }
        std::process::exit(i32::from(crate::exit::MISSION_ABORTED));
    });
    if let Err(e) = set {
        eprintln!("warning: Ctrl-C will not hold the arms: {e}");
    }
}

/// Run `loaded` on a real dVRK over ROS 2: the arms, and the stereo pipeline on the camera's
/// streamed pairs; no simulator, so no scoring (no observer) and no simulated recovery: the
/// surgeon at this terminal supervises ([`ConsoleSupervisor`]).
pub fn run_real(
    loaded: &Loaded,
    scene: &SceneConfig,
    perception: MockPerception,
    seed: u64,
    on: Connection<'_>,
) -> anyhow::Result<Report> {
    let Connection {
        ros,
        config,
        recorder,
        supervision,
    } = on;
    let MockPerception::Pipeline(_, segmenter) = perception else {
        anyhow::bail!(
            "--no-simulator: a real dVRK has no noise model to estimate the needle with; add \
             --perception pipeline (the stereo pipeline on the camera's topics)"
        );
    };
    let Some(hand_eye) = &config.camera.camera_to_robot else {
        anyhow::bail!(
            "--no-simulator: set camera.camera_to_robot in --dvrk-config (the rectified left \
             camera's pose in the robot frame: its hand-eye calibration; docs/dvrk.md)"
        );
    };
    let camera_to_robot = hand_eye.pose().map_err(anyhow::Error::msg)?;
    let timeout = Duration::from_secs_f64(config.connect_timeout_s);
    let clock: Arc<dyn Clock> = Arc::new(WallClock::new());
    // The camera first: connecting to the arms enables and homes them, which moves them.
    let camera = Ros2Camera::connect(
        ros,
        &config.camera,
        camera_to_robot,
        None,
        clock.clone(),
        timeout,
    )
    .context("cannot connect to the stereo camera")?;
    let mut pipeline = NeedlePipeline::classical(camera.calibration().clone(), scene.needle)
        .context("the stereo camera's calibration")?;
    if let Some(s) = segmenter {
        pipeline.segmenter = Box::new(s);
    }
    let dvrk = connect_arms(ros, config)?;
    let tap = recorder.map(|r| r.tap(Arc::clone(&clock)));
    if let Some(tap) = &tap {
        tap.wall_epoch();
    }
    let frames = tap.as_ref().and_then(stitch_recorder::Tap::frames);
    // The web console's view of the camera, if it shows one.
    let frames = supervision.observe(frames);
    let estimator = Box::new(PipelineEstimator::new(
        ObservedCamera::new(camera, frames),
        pipeline,
        seed,
    ));
    let rig = rig(
        &dvrk,
        estimator,
        None,
        scene,
        &SensingConfig::default(),
        seed,
    )?;
    let rig = supervision.drawn(rig);
    let mut primitives = RobotPrimitives::new(tapped(rig, tap, &dvrk));
    eprintln!(
        "no simulator: nothing scores the passes or watches the thread. What the robot cannot \
         sense (a caught thread, a missed exit point) is yours to see: type pause or abort."
    );
    #[cfg(feature = "console")]
    let mut supervisor = match supervision.console.borrow_mut().take() {
        Some(feeds) => ConsoleSupervisor::stdin_and_web(feeds),
        None => ConsoleSupervisor::stdin(),
    };
    #[cfg(not(feature = "console"))]
    let mut supervisor = ConsoleSupervisor::stdin();
    let runner = Runner::new(
        Arc::new(loaded.plan.clone()),
        &mut primitives,
        &mut supervisor,
        clock,
        Some(seed),
    )
    .streaming(supervision.sink(recorder));
    let outcome = supervision.show(runner).run();
    say_resends(&dvrk);
    Ok(outcome)
}

/// How often a recorded run samples the dVRK's arms between the primitives' calls, s.
const SAMPLE_PERIOD: Duration = Duration::from_millis(50);

/// `rig` with a recorder's tap on it, if the run is recorded, and a sampler recording each
/// arm's measured and setpoint poses and jaw at 20 Hz, and its operating states and errors
/// as they change.
fn tapped(rig: Rig, tap: Option<stitch_recorder::Tap>, dvrk: &Arc<Ros2Dvrk>) -> Rig {
    let Some(tap) = tap else {
        return rig;
    };
    let weak = Arc::downgrade(dvrk);
    let mut seen: Vec<(Option<stitch_dvrk::msg::OperatingState>, usize)> = Vec::new();
    let mut gaps = std::collections::HashSet::new();
    tap.sample_every(SAMPLE_PERIOD, move |tap| {
        // The run is over once the dVRK is dropped.
        let Some(dvrk) = weak.upgrade() else {
            return false;
        };
        for (i, state) in dvrk.states().into_iter().enumerate() {
            if seen.len() <= i {
                seen.push((None, 0));
            }
            let (last, errors) = &mut seen[i];
            if state.operating != *last {
                if let Some(s) = &state.operating {
                    tap.operating_state(&state.name, s);
                }
                *last = state.operating.clone();
            }
            for e in state.errors.iter().skip(*errors) {
                tap.log(
                    stitch_recorder::Log::ERROR,
                    &state.name,
                    &format!("error: {e}"),
                );
            }
            *errors = state.errors.len();
            // A read that fails leaves a gap in the samples, and says why once, when the
            // gap opens (a stale arm would otherwise fill /rosout at 20 Hz).
            let mut gap = |what: &str, r: Result<(), stitch_robot::RobotError>| {
                let key = format!("{}/{what}", state.name);
                match r {
                    Ok(()) => {
                        gaps.remove(&key);
                    }
                    Err(e) => {
                        if gaps.insert(key) {
                            tap.log(
                                stitch_recorder::Log::WARN,
                                &state.name,
                                &format!("sampling {what}: {e} (no samples until it reads again)"),
                            );
                        }
                    }
                }
            };
            if let Some(arm) = dvrk.arm(i) {
                let r = arm.measured_cp().map(|p| {
                    tap.pose(&format!("/{}/measured_cp", state.name), &p);
                });
                gap("measured_cp", r);
                let r = arm.setpoint_cp().map(|p| {
                    tap.pose(&format!("/{}/setpoint_cp", state.name), &p);
                });
                gap("setpoint_cp", r);
            }
            if let Some(jaw) = dvrk.jaw(i) {
                let r = jaw.measured_jp().map(|a| {
                    tap.jaw_angle(
                        &format!("/{}/jaw/measured_js", state.name),
                        &format!("{}_jaw", state.name),
                        a,
                    );
                });
                gap("jaw/measured_js", r);
            }
        }
        true
    });
    tap.rig(rig, None)
}

/// `stitch bench ros2`.
#[derive(Debug, clap::Args)]
pub struct BenchRos2Args {
    #[command(flatten)]
    pub ros: Ros2Args,
    /// Seconds streamed at each rate.
    #[arg(long, default_value_t = 5.0)]
    pub seconds: f64,
    /// Stereo pairs captured over ROS 2 and, for the baseline, in process.
    #[arg(long, default_value_t = 40)]
    pub pairs: usize,
    /// Print JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// One rate's measurement.
#[derive(Debug, serde::Serialize)]
struct StreamStats {
    rate_hz: f64,
    sent: usize,
    received: usize,
    median_us: f64,
    p99_us: f64,
    max_us: f64,
}

/// Capture times of stereo pairs, ms.
#[derive(Debug, serde::Serialize)]
struct PairStats {
    pairs: usize,
    median_ms: f64,
    p99_ms: f64,
    max_ms: f64,
}

impl PairStats {
    fn of(mut ms: Vec<f64>) -> Self {
        ms.sort_by(f64::total_cmp);
        let at = |q: f64| percentile(&ms, q);
        Self {
            pairs: ms.len(),
            median_ms: at(0.5),
            p99_ms: at(0.99),
            max_ms: at(1.0),
        }
    }
}

/// Time `n` captures of the mock's stereo pair: rendered in process (the baseline), and
/// over ROS 2 from the sim-node on `ros` (trigger, render, two 1280×960 images over DDS,
/// conversion), both on the default scene and camera.
fn bench_pairs(ros: &Ros2Options, n: usize) -> anyhow::Result<(PairStats, PairStats)> {
    use stitch_primitives::PIPELINE_FRAME_TIME_S;
    use stitch_sim::{MockCamera, MockDvrk, StereoRenderer};
    let camera = CameraConfig::default();
    let scene = SceneConfig::default();
    let world = MockDvrk::new(&scene, Streams::new(1), stitch_robot::SimClock::new())?;
    let renderer = StereoRenderer::new(camera.clone(), world.phantom_view())?;
    let local = MockCamera::new(
        world,
        renderer,
        Streams::new(1),
        Duration::from_secs_f64(PIPELINE_FRAME_TIME_S),
    );
    let mut in_process = Vec::new();
    for _ in 0..n {
        let t = std::time::Instant::now();
        std::hint::black_box(local.capture()?);
        in_process.push(t.elapsed().as_secs_f64() * 1e3);
    }
    let timeout = Duration::from_secs(15);
    let oracle = Arc::new(Oracle::connect(ros, timeout).map_err(anyhow::Error::msg)?);
    oracle
        .call(Call::Reset {
            seed: 1,
            scene: Box::new(scene),
            sensing: SensingConfig::default(),
            camera: Some(Box::new(camera.clone())),
        })
        .map_err(anyhow::Error::msg)?;
    let remote = Ros2Camera::connect(
        ros,
        &stitch_dvrk::camera::CameraSettings::default(),
        camera.camera_to_robot(),
        Some(Box::new(SimTrigger(Arc::clone(&oracle)))),
        Arc::new(WallClock::new()),
        timeout,
    )?;
    let mut over_ros2 = Vec::new();
    for _ in 0..n {
        let t = std::time::Instant::now();
        std::hint::black_box(remote.capture()?);
        over_ros2.push(t.elapsed().as_secs_f64() * 1e3);
    }
    Ok((PairStats::of(in_process), PairStats::of(over_ros2)))
}

/// Stream `servo_cp` to a sim-node served in this process over real DDS on loopback, at
/// 100 Hz (the baseline: the dVRK's state rate) and at 1 kHz, and measure each command's
/// one-way latency (the sim-node's receive time minus the command's stamp, one clock); then
/// time stereo pairs captured over ROS 2 against the same pairs rendered in process.
pub fn bench(args: BenchRos2Args) -> anyhow::Result<u8> {
    use std::sync::atomic::Ordering;
    use stitch_dvrk::sim_node::SERVO_LATENCIES;
    use stitch_robot::Arm;
    if !(args.seconds.is_finite() && (0.1..=600.0).contains(&args.seconds)) {
        anyhow::bail!("--seconds {}: expected 0.1 to 600", args.seconds);
    }
    if !(1..=10_000).contains(&args.pairs) {
        anyhow::bail!("--pairs {}: expected 1 to 10000", args.pairs);
    }
    let ros = args.ros.options()?;
    let stop = Arc::new(AtomicBool::new(false));
    let node = {
        let stop = Arc::clone(&stop);
        std::thread::spawn(move || {
            let options = SimNodeOptions {
                ros,
                ..SimNodeOptions::default()
            };
            stitch_dvrk::sim_node::serve(&options, &stop, &mut |_| {})
        })
    };
    let dvrk = Ros2Dvrk::connect(&ros, &DvrkConfig::default())
        .context("cannot connect to the in-process sim-node")?;
    let arm = dvrk.arm(0).ok_or_else(|| anyhow::anyhow!("no arm 0"))?;
    let start = arm.measured_cp()?;
    let mut rows = Vec::new();
    for rate_hz in [100.0, 1000.0] {
        SERVO_LATENCIES
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clear();
        let period = Duration::from_secs_f64(1.0 / rate_hz);
        let n = (args.seconds * rate_hz).round() as usize;
        let t0 = std::time::Instant::now();
        for k in 0..n {
            // A 1 mm circle, once over the stream.
            let a = std::f64::consts::TAU * k as f64 / n as f64;
            let mut goal = start;
            goal.translation.vector +=
                stitch_robot::Vector::new(a.cos() - 1.0, a.sin(), 0.0) * 1e-3;
            arm.servo_cp(&goal)?;
            let next = t0 + period * (k as u32 + 1);
            if let Some(wait) = next.checked_duration_since(std::time::Instant::now()) {
                std::thread::sleep(wait);
            }
        }
        std::thread::sleep(Duration::from_millis(300));
        let mut l = SERVO_LATENCIES
            .lock()
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .clone();
        l.sort_by(f64::total_cmp);
        let at = |q: f64| percentile(&l, q) * 1e6;
        rows.push(StreamStats {
            rate_hz,
            sent: n,
            received: l.len(),
            median_us: at(0.5),
            p99_us: at(0.99),
            max_us: at(1.0),
        });
    }
    let pairs = bench_pairs(&ros, args.pairs);
    stop.store(true, Ordering::SeqCst);
    drop(arm);
    drop(dvrk);
    let _ = node.join();
    let (in_process, over_ros2) = pairs?;
    if args.json {
        println!(
            "{}",
            serde_json::to_string_pretty(&serde_json::json!({
                "servo_cp": rows,
                "stereo_pair": { "in_process": in_process, "over_ros2": over_ros2 },
            }))?
        );
    } else {
        println!(
            "servo_cp over ROS 2 (DDS on loopback, reliable, keep last 10), ROS_DOMAIN_ID {}:",
            ros.domain_id
        );
        println!("  rate      sent  received   median      p99      max");
        for r in &rows {
            println!(
                "  {:>5} Hz {:>6} {:>8} {:>8.0} µs {:>6.0} µs {:>6.0} µs",
                r.rate_hz, r.sent, r.received, r.median_us, r.p99_us, r.max_us
            );
        }
        if let [base, fast] = &rows[..] {
            println!(
                "  1 kHz / 100 Hz: median {:.2}×, p99 {:.2}×",
                fast.median_us / base.median_us,
                fast.p99_us / base.p99_us
            );
        }
        println!(
            "stereo pair capture, 1280×960 rgb8 ×2 (over ROS 2: trigger, render, DDS, convert):"
        );
        println!("  where         pairs   median      p99      max");
        for (name, p) in [("in process", &in_process), ("over ROS 2", &over_ros2)] {
            println!(
                "  {name:<12} {:>6} {:>6.1} ms {:>5.1} ms {:>5.1} ms",
                p.pairs, p.median_ms, p.p99_ms, p.max_ms
            );
        }
        println!(
            "  over ROS 2 / in process: median {:.2}×, p99 {:.2}×",
            over_ros2.median_ms / in_process.median_ms,
            over_ros2.p99_ms / in_process.p99_ms
        );
    }
    Ok(crate::exit::OK)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The settings file shown in docs/dvrk.md, its commented hand-eye line included.
    fn documented_settings() -> String {
        let doc = include_str!("../../docs/dvrk.md");
        let block = doc
            .split("### Settings: `--dvrk-config FILE`")
            .nth(1)
            .and_then(|rest| rest.split("```toml\n").nth(1))
            .and_then(|rest| rest.split("```").next())
            .expect("docs/dvrk.md shows a settings file");
        block.replace("# camera_to_robot", "camera_to_robot")
    }

    #[test]
    fn the_documented_settings_file_is_valid_and_says_the_defaults() {
        let path = std::env::temp_dir().join(format!("dvrk-doc-{}.toml", std::process::id()));
        std::fs::write(&path, documented_settings()).expect("write");
        let read = read_dvrk_config(Some(&path)).expect("the documented file is valid");
        let _ = std::fs::remove_file(&path);
        let d = DvrkConfig::default();
        let hand_eye = read.camera.camera_to_robot.expect("the hand-eye line");
        let pose = hand_eye.pose().expect("a pose");
        // 180° about x: the camera's optical axis (z) points down.
        let z = pose.rotation * stitch_robot::Vector::z();
        assert!((z - -stitch_robot::Vector::z()).norm() < 1e-12, "{z}");
        assert_eq!(
            stitch_dvrk::camera::CameraSettings {
                camera_to_robot: None,
                ..read.camera.clone()
            },
            d.camera,
            "the documented camera settings are the defaults"
        );
        for (name, doc, default) in [
            (
                "connect_timeout_s",
                read.connect_timeout_s,
                d.connect_timeout_s,
            ),
            ("stale_after_s", read.stale_after_s, d.stale_after_s),
            ("move_timeout_s", read.move_timeout_s, d.move_timeout_s),
            ("speed_ratio", read.speed_ratio, d.speed_ratio),
            (
                "rotation_tolerance_rad",
                read.rotation_tolerance_rad,
                d.rotation_tolerance_rad,
            ),
            (
                "jaw_tolerance_rad",
                read.jaw_tolerance_rad,
                d.jaw_tolerance_rad,
            ),
        ] {
            assert!(
                (doc - default).abs() < 1e-4,
                "{name}: documented {doc}, default {default}"
            );
        }
        assert_eq!(read.arms, d.arms);
    }
}
