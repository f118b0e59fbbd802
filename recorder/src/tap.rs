//! [`Tap`]: the robot's side of the recorder. Arms, jaws and the needle estimator wrapped so
//! that every command they are given and every value they return is recorded as it passes,
//! stamped with the run's clock; a sampler for a real robot's state between calls.
//!
//! On the mock, a tap records only what flows through it: it never asks the robot anything
//! itself (a read can fire a simulated fault and would change the run), so the same seed
//! still gives the same file, and a run with the recorder is the run without it.

use crate::msgs::{
    CircleAnnotation, Color, IMAGE_ANNOTATIONS, ImageAnnotations, JOINT_STATE, LOG, Log, MsgType,
    NEEDLE_ESTIMATE, NeedleEstimate as EstimateMsg, OPERATING_STATE, PATH, POSE_STAMPED, Path,
    Point2, PointsAnnotation, Qos, THREAD_TRACE, TextAnnotation, ThreadTrace as TraceMsg, pose_msg,
    stamp_ns,
};
use crate::write::Item;
use serde::Serialize;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::Duration;
use stitch_dvrk::msg::{Header, JointState, OperatingState, PoseStamped};
use stitch_perception::{
    NeedleEnd, NeedleEstimate, NeedleEstimator, NeedleHint, PerceptionError, ThreadHint,
    ThreadTrace,
};
use stitch_primitives::Rig;
use stitch_robot::{
    Arm, Clock, FrameObserver, Jaw, MoveHandle, Needle, Pose, RobotError, SpeedLimits,
    StereoCalibration, StereoFrame,
};

/// The frame every recorded pose is in: the robot frame the primitives work in.
pub const FRAME: &str = "world";

/// The queue to the writer: a vector under a lock, the writer woken for engine events and
/// then only every [`BATCH`] messages. A `std::sync::mpsc` channel wakes a parked receiver
/// on every send, a `futex` call each: for a kinematic mock mission, whose ~850 messages
/// come in a few milliseconds, that was a third of what the recorder cost (perf). Written
/// by hand: the channel crates wake per message too.
#[derive(Debug, Default)]
pub(crate) struct Queue {
    items: Mutex<(Vec<Item>, bool)>,
    ready: Condvar,
}

/// Telemetry messages queued before the writer is woken for them.
pub(crate) const BATCH: usize = 64;

impl Queue {
    /// Add `item`; wake the writer if it waits and `urgent` or a batch is full.
    fn push(&self, item: Item, urgent: bool) {
        let mut q = self.items.lock().unwrap_or_else(PoisonError::into_inner);
        q.0.push(item);
        if q.1 && (urgent || q.0.len() >= BATCH) {
            q.1 = false;
            self.ready.notify_one();
        }
    }

    /// Everything queued, waiting for something if nothing is (at most `timeout`, if given:
    /// then possibly nothing).
    pub(crate) fn take(&self, timeout: Option<Duration>) -> Vec<Item> {
        let mut q = self.items.lock().unwrap_or_else(PoisonError::into_inner);
        if q.0.is_empty() {
            q.1 = true;
            match timeout {
                Some(t) => {
                    q = self
                        .ready
                        .wait_timeout_while(q, t, |q| q.1)
                        .unwrap_or_else(PoisonError::into_inner)
                        .0;
                }
                None => {
                    q = self
                        .ready
                        .wait_while(q, |q| q.1)
                        .unwrap_or_else(PoisonError::into_inner);
                }
            }
            q.1 = false;
        }
        std::mem::take(&mut q.0)
    }
}

/// What the engine's side (sink, taps) and the writer thread share.
#[derive(Debug)]
pub(crate) struct Shared {
    /// The writer's queue.
    pub(crate) queue: Queue,
    ended: AtomicBool,
    /// The step running now, for estimates (`t0 s2 insert a0`).
    pub(crate) step: Mutex<String>,
    /// Camera frames dropped so far.
    pub(crate) frames_dropped: AtomicU64,
    /// Bytes of camera frames queued and not yet written.
    frame_queue: Mutex<usize>,
    frame_written: Condvar,
    max_frame_queue_bytes: usize,
    /// How often to record a pair, if at all.
    frame_period: Option<Duration>,
    /// Whether a pair with no room is dropped (a robot's run) or waited for (simulated).
    drop_frames: bool,
    /// The recorded camera's calibration, from its first frame: to draw estimates on it.
    calibration: Mutex<Option<StereoCalibration>>,
}

