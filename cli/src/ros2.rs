//! `stitch run --robot ros2` and `stitch sim-node`: missions over the dVRK's CRTK topics on
//! ROS 2, against a real dVRK or the mock served by `stitch sim-node`.

use anyhow::Context;
use std::path::PathBuf;
use std::sync::Arc;
use std::sync::atomic::AtomicBool;
use std::time::Duration;
use stitch_dvrk::arm::{DvrkConfig, Ros2Dvrk};
use stitch_dvrk::oracle::{Answer, Call, Oracle};
use stitch_dvrk::ros2::Ros2Options;
use stitch_dvrk::sim_node::{SimNodeOptions, WireFault};
use stitch_engine::{Loaded, Report, Runner};
use stitch_perception::{NeedleEstimate, NeedleEstimator, PerceptionError};
use stitch_primitives::{
    FailureKind, Observer, PassObservation, Rig, RobotPrimitives, mock_layout,
};
use stitch_robot::{WallClock, WoundPoint};
use stitch_sim::{SceneConfig, SensingConfig, Streams, Subsystem};

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
    /// drop-command@N. Repeatable.
    #[arg(long = "wire-fault", value_name = "KIND@N")]
    pub wire_faults: Vec<WireFault>,
}

/// Serve the mock until killed.
pub fn sim_node(args: SimNodeArgs) -> anyhow::Result<u8> {
    let config = crate::read_mock_config(args.mock_config.as_deref())?;
    let options = SimNodeOptions {
        ros: args.ros.options()?,
        seed: args.seed,
        scene: config.scene,
        sensing: config.sensing,
        time_scale: args.time_scale,
        rate_hz: args.rate_hz,
        faults: args.wire_faults,
        ..SimNodeOptions::default()
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
            _ => PassObservation {
                entry_error_m: None,
                exit_error_m: None,
                protrusion_m: 0.0,
                passed: false,
            },
        }
    }

    fn problem(&mut self) -> Option<FailureKind> {
        if let Some(message) = self.lost.take() {
            return Some(FailureKind::ArmFault { message });
        }
        match self.ask(Call::Problem) {
            Some(Answer::Problem(p)) => p,
            _ => self
                .lost
                .take()
                .map(|message| FailureKind::ArmFault { message }),
        }
    }

    fn needle_in_tissue(&mut self) -> bool {
        matches!(self.ask(Call::NeedleInTissue), Some(Answer::Bool(true)))
    }

    fn cinched(&mut self, beta_m: f64) {
        let _ = self.ask(Call::Cinched { beta_m });
    }

    fn thread_left_m(&mut self) -> f64 {
        match self.ask(Call::ThreadLeft) {
            Some(Answer::Meters(m)) => m,
            _ => 0.0,
        }
    }
}

/// Run `loaded` over ROS 2: connect to the dVRK's arms, and to the simulator's side channel
/// for the estimator, the observer and the supervisor's recovery motion.
pub fn run_ros2(
    loaded: &Loaded,
    scene: &SceneConfig,
    sensing: SensingConfig,
    seed: u64,
    ros: &Ros2Options,
    config: &DvrkConfig,
) -> anyhow::Result<Report> {
    let timeout = Duration::from_secs_f64(config.connect_timeout_s);
    let oracle = Oracle::connect(ros, timeout).map_err(|e| {
        anyhow::anyhow!(
            "{e}\nThe noise-model estimator, the scene's scoring and the supervisor's recovery \
             come from `stitch sim-node` over ROS 2; a real dVRK has none of them (the stereo \
             camera over ROS 2 is not built yet), so --robot ros2 runs against the sim-node only."
        )
    })?;
    let oracle = Arc::new(oracle);
    let dvrk = Arc::new(Ros2Dvrk::connect(ros, config).context("cannot connect to the dVRK")?);
    oracle
        .call(Call::Reset {
            seed,
            scene: Box::new(scene.clone()),
            sensing,
        })
        .map_err(anyhow::Error::msg)?;
    dvrk.wait_fresh(timeout)?;
    let arm = |i: usize| {
        dvrk.arm(i)
            .ok_or_else(|| anyhow::anyhow!("the dVRK configuration names no arm {i}"))
    };
    let jaw = |i: usize| {
        dvrk.jaw(i)
            .ok_or_else(|| anyhow::anyhow!("the dVRK configuration names no arm {i}"))
    };
    let streams = Streams::new(seed);
    let rig = Rig {
        right: Arc::new(arm(0)?),
        left: Arc::new(arm(1)?),
        right_jaw: Arc::new(jaw(0)?),
        left_jaw: Arc::new(jaw(1)?),
        estimator: Box::new(RemoteEstimator(Arc::clone(&oracle))),
        observer: Some(Box::new(RemoteObserver {
            oracle: Arc::clone(&oracle),
            lost: None,
        })),
        needle: scene.needle,
        layout: mock_layout(scene, &sensing),
        rng: streams.rng(Subsystem::Primitives),
    };
    let mut primitives = RobotPrimitives::new(rig);
    let plan = Arc::new(loaded.plan.clone());
    let (o, d) = (Arc::clone(&oracle), Arc::clone(&dvrk));
    let mut supervisor = crate::mock::MockSupervisor::with(
        Box::new(move |needs| {
            o.call(Call::Recover { needs })?;
            d.wait_fresh(timeout).map_err(|e| e.to_string())
        }),
        Arc::clone(&plan),
    );
    Ok(Runner::new(
        plan,
        &mut primitives,
        &mut supervisor,
        Arc::new(WallClock::new()),
        Some(seed),
    )
    .run())
}
