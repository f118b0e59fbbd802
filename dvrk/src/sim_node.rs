//! `stitch sim-node`: the mock dVRK served over the dVRK's own CRTK topics on ROS 2, so a
//! mission runs over real DDS on one machine exactly as it would against a dVRK console.
//!
//! Per arm (`/PSM1`, `/PSM2`) it publishes `measured_cp`, `setpoint_cp` and `jaw/measured_js`
//! at a fixed rate (100 Hz by default, and at once after every motion), `operating_state`
//! (latched, on every change) and `error`; it takes `move_cp`, `servo_cp`, `jaw/move_jp`,
//! `hold`, `state_command` and `trajectory_j/set_ratio`. Arms start DISABLED and unhomed, as
//! a console does. With a stereo camera (a client's reset asks for one), it publishes
//! `camera_info` for both sides 10 times a second, and a rendered pair (two `rgb8`
//! `sensor_msgs/Image`s and their `camera_info`, one stamp) on each capture trigger of the
//! side channel, as the in-process mock renders one per capture. A motion runs in the mock at once and is reported busy for its simulated
//! duration divided by the time scale (so missions run faster than real time), then idle.
//! Beside the CRTK topics it answers the simulator's side channel ([`crate::oracle`]).
//!
//! Wire faults ([`WireFault`]) make it misbehave as a dVRK can: publish an error and go to
//! FAULT, stay busy, stamp its measurements stale or zero, drop a command, or let the camera
//! fall silent.

use crate::camera::{self, CameraSettings};
use crate::msg::{
    self, CameraInfo, Empty, Float64, Image, JointState, OperatingState, PoseStamped, StringMsg,
};
use crate::oracle::{self, Answer, Call, Reply, Request, WireEstimate, WirePass};
use crate::ros2::{Bus, Ros2Options, Topic, latched_qos, now_stamp, stream_qos, types};
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender};
use std::sync::{Arc, Mutex, PoisonError};
use std::time::{Duration, Instant};
use stitch_perception::NeedleEstimator;
use stitch_primitives::ModelEstimator;
use stitch_primitives::{MockObserver, Observer, PIPELINE_FRAME_TIME_S};
use stitch_robot::{Arm, Jaw, Pose, SimClock, StereoCalibration, StereoCamera};
use stitch_sim::{
    CameraConfig, MockCamera, MockDvrk, SceneConfig, SensingConfig, Side, StereoRenderer, Streams,
};

/// A way for the sim-node to misbehave, at the n-th motion command (`move_cp` or
/// `jaw/move_jp`, both arms counted together, 1-based).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct WireFault {
    /// What goes wrong.
    pub kind: WireFaultKind,
    /// At which motion command.
    pub nth: u32,
}

/// What goes wrong over the wire.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum WireFaultKind {
    /// Publish an `error` and go to FAULT instead of moving.
    ArmError,
    /// Report busy and never clear it.
    BusyStuck,
    /// From then on, stamp measurements 10 s in the past.
    StaleStamps,
    /// From then on, stamp measurements zero (CRTK's "invalid").
    ZeroStamps,
    /// Ignore the command, as if it were lost (a resend gets through).
    DropCommand,
    /// From then on, ignore every motion command, resends too (a dVRK that stopped
    /// listening).
    Deaf,
    /// From then on, the stereo camera publishes nothing.
    CameraSilent,
    /// From then on, the side channel answers nothing (the CRTK topics go on).
    OracleSilent,
}

impl std::str::FromStr for WireFault {
    type Err = String;
    /// `KIND@N`, e.g. `arm-error@5`.
    fn from_str(s: &str) -> Result<Self, String> {
        let (kind, nth) = s
            .split_once('@')
            .ok_or_else(|| format!("wire fault {s:?}: expected KIND@N, e.g. arm-error@5"))?;
        let kind = match kind {
            "arm-error" => WireFaultKind::ArmError,
            "busy-stuck" => WireFaultKind::BusyStuck,
            "stale-stamps" => WireFaultKind::StaleStamps,
            "zero-stamps" => WireFaultKind::ZeroStamps,
            "drop-command" => WireFaultKind::DropCommand,
            "deaf" => WireFaultKind::Deaf,
            "camera-silent" => WireFaultKind::CameraSilent,
            "oracle-silent" => WireFaultKind::OracleSilent,
            other => {
                return Err(format!(
                    "wire fault {other:?}: expected arm-error, busy-stuck, stale-stamps, \
                     zero-stamps, drop-command, deaf, camera-silent or oracle-silent"
                ));
            }
        };
        let nth = nth
            .parse::<u32>()
            .ok()
            .filter(|n| *n >= 1)
            .ok_or_else(|| format!("wire fault {s:?}: N counts motion commands from 1"))?;
        Ok(Self { kind, nth })
    }
}

/// How the sim-node runs.
#[derive(Clone, Debug)]
pub struct SimNodeOptions {
    /// Domain.
    pub ros: Ros2Options,
    /// The first world's seed (each client's reset brings its own).
    pub seed: u64,
    /// The first world's scene.
    pub scene: SceneConfig,
    /// The first world's estimator noise.
    pub sensing: SensingConfig,
    /// Simulated seconds per wall second while a motion is reported busy (1: real time).
    pub time_scale: f64,
    /// State publishing rate, Hz.
    pub rate_hz: f64,
    /// Misbehaviour.
    pub faults: Vec<WireFault>,
    /// The arms' namespaces: right, left.
    pub arms: [String; 2],
    /// The first world's stereo camera (none until a client resets with one).
    pub camera: Option<CameraConfig>,
    /// Stream the camera at this rate, Hz, as a camera driver does (none: a pair per
    /// trigger only). Each frame advances the world's clock and draws its noise, so a run
    /// against a streaming camera is not the in-process mock's twin.
    pub camera_hz: Option<f64>,
    /// The camera's topics (the client's defaults).
    pub camera_topics: CameraSettings,
}