impl Shared {
    pub(crate) fn new(options: crate::RecorderOptions) -> Self {
        let max_frame_queue_bytes = options.max_frame_queue_bytes;
        Self {
            frame_period: options.frame_period,
            drop_frames: options.wall_flush,
            queue: Queue::default(),
            calibration: Mutex::new(None),
            ended: AtomicBool::new(false),
            step: Mutex::new(String::new()),
            frames_dropped: AtomicU64::new(0),
            frame_queue: Mutex::new(0),
            frame_written: Condvar::new(),
            max_frame_queue_bytes: if max_frame_queue_bytes == 0 {
                crate::write::MAX_FRAME_QUEUE_BYTES
            } else {
                max_frame_queue_bytes
            },
        }
    }

    /// Queue `item`, unless the recording is over. Anything but a telemetry message wakes
    /// the writer at once.
    pub(crate) fn send(&self, item: Item) {
        if !self.ended.load(Ordering::Acquire) {
            let urgent = !matches!(item, Item::Message { .. });
            self.queue.push(item, urgent);
        }
    }

    /// End the recording (once): nothing queued after this is written.
    pub(crate) fn end(&self) {
        if !self.ended.swap(true, Ordering::AcqRel) {
            self.queue.push(Item::End, true);
        }
        self.frame_written.notify_all();
    }

    /// Whether the recording is over.
    pub(crate) fn ended(&self) -> bool {
        self.ended.load(Ordering::Acquire)
    }

    /// The writer wrote a frame of `bytes`.
    pub(crate) fn frame_written(&self, bytes: usize) {
        let mut q = self
            .frame_queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        *q = q.saturating_sub(bytes);
        self.frame_written.notify_all();
    }

    /// Room for a frame of `bytes` in the queue: taken at once, or, when full, waited for
    /// (`wait`: a simulated run, whose time does not run on while it waits) or refused and
    /// counted (a robot's run, which must not wait on the disk).
    pub(crate) fn admit_frame(&self, bytes: usize, wait: bool) -> bool {
        let mut q = self
            .frame_queue
            .lock()
            .unwrap_or_else(PoisonError::into_inner);
        while *q > 0 && *q + bytes > self.max_frame_queue_bytes {
            if !wait || self.ended() {
                self.frames_dropped.fetch_add(1, Ordering::Relaxed);
                return false;
            }
            q = self
                .frame_written
                .wait_timeout(q, Duration::from_millis(100))
                .unwrap_or_else(PoisonError::into_inner)
                .0;
        }
        *q += bytes;
        true
    }
}

/// The recorder's tap on a robot: see the module docs. Cheap to clone; every clone records
/// into the same file.
#[derive(Clone)]
pub struct Tap {
    shared: Arc<Shared>,
    clock: Arc<dyn Clock>,
    topics: Arc<Topics>,
}

/// The fixed topics, made once (a message's topic is shared, not copied).
#[derive(Debug)]
struct Topics {
    rosout: Arc<str>,
    estimate: Arc<str>,
    needle_pose: Arc<str>,
    needle_truth: Arc<str>,
    annotations: Arc<str>,
    thread: Arc<str>,
    thread_path: Arc<str>,
    thread_annotations: Arc<str>,
}

impl std::fmt::Debug for Tap {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Tap").finish_non_exhaustive()
    }
}

/// The needle's true pose where something knows it (the mock's world), read when an estimate
/// is recorded, to set beside it.
pub type Truth = Box<dyn FnMut() -> Option<Pose> + Send>;

impl Tap {
    pub(crate) fn new(shared: Arc<Shared>, clock: Arc<dyn Clock>) -> Self {
        Self {
            shared,
            clock,
            topics: Arc::new(Topics {
                rosout: "/rosout".into(),
                estimate: "/stitch/needle/estimate".into(),
                needle_pose: "/stitch/needle/pose".into(),
                needle_truth: "/stitch/needle/truth".into(),
                annotations: "/stitch/camera/left/annotations".into(),
                thread: "/stitch/thread".into(),
                thread_path: "/stitch/thread/path".into(),
                thread_annotations: "/stitch/camera/left/thread_annotations".into(),
            }),
        }
    }