impl Default for SimNodeOptions {
    fn default() -> Self {
        Self {
            ros: Ros2Options { domain_id: 0 },
            seed: 1,
            scene: SceneConfig::default(),
            sensing: SensingConfig::default(),
            time_scale: 100.0,
            rate_hz: 100.0,
            faults: Vec::new(),
            arms: ["PSM1".into(), "PSM2".into()],
            camera: None,
            camera_hz: None,
            camera_topics: CameraSettings::default(),
        }
    }
}

/// A command from the wire.
#[derive(Debug)]
enum Cmd {
    Move(usize, PoseStamped),
    Servo(usize, PoseStamped),
    Jaw(usize, JointState),
    Hold(usize),
    State(usize, String),
    Ratio(usize, f64),
    Oracle(Request),
    Unreadable(String),
}

/// How measurements are stamped.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Stamps {
    Now,
    Stale,
    Zero,
}

#[derive(Debug)]
struct Snapshot {
    poses: [Pose; 2],
    setpoints: [Pose; 2],
    jaws: [f64; 2],
    stamps: Stamps,
}

struct ArmOut {
    measured_cp: Topic<PoseStamped>,
    setpoint_cp: Topic<PoseStamped>,
    jaw: Topic<JointState>,
    state: Topic<OperatingState>,
    error: Topic<StringMsg>,
    /// `trajectory_j/ratio`, latched as the console latches it.
    ratio: Topic<Float64>,
}

struct CameraOut {
    images: [Topic<Image>; 2],
    infos: [Topic<CameraInfo>; 2],
    /// The current camera's calibration, published as `camera_info` with every pair and
    /// 10 times a second.
    calibration: Mutex<Option<StereoCalibration>>,
}

/// The optical frames the pair is stamped in.
const FRAMES: [&str; 2] = ["stitch_stereo_left_optical", "stitch_stereo_right_optical"];

impl CameraOut {
    fn publish_infos(&self, stamp: msg::Time, failures: &Failures) {
        let c = self
            .calibration
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone();
        if let Some(c) = c {
            for (i, topic) in self.infos.iter().enumerate() {
                failures.note(topic.publish(camera::camera_info_msg(&c, i == 1, stamp, FRAMES[i])));
            }
        }
    }
}

struct Out {
    arms: Vec<ArmOut>,
    reply: Topic<StringMsg>,
    snapshot: Mutex<Snapshot>,
    camera: CameraOut,
    failures: Failures,
}

/// What the node could not publish (DDS refused a write), kept until the main loop logs it:
/// the 100 Hz stream would flood the log with one line per failure.
#[derive(Default)]
struct Failures(Mutex<Option<(u64, String)>>);

impl Failures {
    fn note(&self, sent: Result<(), String>) {
        if let Err(e) = sent {
            let mut f = self.0.lock().unwrap_or_else(PoisonError::into_inner);
            let n = f.as_ref().map_or(0, |(n, _)| *n);
            *f = Some((n + 1, e));
        }
    }

    /// Log what failed since the last call, if anything.
    fn report(&self, log: &mut dyn FnMut(&str)) {
        let taken = self.0.lock().unwrap_or_else(PoisonError::into_inner).take();
        if let Some((n, e)) = taken {
            log(&format!(
                "sim-node: {n} message{} could not be published; the last: {e}",
                if n == 1 { "" } else { "s" }
            ));
        }
    }
}

impl Out {
    /// Publish the snapshot, stamped now. The snapshot stays locked until it is written: the
    /// state thread's 100 Hz stream and the main loop's publication after a motion must not
    /// interleave, or a copy of the pose from before the motion, stamped and written after
    /// the motion's own, reaches the client last, and a `measured_cp` read just then sees
    /// the arm where it was. (Under load, ROS 2 runs parted from their in-process twins at a
    /// cinch, which pulls from where `measured_cp` says the arm is: 1 mission in about 20
    /// before, none of 105 after, 2026-12-06.)
    fn publish_measurements(&self) {
        let s = self.snapshot.lock().unwrap_or_else(PoisonError::into_inner);
        let (snap, stamps) = ((s.poses, s.setpoints, s.jaws), s.stamps);
        let t = stamp(stamps);
        for (i, a) in self.arms.iter().enumerate() {
            let f = &self.failures;
            f.note(a.measured_cp.publish(crate::pose_to_msg(&snap.0[i], t, "")));
            f.note(a.setpoint_cp.publish(crate::pose_to_msg(&snap.1[i], t, "")));
            f.note(a.jaw.publish(JointState {
                header: msg::Header {
                    stamp: t,
                    frame_id: String::new(),
                },
                name: vec!["jaw".into()],
                position: vec![snap.2[i]],
                velocity: vec![],
                effort: vec![],
            }));
        }
    }
}

fn stamp(mode: Stamps) -> msg::Time {
    match mode {
        Stamps::Now => now_stamp(),
        Stamps::Stale => {
            let mut t = now_stamp();
            t.sec -= 10;
            t
        }
        Stamps::Zero => msg::Time::default(),
    }
}

/// One arm's operating state as the sim-node reports it.
#[derive(Clone, Debug, PartialEq)]
struct ArmState {
    state: &'static str,
    homed: bool,
    busy: bool,
}

/// The world and what answers for it.
struct World {
    world: MockDvrk,
    estimator: ModelEstimator,
    observer: MockObserver,
    /// The stereo camera, as the in-process mock builds it for `--perception pipeline`.
    camera: Option<MockCamera>,
    holds: [u64; 2],
}

impl World {
    fn new(
        seed: u64,
        scene: &SceneConfig,
        sensing: SensingConfig,
        camera: Option<&CameraConfig>,
    ) -> Result<Self, String> {
        let streams = Streams::new(seed);
        let world = MockDvrk::new(scene, streams, SimClock::new()).map_err(|e| e.to_string())?;
        let estimator =
            ModelEstimator::new(world.clone(), sensing, streams).map_err(|e| e.to_string())?;
        let camera = match camera {
            Some(c) => {
                let renderer = StereoRenderer::new(c.clone(), world.phantom_view())
                    .map_err(|e| e.to_string())?;
                Some(MockCamera::new(
                    world.clone(),
                    renderer,
                    streams,
                    Duration::from_secs_f64(PIPELINE_FRAME_TIME_S),
                ))
            }
            None => None,
        };
        Ok(Self {
            observer: MockObserver::new(world.clone()),
            estimator,
            camera,
            world,
            holds: [0; 2],
        })
    }

    fn calibration(&self) -> Option<StereoCalibration> {
        self.camera
            .as_ref()
            .map(|c| StereoCamera::calibration(c).clone())
    }
}

const SIDES: [Side; 2] = [Side::Right, Side::Left];

/// Serve until `stop` is set. `log` gets one line per event worth telling (ready, resets,
/// motions, holds, faults), for people and for tests watching the process.
pub fn serve(
    options: &SimNodeOptions,
    stop: &AtomicBool,
    log: &mut dyn FnMut(&str),
) -> Result<(), String> {
    if !(options.time_scale.is_finite() && options.time_scale >= 1.0) {
        return Err(format!(
            "time scale {}: expected at least 1 (simulated seconds per wall second)",
            options.time_scale
        ));
    }
    if !(options.rate_hz.is_finite() && (1.0..=1000.0).contains(&options.rate_hz)) {
        return Err(format!(
            "rate {} Hz: expected 1 to 1000 Hz",
            options.rate_hz
        ));
    }
    if let Some(hz) = options.camera_hz
        && !(hz.is_finite() && (0.1..=60.0).contains(&hz))
    {
        return Err(format!("camera rate {hz} Hz: expected 0.1 to 60 Hz"));
    }
    let mut world = World::new(
        options.seed,
        &options.scene,
        options.sensing,
        options.camera.as_ref(),
    )?;
    let (tx, rx) = std::sync::mpsc::channel::<Cmd>();
    let mut link = Link::open(options, &world, Stamps::Now, &tx)?;
    let mut node = Node {
        out: Arc::clone(&link.out),
        states: vec![
            ArmState {
                state: "DISABLED",
                homed: false,
                busy: false,
            };
            2
        ],
        ratios: [1.0; 2],
        motions: 0,
        stuck: false,
        deaf: false,
        camera_silent: false,
        oracle_silent: false,
        last_pair: None,
        options: options.clone(),
        pending: VecDeque::new(),
    };
    node.announce();
    if let Some(c) = world.calibration() {
        let h = camera::HandEye::from_pose(&c.camera_to_robot);
        log(&format!(
            "sim-node: stereo camera on {} and {}{}; its hand-eye, for [camera]: \
             camera_to_robot = {{ translation_m = {:?}, rotation_xyzw = {:?} }}",
            options.camera_topics.left_image,
            options.camera_topics.right_image,
            options
                .camera_hz
                .map(|hz| format!(" at {hz} Hz"))
                .unwrap_or_default(),
            h.translation_m,
            h.rotation_xyzw
        ));
    }
    log(&format!(
        "sim-node: ready on ROS_DOMAIN_ID {} (ROS 2 {}), arms /{} and /{}, seed {}, time scale {}×",
        options.ros.domain_id,
        crate::ros2::DISTRIBUTION,
        options.arms[0],
        options.arms[1],
        options.seed,
        options.time_scale
    ));
    let frame_period = options
        .camera_hz
        .map(|hz| Duration::from_secs_f64(1.0 / hz));
    let mut next_frame = Instant::now();
    let (mut looked, mut idle_since) = (Instant::now(), None::<Instant>);
    while !stop.load(Ordering::SeqCst) {
        link.out.failures.report(log);
        // Every client gone for a while: a fresh participant (see `Link`).
        if looked.elapsed() >= LOOK_FOR_CLIENTS {
            looked = Instant::now();
            // A discovery event (a participant found, an endpoint lost) is a client coming or
            // going: never recycle then. A client found but not yet counted could already
            // have matched this participant's endpoints; what it sends to the old participant
            // is lost and sent again (confirmed commands are resent, pings repeated).
            let stirring = link.bus.discovery_events() > 0;
            if link.bus.remote_endpoints() > 0 {
                link.served = true;
                idle_since = None;
            } else if stirring {
                idle_since = None;
            } else if link.served {
                let since = *idle_since.get_or_insert(looked);
                if since.elapsed() >= RECYCLE_AFTER_IDLE {
                    idle_since = None;
                    let stamps = link
                        .out
                        .snapshot
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .stamps;
                    // Nothing to deliver: no linger, so a client arriving now finds the
                    // old participant gone at once rather than matching it.
                    link.bus.set_linger(Duration::ZERO);
                    link.close(log);
                    link = Link::open(options, &world, stamps, &tx)?;
                    node.out = Arc::clone(&link.out);
                    node.announce();
                    log("sim-node: every client has left: a fresh DDS participant");
                }
            }
        }
        // A streaming camera: a frame when one is due, between commands.
        let mut idle = LOOK_FOR_CLIENTS;
        if let Some(period) = frame_period
            && world.camera.is_some()
        {
            let now = Instant::now();
            if now >= next_frame {
                if let Err(e) = node.capture_pair(&world) {
                    log(&format!("sim-node: camera: {e}"));
                }
                next_frame = (next_frame + period).max(now);
            }
            idle = idle.min(next_frame.saturating_duration_since(Instant::now()));
        }
        let cmd = match node.pending.pop_front() {
            Some(c) => c,
            None => match rx.recv_timeout(idle) {
                Ok(c) => c,
                Err(RecvTimeoutError::Timeout) => continue,
                Err(RecvTimeoutError::Disconnected) => break,
            },
        };
        node.handle(cmd, &mut world, &rx, log);
    }
    link.close(log);
    Ok(())
}