    fn now_ns(&self) -> u64 {
        u64::try_from(self.clock.now().as_nanos()).unwrap_or(u64::MAX)
    }

    fn header(&self, t_ns: u64) -> Header {
        Header {
            stamp: stamp_ns(t_ns),
            frame_id: FRAME.into(),
        }
    }

    fn put<T: Serialize>(&self, topic: &Arc<str>, ty: &'static MsgType, t_ns: u64, msg: &T) {
        match stitch_dvrk::encode(msg, ty.name) {
            Ok(bytes) => self.shared.send(Item::Message {
                topic: Arc::clone(topic),
                ty,
                qos: Qos::Stream,
                t_ns,
                bytes,
            }),
            // These types always encode; should one not, the file says so rather than
            // silently missing a message.
            Err(e) => self.log(Log::ERROR, "recorder", &format!("{topic}: {e}")),
        }
    }

    /// Record `pose` on `topic` (`geometry_msgs/PoseStamped`), now.
    pub fn pose(&self, topic: &str, pose: &Pose) {
        self.pose_on(&Arc::from(topic), pose);
    }

    fn pose_on(&self, topic: &Arc<str>, pose: &Pose) {
        let t = self.now_ns();
        let msg = PoseStamped {
            header: self.header(t),
            pose: pose_msg(pose),
        };
        self.put(topic, &POSE_STAMPED, t, &msg);
    }

    /// Record a jaw's opening, rad, on `topic` (`sensor_msgs/JointState`), now.
    pub fn jaw_angle(&self, topic: &str, joint: &str, angle_rad: f64) {
        self.jaw_angle_on(&Arc::from(topic), joint, angle_rad);
    }

    fn jaw_angle_on(&self, topic: &Arc<str>, joint: &str, angle_rad: f64) {
        let t = self.now_ns();
        let msg = JointState {
            header: self.header(t),
            name: vec![joint.to_string()],
            position: vec![angle_rad],
            velocity: Vec::new(),
            effort: Vec::new(),
        };
        self.put(topic, &JOINT_STATE, t, &msg);
    }

    /// Record, as the `stitch_clock` metadata, the Unix time at which the run's clock read
    /// zero: a robot's run is logged in run time, and log time + `epoch_unix_ns` is Unix time
    /// (to line the file up with a bag the dVRK recorded). Not on a simulated run.
    pub fn wall_epoch(&self) {
        let unix = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .unwrap_or_default()
            .saturating_sub(self.clock.now());
        let mut m = std::collections::BTreeMap::new();
        m.insert("epoch_unix_ns".to_string(), unix.as_nanos().to_string());
        self.shared.send(Item::Metadata(mcap::records::Metadata {
            name: "stitch_clock".into(),
            metadata: m,
        }));
    }

    /// Record a line on `/rosout` (`rcl_interfaces/Log`), now: `level` is [`Log::ERROR`],
    /// [`Log::WARN`] or [`Log::INFO`].
    pub fn log(&self, level: u8, name: &str, text: &str) {
        let t = self.now_ns();
        let msg = Log {
            stamp: stamp_ns(t),
            level,
            name: name.to_string(),
            msg: text.to_string(),
            file: String::new(),
            function: String::new(),
            line: 0,
        };
        if let Ok(bytes) = stitch_dvrk::encode(&msg, LOG.name) {
            self.shared.send(Item::Message {
                topic: Arc::clone(&self.topics.rosout),
                ty: &LOG,
                qos: Qos::Stream,
                t_ns: t,
                bytes,
            });
        }
    }

    /// Record an arm's operating state on `/{arm}/operating_state`, now.
    pub fn operating_state(&self, arm: &str, state: &OperatingState) {
        let t = self.now_ns();
        let mut msg = state.clone();
        msg.header = self.header(t);
        self.put(
            &format!("/{arm}/operating_state").into(),
            &OPERATING_STATE,
            t,
            &msg,
        );
    }