/// How often the main loop asks DDS whether any client is there.
const LOOK_FOR_CLIENTS: Duration = Duration::from_millis(20);

/// How long every client must have been gone (no endpoint of another participant, no
/// discovery event) before the node takes a fresh participant.
const RECYCLE_AFTER_IDLE: Duration = Duration::from_millis(60);

/// The node's side of DDS: its participant (the bus), its topics and the state stream's
/// thread, over a world that outlives it.
///
/// Why it is rebuilt once every client has left: a RustDDS 0.15 participant keeps something
/// of every participant it ever met, after that one has left: an entry per remote endpoint in
/// its discovery database's topic table, which is never removed, and thousands of discovery
/// samples in its built-in readers' caches. A node that serves mission after mission grew by
/// about 40–90 kB per client (`stitch run --robot ros2` brings two participants) and never
/// stopped. A fresh participant drops all of it; the world, the arms' states and the wire
/// faults stay with the node.
struct Link {
    bus: Bus,
    out: Arc<Out>,
    publishing: Arc<AtomicBool>,
    publisher: Option<std::thread::JoinHandle<()>>,
    /// Some client's endpoints were seen on this participant.
    served: bool,
}

impl Link {
    fn open(
        options: &SimNodeOptions,
        world: &World,
        stamps: Stamps,
        tx: &Sender<Cmd>,
    ) -> Result<Self, String> {
        let mut bus = Bus::new(&options.ros, "sim_node")?;
        bus.watch_discovery();
        let mut arms = Vec::new();
        for (i, name) in options.arms.iter().enumerate() {
            arms.push(arm_topics(&mut bus, name, i, tx)?);
        }
        let reply =
            bus.publisher::<StringMsg>(oracle::REPLY_TOPIC, types::STRING, &stream_qos())?;
        let otx = tx.clone();
        bus.subscribe::<StringMsg, _>(
            oracle::REQUEST_TOPIC,
            types::STRING,
            &stream_qos(),
            move |r| {
                let cmd = match r.and_then(|m| {
                    serde_json::from_str::<Request>(&m.data)
                        .map_err(|e| format!("{}: bad request: {e}", oracle::REQUEST_TOPIC))
                }) {
                    Ok(req) => Cmd::Oracle(req),
                    Err(e) => Cmd::Unreadable(e),
                };
                // Fails only once the node has stopped listening.
                let _ = otx.send(cmd);
            },
        )?;
        let camera = camera_topics(&mut bus, &options.camera_topics, world.calibration())?;
        let out = Arc::new(Out {
            arms,
            reply,
            snapshot: Mutex::new(snapshot(&world.world, stamps)),
            camera,
            failures: Failures::default(),
        });
        // The state stream, at its rate, on its own thread.
        let publishing = Arc::new(AtomicBool::new(true));
        let (p_out, p_on, period) = (
            Arc::clone(&out),
            Arc::clone(&publishing),
            Duration::from_secs_f64(1.0 / options.rate_hz),
        );
        let publisher = std::thread::Builder::new()
            .name("sim-node-state".into())
            .spawn(move || {
                let mut next = Instant::now();
                let mut info_at = next;
                while p_on.load(Ordering::SeqCst) {
                    p_out.publish_measurements();
                    if next >= info_at {
                        p_out.camera.publish_infos(now_stamp(), &p_out.failures);
                        info_at = next + Duration::from_millis(100);
                    }
                    next += period;
                    let now = Instant::now();
                    if next > now {
                        std::thread::sleep(next - now);
                    } else {
                        next = now;
                    }
                }
            })
            .map_err(|e| format!("cannot start the state stream's thread: {e}"))?;
        Ok(Self {
            bus,
            out,
            publishing,
            publisher: Some(publisher),
            served: false,
        })
    }

    /// Stop the state stream, say what could not be published, leave DDS.
    fn close(mut self, log: &mut dyn FnMut(&str)) {
        self.publishing.store(false, Ordering::SeqCst);
        if let Some(p) = self.publisher.take()
            && p.join().is_err()
        {
            log("sim-node: the state stream's thread panicked");
        }
        self.out.failures.report(log);
    }
}