    /// `arm`, recording every command it is given and every pose it reports (and every
    /// error, on `/rosout`).
    pub fn arm(&self, arm: Arc<dyn Arm>) -> Arc<dyn Arm> {
        let name = arm.name().to_string();
        Arc::new(TappedArm {
            topics: [
                format!("/{name}/measured_cp").into(),
                format!("/{name}/setpoint_cp").into(),
                format!("/{name}/move_cp").into(),
                format!("/{name}/servo_cp").into(),
            ],
            name,
            arm,
            tap: self.clone(),
        })
    }

    /// `jaw`, recording every opening it reports and is told.
    pub fn jaw(&self, jaw: Arc<dyn Jaw>) -> Arc<dyn Jaw> {
        let name = jaw.name().to_string();
        Arc::new(TappedJaw {
            topics: [
                format!("/{name}/measured_js").into(),
                format!("/{name}/move_jp").into(),
            ],
            joint: name.replace('/', "_"),
            name,
            jaw,
            tap: self.clone(),
        })
    }

    /// `estimator`, recording every estimate and typed failure with the step that asked, on
    /// `/stitch/needle/estimate`, and its pose on `/stitch/needle/pose`; with `truth`, the
    /// true pose beside it on `/stitch/needle/truth`.
    pub fn estimator(
        &self,
        estimator: Box<dyn NeedleEstimator>,
        truth: Option<Truth>,
    ) -> Box<dyn NeedleEstimator> {
        self.estimator_of(estimator, truth, None)
    }

    fn estimator_of(
        &self,
        estimator: Box<dyn NeedleEstimator>,
        truth: Option<Truth>,
        needle: Option<Needle>,
    ) -> Box<dyn NeedleEstimator> {
        Box::new(TappedEstimator {
            estimator,
            truth,
            needle,
            tap: self.clone(),
        })
    }

    /// An observer for a camera ([`stitch_robot::ObservedCamera`]) that records a stereo pair
    /// (JPEG, encoded on the writer's thread) at most every `frame_period` of run time, or
    /// `None` if the recording takes no frames. On a robot (`wall_flush`), a pair the writer
    /// has no room for is dropped and counted; on a simulated run the camera waits for room
    /// (its time stands still), so the file stays the same.
    pub fn frames(&self) -> Option<FrameObserver> {
        let period = self.shared.frame_period?;
        let drop = self.shared.drop_frames;
        let tap = self.clone();
        let last: Mutex<Option<Duration>> = Mutex::new(None);
        Some(Arc::new(
            move |frame: &StereoFrame, calibration: &StereoCalibration| {
                {
                    let mut c = tap
                        .shared
                        .calibration
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner);
                    if c.is_none() {
                        *c = Some(calibration.clone());
                    }
                }
                let now = tap.clock.now();
                {
                    let mut last = last.lock().unwrap_or_else(PoisonError::into_inner);
                    if last.is_some_and(|l| now.saturating_sub(l) < period) {
                        return;
                    }
                    *last = Some(now);
                }
                let size = frame.left.data.len() + frame.right.data.len();
                if tap.shared.admit_frame(size, !drop) {
                    tap.shared.send(Item::Frame {
                        t_ns: u64::try_from(frame.stamp.as_nanos()).unwrap_or(u64::MAX),
                        views: Box::new([frame.left.clone(), frame.right.clone()]),
                    });
                }
            },
        ))
    }

    /// Every arm, jaw and the estimator of `rig` tapped; with recorded frames, each estimate
    /// (and the truth) is also drawn on the left image (`/stitch/camera/left/annotations`,
    /// `foxglove_msgs/ImageAnnotations`), projected with the camera's calibration.
    pub fn rig(&self, rig: Rig, truth: Option<Truth>) -> Rig {
        Rig {
            right: self.arm(rig.right),
            left: self.arm(rig.left),
            right_jaw: self.jaw(rig.right_jaw),
            left_jaw: self.jaw(rig.left_jaw),
            estimator: self.estimator_of(rig.estimator, truth, Some(rig.needle)),
            ..rig
        }
    }

    /// Call `sample` every `period` of wall time on a thread of its own until the recording
    /// ends or it returns `false`: a real robot's state between the primitives' calls. Never
    /// on a simulated run (its time is not the wall's, and reads change it).
    pub fn sample_every(
        &self,
        period: Duration,
        mut sample: impl FnMut(&Tap) -> bool + Send + 'static,
    ) {
        let tap = self.clone();
        let spawned = std::thread::Builder::new()
            .name("recorder-sampler".into())
            .spawn(move || {
                while !tap.shared.ended() && sample(&tap) {
                    std::thread::sleep(period);
                }
            });
        if let Err(e) = spawned {
            self.log(Log::ERROR, "recorder", &format!("no sampler thread: {e}"));
        }
    }

    /// The step under way (`t0 s2 insert a0`), empty between steps.
    fn step(&self) -> String {
        self.shared
            .step
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// The left camera's calibration, once a frame has brought it.
    fn calibration(&self) -> Option<StereoCalibration> {
        self.shared
            .calibration
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .clone()
    }

    /// Record a thread trace (or the tracer's typed failure) with the step that asked; a
    /// trace also as a line in 3D (`nav_msgs/Path`) and, with a calibration, drawn on the
    /// left image.
    fn thread(&self, hint: &ThreadHint, result: &Result<ThreadTrace, PerceptionError>) {
        let t = self.now_ns();
        let step = self.step();
        let point = |p: &stitch_robot::Point| stitch_dvrk::msg::Point {
            x: p.x,
            y: p.y,
            z: p.z,
        };
        let mut msg = TraceMsg {
            stamp: stamp_ns(t),
            step,
            has_start: hint.start.is_some(),
            start: hint.start.as_ref().map(point).unwrap_or_default(),
            swage: point(&hint.swage),
            length_prior_m: hint.length_m.unwrap_or(f64::NAN),
            ok: result.is_ok(),
            points: Vec::new(),
            sigma_m: Vec::new(),
            length_m: f64::NAN,
            hidden_from_m: Vec::new(),
            hidden_to_m: Vec::new(),
            seen_share: f64::NAN,
            matched: 0,
            failure: String::new(),
        };
        match result {
            Ok(trace) => {
                msg.points = trace.points.iter().map(point).collect();
                msg.sigma_m.clone_from(&trace.sigma_m);
                msg.length_m = trace.length_m;
                msg.hidden_from_m = trace.hidden.iter().map(|h| h[0]).collect();
                msg.hidden_to_m = trace.hidden.iter().map(|h| h[1]).collect();
                msg.seen_share = trace.seen_share;
                msg.matched = u32::try_from(trace.matched).unwrap_or(u32::MAX);
            }
            Err(f) => msg.failure = serde_json::to_string(f).unwrap_or_else(|_| f.to_string()),
        }
        self.put(&self.topics.thread, &THREAD_TRACE, t, &msg);
        let Ok(trace) = result else { return };
        let path = Path {
            header: self.header(t),
            poses: trace
                .points
                .iter()
                .map(|p| PoseStamped {
                    header: self.header(t),
                    pose: stitch_dvrk::msg::Pose {
                        position: point(p),
                        orientation: stitch_dvrk::msg::Quaternion {
                            x: 0.0,
                            y: 0.0,
                            z: 0.0,
                            w: 1.0,
                        },
                    },
                })
                .collect(),
        };
        self.put(&self.topics.thread_path, &PATH, t, &path);
        let calibration = self.calibration();
        if let Some(c) = calibration {
            let stamp = stamp_ns(t);
            let line: Vec<Point2> = trace
                .points
                .iter()
                .filter_map(|p| c.left_pixel(p))
                .map(|[x, y]| Point2 { x, y })
                .collect();
            let drawn = ImageAnnotations {
                points: vec![PointsAnnotation {
                    timestamp: stamp,
                    kind: PointsAnnotation::LINE_STRIP,
                    points: line,
                    outline_color: Color {
                        r: 0.2,
                        g: 0.7,
                        b: 1.0,
                        a: 1.0,
                    },
                    outline_colors: Vec::new(),
                    fill_color: Color::default(),
                    thickness: 2.0,
                }],
                ..ImageAnnotations::default()
            };
            self.put(
                &self.topics.thread_annotations,
                &IMAGE_ANNOTATIONS,
                t,
                &drawn,
            );
        }
    }

    fn estimate(
        &self,
        hint: Option<&NeedleHint>,
        result: &Result<NeedleEstimate, PerceptionError>,
        truth: Option<Pose>,
        needle: Option<&Needle>,
    ) {
        let t = self.now_ns();
        let step = self.step();
        let msg = match result {
            Ok(e) => EstimateMsg {
                stamp: stamp_ns(t),
                step,
                hint: hint_text(hint),
                ok: true,
                pose: pose_msg(&e.pose),
                confidence: e.confidence,
                image_stamp: stamp_ns(u64::try_from(e.stamp.as_nanos()).unwrap_or(u64::MAX)),
                failure: String::new(),
            },
            Err(f) => EstimateMsg {
                stamp: stamp_ns(t),
                step,
                hint: hint_text(hint),
                ok: false,
                pose: pose_msg(&Pose::identity()),
                confidence: 0.0,
                image_stamp: stamp_ns(t),
                failure: serde_json::to_string(f).unwrap_or_else(|_| f.to_string()),
            },
        };
        self.put(&self.topics.estimate, &NEEDLE_ESTIMATE, t, &msg);
        if let Ok(e) = result {
            self.pose_on(&self.topics.needle_pose, &e.pose);
        }
        if let Some(p) = truth {
            self.pose_on(&self.topics.needle_truth, &p);
        }
        let calibration = self.calibration();
        if let (Some(c), Some(needle), Ok(e)) = (calibration, needle, result) {
            let image = stamp_ns(u64::try_from(e.stamp.as_nanos()).unwrap_or(u64::MAX));
            let mut drawn = ImageAnnotations::default();
            let amber = Color {
                r: 1.0,
                g: 0.69,
                b: 0.0,
                a: 1.0,
            };
            let green = Color {
                r: 0.19,
                g: 0.82,
                b: 0.19,
                a: 1.0,
            };
            for (pose, color, label) in [
                (Some(e.pose), amber, format!("estimate {:.2}", e.confidence)),
                (truth, green, "truth".to_string()),
            ] {
                let Some(pose) = pose else { continue };
                let arc = project(&c, needle, &pose);
                let tip = arc.first().copied();
                drawn.points.push(PointsAnnotation {
                    timestamp: image,
                    kind: PointsAnnotation::LINE_STRIP,
                    points: arc,
                    outline_color: color,
                    outline_colors: Vec::new(),
                    fill_color: Color::default(),
                    thickness: 2.0,
                });
                if let Some(tip) = tip {
                    drawn.circles.push(CircleAnnotation {
                        timestamp: image,
                        position: tip,
                        diameter: 8.0,
                        thickness: 2.0,
                        fill_color: Color::default(),
                        outline_color: color,
                    });
                    drawn.texts.push(TextAnnotation {
                        timestamp: image,
                        position: Point2 {
                            x: tip.x + 8.0,
                            y: tip.y - 8.0,
                        },
                        text: label,
                        font_size: 14.0,
                        text_color: color,
                        background_color: Color {
                            r: 0.0,
                            g: 0.0,
                            b: 0.0,
                            a: 0.5,
                        },
                    });
                }
            }
            self.put(&self.topics.annotations, &IMAGE_ANNOTATIONS, t, &drawn);
        }
    }
}