fn snapshot(world: &MockDvrk, stamps: Stamps) -> Snapshot {
    let pose = |s: Side| {
        world
            .arm(s)
            .setpoint_cp()
            .unwrap_or_else(|_| Pose::identity())
    };
    let jaw = |s: Side| world.jaw(s).measured_jp().unwrap_or(0.0);
    Snapshot {
        // The mock's encoders cannot see joint offsets: measured is the setpoint.
        poses: [pose(Side::Right), pose(Side::Left)],
        setpoints: [pose(Side::Right), pose(Side::Left)],
        jaws: [jaw(Side::Right), jaw(Side::Left)],
        stamps,
    }
}

fn camera_topics(
    bus: &mut Bus,
    topics: &CameraSettings,
    calibration: Option<StereoCalibration>,
) -> Result<CameraOut, String> {
    let q = camera::publisher_qos();
    Ok(CameraOut {
        images: [
            bus.publisher(&topics.left_image, types::IMAGE, &q)?,
            bus.publisher(&topics.right_image, types::IMAGE, &q)?,
        ],
        infos: [
            bus.publisher(&topics.left_info, types::CAMERA_INFO, &q)?,
            bus.publisher(&topics.right_info, types::CAMERA_INFO, &q)?,
        ],
        calibration: Mutex::new(calibration),
    })
}

/// The QoS of the 100 Hz state streams the sim-node publishes (`measured_cp`, `setpoint_cp`,
/// `jaw/measured_js`): [`stream_qos`] but transient-local, which every client's volatile
/// reader still matches (a late reader is handed the last few samples, stamped as they were).
///
/// Why not volatile, as the dVRK's are: a volatile RustDDS 0.15 writer that matches a new
/// reader marks every sequence number it ever wrote as a gap for that reader, in a set, and
/// clones that set while it repairs. The set grows with the node's uptime (100 samples a
/// second per stream), so each new client made the node's heap peak higher: over 100 missions
/// back to back its resident memory grew 175 kB a mission with volatile streams, 82 kB with
/// these (release build, 2026-12-03). A transient-local writer has nothing to gap.
fn state_stream_qos() -> ros2_client::QosProfile {
    stream_qos().durability(ros2_client::qos::Durability::TransientLocal)
}

fn arm_topics(bus: &mut Bus, name: &str, i: usize, tx: &Sender<Cmd>) -> Result<ArmOut, String> {
    let t = |topic: &str| format!("/{name}/{topic}");
    fn forward<M: Send + 'static>(
        tx: &Sender<Cmd>,
        make: impl Fn(M) -> Cmd + Send + 'static,
    ) -> impl FnMut(Result<M, String>) + Send + 'static {
        let tx = tx.clone();
        move |r| {
            let _ = tx.send(match r {
                Ok(m) => make(m),
                Err(e) => Cmd::Unreadable(e),
            });
        }
    }
    let q = stream_qos();
    bus.subscribe(
        &t("move_cp"),
        types::POSE_STAMPED,
        &q,
        forward(tx, move |m| Cmd::Move(i, m)),
    )?;
    bus.subscribe(
        &t("servo_cp"),
        types::POSE_STAMPED,
        &q,
        forward(tx, move |m| Cmd::Servo(i, m)),
    )?;
    bus.subscribe(
        &t("jaw/move_jp"),
        types::JOINT_STATE,
        &q,
        forward(tx, move |m| Cmd::Jaw(i, m)),
    )?;
    bus.subscribe(
        &t("hold"),
        types::EMPTY,
        &q,
        forward(tx, move |_: Empty| Cmd::Hold(i)),
    )?;
    bus.subscribe(
        &t("state_command"),
        types::STRING_STAMPED,
        &q,
        forward(tx, move |m: msg::StringStamped| Cmd::State(i, m.string)),
    )?;
    bus.subscribe(
        &t("trajectory_j/set_ratio"),
        types::FLOAT64,
        &q,
        forward(tx, move |m: Float64| Cmd::Ratio(i, m.data)),
    )?;
    let s = state_stream_qos();
    Ok(ArmOut {
        measured_cp: bus.publisher(&t("measured_cp"), types::POSE_STAMPED, &s)?,
        setpoint_cp: bus.publisher(&t("setpoint_cp"), types::POSE_STAMPED, &s)?,
        jaw: bus.publisher(&t("jaw/measured_js"), types::JOINT_STATE, &s)?,
        state: bus.publisher(
            &t("operating_state"),
            types::OPERATING_STATE,
            &latched_qos(),
        )?,
        error: bus.publisher(&t("error"), types::STRING, &q)?,
        ratio: bus.publisher(&t("trajectory_j/ratio"), types::FLOAT64, &latched_qos())?,
    })
}

struct Node {
    out: Arc<Out>,
    states: Vec<ArmState>,
    /// Each arm's trajectory speed ratio, as last commanded (latched on `trajectory_j/ratio`).
    ratios: [f64; 2],
    motions: u32,
    stuck: bool,
    /// A `deaf` fault fired: motion commands are ignored.
    deaf: bool,
    /// A `camera-silent` fault fired.
    camera_silent: bool,
    /// An `oracle-silent` fault fired.
    oracle_silent: bool,
    /// The last pair published, for a resend.
    last_pair: Option<(msg::Time, [Image; 2])>,
    options: SimNodeOptions,
    /// Commands that arrived while a motion was busy, in order.
    pending: VecDeque<Cmd>,
}

enum Motion {
    Pose(Pose),
    Jaw(f64),
}

impl Node {
    /// Publish what the dVRK latches (each arm's operating state and speed ratio): at the
    /// start, and on a fresh participant.
    fn announce(&self) {
        for i in 0..2 {
            self.publish_state(i);
            self.out
                .failures
                .note(self.out.arms[i].ratio.publish(Float64 {
                    data: self.ratios[i],
                }));
        }
    }