/// The needle's half circle at `pose` in the left image, tip first, pixels (points behind the
/// camera left out).
fn project(c: &StereoCalibration, needle: &Needle, pose: &Pose) -> Vec<Point2> {
    const SEGMENTS: u32 = 24;
    (0..=SEGMENTS)
        .filter_map(|i| {
            let angle = std::f64::consts::PI * f64::from(i) / f64::from(SEGMENTS);
            let [x, y] = c.left_pixel(&(pose * needle.point_at(angle)))?;
            Some(Point2 { x, y })
        })
        .collect()
}

fn hint_text(hint: Option<&NeedleHint>) -> String {
    let mm = |p: &stitch_robot::Point| {
        format!("({:.1}, {:.1}, {:.1}) mm", p.x * 1e3, p.y * 1e3, p.z * 1e3)
    };
    match hint {
        None => String::new(),
        Some(NeedleHint::Held(j)) => format!(
            "jaw at {} holding the {}",
            mm(&j.jaw),
            match j.end {
                NeedleEnd::Tip => "tip",
                NeedleEnd::Swage => "swage",
            }
        ),
        Some(NeedleHint::InTissue(h)) => {
            format!("in tissue, entry {} exit {}", mm(&h.entry), mm(&h.exit))
        }
    }
}

struct TappedArm {
    name: String,
    /// measured_cp, setpoint_cp, move_cp, servo_cp.
    topics: [Arc<str>; 4],
    arm: Arc<dyn Arm>,
    tap: Tap,
}