    fn publish_state(&self, i: usize) {
        let s = &self.states[i];
        self.out
            .failures
            .note(self.out.arms[i].state.publish(OperatingState {
                header: msg::Header {
                    stamp: now_stamp(),
                    frame_id: String::new(),
                },
                state: s.state.into(),
                is_homed: s.homed,
                is_busy: s.busy,
            }));
    }

    fn error(&mut self, i: usize, text: &str, log: &mut dyn FnMut(&str)) {
        let text = format!("{}: {text}", self.options.arms[i]);
        log(&format!("sim-node: error {text}"));
        self.out
            .failures
            .note(self.out.arms[i].error.publish(StringMsg { data: text }));
    }

    fn set_busy(&mut self, i: usize, busy: bool) {
        self.states[i].busy = busy;
        self.publish_state(i);
    }

    /// Stop arm `i` where it is, and count it; `during` names the motion under way.
    fn hold(&self, i: usize, world: &mut World, during: Option<u32>, log: &mut dyn FnMut(&str)) {
        world.holds[i] += 1;
        if let Err(e) = world.world.arm(SIDES[i]).hold() {
            log(&format!(
                "sim-node: the mock could not hold /{}: {e}",
                self.options.arms[i]
            ));
        }
        let during = during.map(|n| format!(" during motion {n}"));
        log(&format!(
            "sim-node: hold /{}{}",
            self.options.arms[i],
            during.unwrap_or_default()
        ));
    }

    /// Wait `d` (wall), ending early on a `hold` of arm `i` (a hold of the other arm is
    /// taken at once too); queue everything else.
    fn dwell(
        &mut self,
        i: usize,
        d: Duration,
        rx: &Receiver<Cmd>,
        world: &mut World,
        log: &mut dyn FnMut(&str),
    ) {
        let end = Instant::now() + d;
        loop {
            let now = Instant::now();
            if now >= end {
                return;
            }
            match rx.recv_timeout(end - now) {
                Ok(Cmd::Hold(j)) => {
                    self.hold(j, world, Some(self.motions), log);
                    if j == i {
                        return;
                    }
                }
                Ok(other) => self.pending.push_back(other),
                Err(_) => return,
            }
        }
    }

    fn update_snapshot(&self, world: &World) {
        let mut s = self
            .out
            .snapshot
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        let stamps = s.stamps;
        *s = snapshot(&world.world, stamps);
    }

    fn refresh(&self, world: &World) {
        self.update_snapshot(world);
        self.out.publish_measurements();
    }