impl TappedArm {
    fn fails<T>(&self, what: &str, r: Result<T, RobotError>) -> Result<T, RobotError> {
        if let Err(e) = &r {
            self.tap
                .log(Log::ERROR, &self.name, &format!("{what}: {e}"));
        }
        r
    }
}

impl Arm for TappedArm {
    fn name(&self) -> &str {
        &self.name
    }
    fn measured_cp(&self) -> Result<Pose, RobotError> {
        let r = self.fails("measured_cp", self.arm.measured_cp());
        if let Ok(p) = &r {
            self.tap.pose_on(&self.topics[0], p);
        }
        r
    }
    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        let r = self.fails("setpoint_cp", self.arm.setpoint_cp());
        if let Ok(p) = &r {
            self.tap.pose_on(&self.topics[1], p);
        }
        r
    }
    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        self.tap.pose_on(&self.topics[2], goal);
        self.fails("move_cp", self.arm.move_cp(goal))
    }
    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        self.tap.pose_on(&self.topics[3], goal);
        self.fails("servo_cp", self.arm.servo_cp(goal))
    }
    fn hold(&self) -> Result<(), RobotError> {
        self.tap.log(Log::INFO, &self.name, "hold");
        self.fails("hold", self.arm.hold())
    }
    fn set_max_speed(&self, limits: SpeedLimits) -> Result<(), RobotError> {
        self.tap.log(
            Log::INFO,
            &self.name,
            &format!(
                "max speed {} m/s, {} rad/s",
                limits.linear_m_per_s, limits.angular_rad_per_s
            ),
        );
        self.fails("set_max_speed", self.arm.set_max_speed(limits))
    }
}

struct TappedJaw {
    name: String,
    joint: String,
    /// measured_js, move_jp.
    topics: [Arc<str>; 2],
    jaw: Arc<dyn Jaw>,
    tap: Tap,
}

impl Jaw for TappedJaw {
    fn name(&self) -> &str {
        &self.name
    }
    fn measured_jp(&self) -> Result<f64, RobotError> {
        let r = self.jaw.measured_jp();
        match &r {
            Ok(a) => self.tap.jaw_angle_on(&self.topics[0], &self.joint, *a),
            Err(e) => self
                .tap
                .log(Log::ERROR, &self.name, &format!("measured_jp: {e}")),
        }
        r
    }
    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        self.tap
            .jaw_angle_on(&self.topics[1], &self.joint, angle_rad);
        let r = self.jaw.move_jp(angle_rad);
        if let Err(e) = &r {
            self.tap
                .log(Log::ERROR, &self.name, &format!("move_jp: {e}"));
        }
        r
    }
}

struct TappedEstimator {
    estimator: Box<dyn NeedleEstimator>,
    truth: Option<Truth>,
    /// The needle's shape, to draw estimates with.
    needle: Option<Needle>,
    tap: Tap,
}

impl NeedleEstimator for TappedEstimator {
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError> {
        let r = self.estimator.estimate_needle();
        let truth = self.truth.as_mut().and_then(|t| t());
        self.tap.estimate(None, &r, truth, self.needle.as_ref());
        r
    }
    fn estimate_needle_with(
        &mut self,
        hint: Option<&NeedleHint>,
    ) -> Result<NeedleEstimate, PerceptionError> {
        let r = self.estimator.estimate_needle_with(hint);
        let truth = self.truth.as_mut().and_then(|t| t());
        self.tap.estimate(hint, &r, truth, self.needle.as_ref());
        r
    }
    fn trace_thread(&mut self, hint: &ThreadHint) -> Result<ThreadTrace, PerceptionError> {
        let r = self.estimator.trace_thread(hint);
        self.tap.thread(hint, &r);
        r
    }
}