    fn motion(
        &mut self,
        i: usize,
        what: &str,
        motion: Motion,
        world: &mut World,
        rx: &Receiver<Cmd>,
        log: &mut dyn FnMut(&str),
    ) {
        self.motions += 1;
        let n = self.motions;
        log(&format!(
            "sim-node: motion {n} {what} /{}",
            self.options.arms[i]
        ));
        let fault = self
            .options
            .faults
            .iter()
            .find(|f| f.nth == n)
            .map(|f| f.kind);
        match fault {
            Some(WireFaultKind::DropCommand) => {
                log(&format!("sim-node: wire fault: dropped motion {n}"));
                return;
            }
            Some(WireFaultKind::Deaf) => {
                log(&format!(
                    "sim-node: wire fault: motion commands ignored from motion {n}"
                ));
                self.deaf = true;
            }
            Some(WireFaultKind::ArmError) => {
                self.error(
                    i,
                    "sim-node wire fault: joint 3 following error, arm powered off",
                    log,
                );
                self.states[i].state = "FAULT";
                self.publish_state(i);
                return;
            }
            Some(WireFaultKind::BusyStuck) => {
                log(&format!("sim-node: wire fault: motion {n} stays busy"));
                self.stuck = true;
                self.set_busy(i, true);
                return;
            }
            Some(WireFaultKind::CameraSilent) => {
                log(&format!(
                    "sim-node: wire fault: camera silent from motion {n}"
                ));
                self.camera_silent = true;
            }
            Some(WireFaultKind::OracleSilent) => {
                log(&format!(
                    "sim-node: wire fault: side channel silent from motion {n}"
                ));
                self.oracle_silent = true;
            }
            Some(WireFaultKind::StaleStamps) | Some(WireFaultKind::ZeroStamps) => {
                let mode = if fault == Some(WireFaultKind::StaleStamps) {
                    Stamps::Stale
                } else {
                    Stamps::Zero
                };
                log(&format!(
                    "sim-node: wire fault: {mode:?} stamps from motion {n}"
                ));
                self.out
                    .snapshot
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner)
                    .stamps = mode;
            }
            None => {}
        }
        if self.deaf {
            log(&format!("sim-node: deaf: ignored motion {n}"));
            return;
        }
        let st = &self.states[i];
        if st.state != "ENABLED" || !st.homed || self.stuck {
            let why = format!(
                "{what} refused: the arm is {} (homed: {}, busy: {})",
                st.state, st.homed, st.busy
            );
            self.error(i, &why, log);
            return;
        }
        let side = SIDES[i];
        let result = match motion {
            Motion::Pose(p) => world.world.arm(side).move_cp(&p),
            Motion::Jaw(a) => world.world.jaw(side).move_jp(a),
        };
        self.set_busy(i, true);
        match result {
            Err(e) => self.error(i, &e.to_string(), log),
            Ok(handle) => {
                // The motion runs on the world's clock in wall-clock slices of DWELL (scaled
                // by the time scale), at least 2 ms and at most 10 s in all; a hold of this
                // arm stops it where it is, mid-move, as on a dVRK.
                const DWELL: Duration = Duration::from_millis(2);
                let scale = self.options.time_scale;
                let started = Instant::now();
                let held = world.holds[i];
                let mut first = true;
                while (handle.is_busy() || first) && world.holds[i] == held {
                    first = false;
                    let _ = handle.wait(DWELL.mul_f64(scale));
                    if started.elapsed() >= Duration::from_secs(10) {
                        let _ = handle.wait(Duration::MAX);
                    }
                    self.dwell(i, DWELL, rx, world, log);
                }
            }
        }
        // Idle first, then a measurement stamped after it: what the dVRK's 100 Hz stream
        // gives a client that waits for a measurement newer than the idle state.
        self.update_snapshot(world);
        self.set_busy(i, false);
        self.out.publish_measurements();
    }

    fn handle(
        &mut self,
        cmd: Cmd,
        world: &mut World,
        rx: &Receiver<Cmd>,
        log: &mut dyn FnMut(&str),
    ) {
        match cmd {
            Cmd::Move(i, m) => match crate::pose_from_msg(&m) {
                Ok(p) => self.motion(i, "move_cp", Motion::Pose(p), world, rx, log),
                Err(e) => self.error(i, &format!("move_cp refused: {e}"), log),
            },
            Cmd::Jaw(i, m) => match m.position.first() {
                Some(a) if a.is_finite() => {
                    self.motion(i, "jaw/move_jp", Motion::Jaw(*a), world, rx, log);
                }
                _ => self.error(
                    i,
                    &format!("jaw/move_jp refused: position {:?}", m.position),
                    log,
                ),
            },
            Cmd::Servo(i, m) => {
                let latency_s = crate::ros2::stamp_age_s(&m.header.stamp);
                match crate::pose_from_msg(&m) {
                    Ok(p) if self.states[i].state == "ENABLED" && self.states[i].homed => {
                        if let Err(e) = world.world.arm(SIDES[i]).servo_cp(&p) {
                            self.error(i, &e.to_string(), log);
                        }
                        let mut l = SERVO_LATENCIES
                            .lock()
                            .unwrap_or_else(PoisonError::into_inner);
                        // A node streamed to for hours keeps the latest only.
                        if l.len() >= SERVO_LATENCIES_KEPT {
                            l.drain(..SERVO_LATENCIES_KEPT / 2);
                        }
                        l.push(latency_s);
                        drop(l);
                        self.update_snapshot(world);
                    }
                    Ok(_) => {
                        self.error(i, "servo_cp refused: the arm is not enabled and homed", log)
                    }
                    Err(e) => self.error(i, &format!("servo_cp refused: {e}"), log),
                }
            }
            Cmd::Hold(i) => self.hold(i, world, None, log),
            Cmd::State(i, command) => self.state_command(i, &command, log),
            Cmd::Ratio(i, r) => {
                log(&format!(
                    "sim-node: /{} trajectory speed ratio {r}",
                    self.options.arms[i]
                ));
                self.ratios[i] = r;
                self.out
                    .failures
                    .note(self.out.arms[i].ratio.publish(Float64 { data: r }));
            }
            Cmd::Oracle(_) if self.oracle_silent => {}
            Cmd::Oracle(req) => {
                let result = self.answer(req.call, world, log);
                let text = serde_json::to_string(&Reply {
                    client: req.client,
                    seq: req.seq,
                    result,
                })
                .unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"));
                self.out
                    .failures
                    .note(self.out.reply.publish(StringMsg { data: text }));
            }
            Cmd::Unreadable(e) => log(&format!("sim-node: ignored {e}")),
        }
    }

    /// Render a pair, keep it for a resend, publish it; its stamp.
    fn capture_pair(&mut self, w: &World) -> Result<msg::Time, String> {
        let Some(camera) = &w.camera else {
            return Err("no stereo camera: reset with one first".into());
        };
        let pair = camera.capture_with_truth();
        // Stamped when the pair exists, as a camera stamps at exposure.
        let stamp = now_stamp();
        let images = [
            camera::image_msg(&pair.left, stamp, FRAMES[0]),
            camera::image_msg(&pair.right, stamp, FRAMES[1]),
        ];
        self.last_pair = Some((stamp, images));
        self.publish_pair()?;
        Ok(stamp)
    }

    /// Publish the last pair and its camera info (nothing once the camera is silent).
    fn publish_pair(&self) -> Result<(), String> {
        let Some((stamp, images)) = &self.last_pair else {
            return Ok(());
        };
        if self.camera_silent {
            return Ok(());
        }
        let c = &self.out.camera;
        for (topic, image) in c.images.iter().zip(images) {
            topic
                .publish(image.clone())
                .map_err(|e| format!("cannot publish the pair: {e}"))?;
        }
        c.publish_infos(*stamp, &self.out.failures);
        Ok(())
    }

    fn state_command(&mut self, i: usize, command: &str, log: &mut dyn FnMut(&str)) {
        log(&format!(
            "sim-node: /{} state_command {command}",
            self.options.arms[i]
        ));
        let s = &mut self.states[i];
        match command {
            "enable" => s.state = "ENABLED",
            "disable" => s.state = "DISABLED",
            "home" if s.state == "ENABLED" => {
                // Homing is a motion: busy, then homed.
                self.set_busy(i, true);
                std::thread::sleep(Duration::from_millis(5));
                self.states[i].homed = true;
                self.states[i].busy = false;
            }
            "unhome" => s.homed = false,
            "pause" => s.state = "PAUSED",
            "resume" if s.state == "PAUSED" => s.state = "ENABLED",
            other => {
                let why = format!("state_command {other:?} refused in state {}", s.state);
                self.error(i, &why, log);
                return;
            }
        }
        self.publish_state(i);
    }

    fn answer(
        &mut self,
        call: Call,
        w: &mut World,
        log: &mut dyn FnMut(&str),
    ) -> Result<Answer, String> {
        Ok(match call {
            Call::Ping => Answer::Done,
            Call::Reset {
                seed,
                scene,
                sensing,
                camera,
            } => {
                *w = World::new(seed, &scene, sensing, camera.as_deref())?;
                *self
                    .out
                    .camera
                    .calibration
                    .lock()
                    .unwrap_or_else(PoisonError::into_inner) = w.calibration();
                self.refresh(w);
                log(&format!(
                    "sim-node: reset to seed {seed}{}",
                    if camera.is_some() {
                        ", with the stereo camera"
                    } else {
                        ""
                    }
                ));
                Answer::Done
            }
            Call::Capture => Answer::Frame(self.capture_pair(w)?),
            Call::Resend { stamp } => {
                match &self.last_pair {
                    Some((t, _)) if *t == stamp => self.publish_pair()?,
                    _ => return Err(format!("no pair stamped {stamp:?} to resend")),
                }
                log(&format!(
                    "sim-node: resent the pair stamped {:.3} s",
                    stamp.as_secs_f64()
                ));
                Answer::Done
            }
            Call::Estimate => {
                Answer::Estimate(w.estimator.estimate_needle().map(|e| WireEstimate {
                    pose: e.pose,
                    confidence: e.confidence,
                    stamp_s: e.stamp.as_secs_f64(),
                }))
            }
            Call::BeginPass => {
                w.observer.begin_pass();
                Answer::Done
            }
            Call::EndPass { point } => {
                let p = w.observer.end_pass(&point);
                Answer::Pass(WirePass {
                    entry_error_m: p.entry_error_m,
                    exit_error_m: p.exit_error_m,
                    protrusion_m: p.protrusion_m,
                    passed: p.passed,
                })
            }
            Call::Problem => Answer::Problem(w.observer.problem()),
            Call::NeedleInTissue => Answer::Bool(w.observer.needle_in_tissue()),
            Call::Cinched { beta_m } => {
                w.observer.cinched(beta_m);
                Answer::Done
            }
            Call::ThreadLeft => Answer::Meters(w.observer.thread_left_m()),
            Call::Recover { needs } => {
                w.world.recover(needs);
                self.refresh(w);
                log(&format!("sim-node: recovery motion, needle to {needs:?}"));
                Answer::Done
            }
            Call::Holds => Answer::Holds(w.holds),
        })
    }
}

/// One-way latencies of the `servo_cp`s received, the latest [`SERVO_LATENCIES_KEPT`]
/// (receive time minus the command's stamp, both this machine's clock), s: what `stitch
/// bench ros2` reads.
pub static SERVO_LATENCIES: Mutex<Vec<f64>> = Mutex::new(Vec::new());

/// At most this many latencies are kept (the older half goes when it is reached): `stitch
/// bench ros2` streams 5 s at 1 kHz, a node streamed to for hours would otherwise grow.
pub const SERVO_LATENCIES_KEPT: usize = 200_000;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn publish_failures_are_counted_and_logged_once_each_report() {
        let f = Failures::default();
        f.note(Ok(()));
        let mut lines = Vec::new();
        f.report(&mut |l: &str| lines.push(l.to_string()));
        assert!(lines.is_empty(), "nothing failed: {lines:?}");
        f.note(Err("cannot publish on /PSM1/measured_cp: a".into()));
        f.note(Err("cannot publish on /PSM1/jaw/measured_js: b".into()));
        f.report(&mut |l: &str| lines.push(l.to_string()));
        f.report(&mut |l: &str| lines.push(l.to_string()));
        assert_eq!(
            lines,
            [
                "sim-node: 2 messages could not be published; the last: cannot publish on \
              /PSM1/jaw/measured_js: b"
            ]
        );
    }

    #[test]
    fn wire_faults_parse_and_bad_ones_say_why() {
        let f: WireFault = "busy-stuck@7".parse().expect("parses");
        assert_eq!(
            f,
            WireFault {
                kind: WireFaultKind::BusyStuck,
                nth: 7
            }
        );
        let e = "busy-stuck@0".parse::<WireFault>().expect_err("from 1");
        assert!(e.contains("from 1"), "{e}");
        let e = "melt@3".parse::<WireFault>().expect_err("unknown");
        assert!(e.contains("expected arm-error"), "{e}");
        assert!("arm-error".parse::<WireFault>().is_err());
    }

    #[test]
    fn a_bad_time_scale_or_rate_is_refused_before_joining_the_network() {
        let stop = AtomicBool::new(false);
        let o = SimNodeOptions {
            time_scale: 0.5,
            ..SimNodeOptions::default()
        };
        let e = serve(&o, &stop, &mut |_| {}).expect_err("refused");
        assert!(e.contains("time scale 0.5"), "{e}");
        let o = SimNodeOptions {
            rate_hz: 0.0,
            ..SimNodeOptions::default()
        };
        assert!(serve(&o, &stop, &mut |_| {}).is_err());
    }
}
