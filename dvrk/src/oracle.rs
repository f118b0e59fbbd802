//! The simulator's side channel, served by `stitch sim-node` beside the CRTK topics: what a
//! real dVRK cannot tell over ROS 2 but a simulated run needs to stay the in-process mock's
//! twin: the mock's needle estimator (its seeded noise model), the ground-truth observer
//! (pass scores, dropped needle, thread problems), the supervising surgeon's recovery motion,
//! and a reset of the world to a seed. On a real dVRK nothing answers it.
//!
//! Requests and replies are JSON in `std_msgs/String` on [`REQUEST_TOPIC`] and
//! [`REPLY_TOPIC`], each carrying the client's id and a sequence number.

use crate::msg::StringMsg;
use crate::ros2::{Bus, Matched, Ros2Options, Topic, stream_qos, types};
use serde::{Deserialize, Serialize};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, PoisonError};
use std::time::{Duration, Instant};
use stitch_perception::PerceptionError;
use stitch_primitives::FailureKind;
use stitch_robot::{Pose, WoundPoint};
use stitch_sim::{CameraConfig, NeedlePlace, SceneConfig, SensingConfig};

/// Requests to the simulator.
pub const REQUEST_TOPIC: &str = "/stitch_sim/oracle/request";
/// Its replies.
pub const REPLY_TOPIC: &str = "/stitch_sim/oracle/reply";

/// What the client asks.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "call", rename_all = "snake_case")]
pub enum Call {
    /// Are you there? (No effect; retried until answered.)
    Ping,
    /// Start a fresh world: this seed, scene and needle estimator.
    Reset {
        /// The run's seed.
        seed: u64,
        /// The scene.
        scene: Box<SceneConfig>,
        /// The estimator's noise model.
        sensing: SensingConfig,
        /// The stereo camera to render (none: the mission uses the noise model).
        #[serde(default)]
        camera: Option<Box<CameraConfig>>,
    },
    /// Render one stereo pair now and publish it on the camera topics; the answer is its
    /// stamp ([`Answer::Frame`]).
    Capture,
    /// Publish the pair stamped so again (it did not arrive whole).
    Resend {
        /// The pair's stamp.
        stamp: crate::msg::Time,
    },
    /// One needle estimate from the mock's estimator.
    Estimate,
    /// Observer: an insertion begins.
    BeginPass,
    /// Observer: the insertion through `point` ended.
    EndPass {
        /// The wound point.
        point: WoundPoint,
    },
    /// Observer: a problem the scene shows.
    Problem,
    /// Observer: whether the needle is in the tissue.
    NeedleInTissue,
    /// Observer: a cinch left this much free thread, m.
    Cinched {
        /// Free thread, m.
        beta_m: f64,
    },
    /// Observer: thread left, m.
    ThreadLeft,
    /// The supervising surgeon's recovery motion, readying the needle at `needs`.
    Recover {
        /// Where the failed step needs the needle.
        needs: NeedlePlace,
    },
    /// How many `hold` commands each arm received since the reset.
    Holds,
}

/// A needle estimate on the wire.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WireEstimate {
    /// Needle frame, robot frame.
    pub pose: Pose,
    /// 0 to 1.
    pub confidence: f64,
    /// Simulated time of the images, s.
    pub stamp_s: f64,
}

/// A pass score on the wire (`stitch_primitives::PassObservation`).
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct WirePass {
    /// m.
    pub entry_error_m: Option<f64>,
    /// m.
    pub exit_error_m: Option<f64>,
    /// m.
    pub protrusion_m: f64,
    /// Every criterion passed.
    pub passed: bool,
}

/// What the simulator answers.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(tag = "answer", content = "value", rename_all = "snake_case")]
pub enum Answer {
    /// Done, nothing to say.
    Done,
    /// An estimate, or why none.
    Estimate(Result<WireEstimate, PerceptionError>),
    /// A pass score.
    Pass(WirePass),
    /// A problem, if any.
    Problem(Option<FailureKind>),
    /// Yes or no.
    Bool(bool),
    /// A length, m.
    Meters(f64),
    /// Holds per arm.
    Holds([u64; 2]),
    /// The stamp of the pair just published.
    Frame(crate::msg::Time),
}

/// A request.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Request {
    /// The client's id (its replies carry it).
    pub client: u64,
    /// Sequence number within the client.
    pub seq: u64,
    /// The call.
    pub call: Call,
}

/// A reply.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Reply {
    /// The request's client.
    pub client: u64,
    /// The request's sequence number.
    pub seq: u64,
    /// The answer, or why there is none.
    pub result: Result<Answer, String>,
}

/// The answers heard, by sequence number, and the replies that could not be read.
#[derive(Default)]
struct Mail {
    answers: HashMap<u64, Result<Answer, String>>,
    /// Replies on the reply topic that did not decode: how many, and the last one's error.
    /// Whose they were cannot be known, so an unanswered call names them as a likely cause.
    unreadable: Option<(u64, String)>,
}

impl Mail {
    fn unreadable(&mut self, e: String) {
        let n = self.unreadable.as_ref().map_or(0, |(n, _)| *n);
        self.unreadable = Some((n + 1, e));
    }
}

type Inbox = Arc<(Mutex<Mail>, Condvar)>;

/// Says whether the simulator is still there (`Err`: why not), asked while a call waits.
pub type Probe = Box<dyn Fn() -> Result<(), String> + Send + Sync>;

/// A client of the simulator's side channel.
pub struct Oracle {
    request: Topic<StringMsg>,
    inbox: Inbox,
    client: u64,
    seq: AtomicU64,
    timeout: Duration,
    probe: Mutex<Option<Probe>>,
    _bus: Bus,
}

impl std::fmt::Debug for Oracle {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Oracle")
            .field("client", &self.client)
            .field("timeout", &self.timeout)
            .finish_non_exhaustive()
    }
}

impl Oracle {
    /// Find the simulator on `options`' domain within `timeout`: wait until it matched the
    /// request topic, then ping until it answers.
    pub fn connect(options: &Ros2Options, timeout: Duration) -> Result<Self, String> {
        let mut bus = Bus::new(options, "oracle_client")?;
        let request = bus.publisher::<StringMsg>(REQUEST_TOPIC, types::STRING, &stream_qos())?;
        let inbox: Inbox = Arc::default();
        let client = u64::from(std::process::id()) << 32
            | u64::from(
                std::time::SystemTime::now()
                    .duration_since(std::time::UNIX_EPOCH)
                    .unwrap_or_default()
                    .subsec_nanos(),
            );
        let sink = Arc::clone(&inbox);
        bus.subscribe::<StringMsg, _>(REPLY_TOPIC, types::STRING, &stream_qos(), move |r| {
            let (mail, cv) = &*sink;
            let mut mail = mail.lock().unwrap_or_else(PoisonError::into_inner);
            match r.and_then(|m| {
                serde_json::from_str::<Reply>(&m.data).map_err(|e| format!("not a reply: {e}"))
            }) {
                Ok(reply) if reply.client == client => {
                    mail.answers.insert(reply.seq, reply.result);
                }
                Ok(_) => return,
                Err(e) => mail.unreadable(e),
            }
            drop(mail);
            cv.notify_all();
        })?;
        let missing = bus.wait_matched(&[(REQUEST_TOPIC, &request as &dyn Matched)], timeout);
        if !missing.is_empty() {
            return Err(format!(
                "no simulator subscribed to {REQUEST_TOPIC} within {:.0} s on ROS_DOMAIN_ID {} \
                 (is `stitch sim-node` running on this domain?)",
                timeout.as_secs_f64(),
                options.domain_id
            ));
        }
        let oracle = Self {
            request,
            inbox,
            client,
            seq: AtomicU64::new(0),
            timeout,
            probe: Mutex::new(None),
            _bus: bus,
        };
        // The reply path may match a little after the request path: ping until answered.
        let deadline = Instant::now() + timeout;
        loop {
            match oracle.call_within(Call::Ping, Duration::from_millis(250)) {
                Ok(_) => return Ok(oracle),
                Err(e) if Instant::now() >= deadline => {
                    return Err(format!("the simulator did not answer a ping: {e}"));
                }
                Err(_) => {}
            }
        }
    }

    /// Ask `probe` every 100 ms while a call waits, and fail the call at once when it says
    /// the simulator is gone (instead of after the whole timeout).
    pub fn watch(&self, probe: Probe) {
        *self.probe.lock().unwrap_or_else(PoisonError::into_inner) = Some(probe);
    }

    /// Ask, and wait for the answer (at most the connect timeout).
    pub fn call(&self, call: Call) -> Result<Answer, String> {
        self.call_within(call, self.timeout)
    }

    fn call_within(&self, call: Call, timeout: Duration) -> Result<Answer, String> {
        let seq = self.seq.fetch_add(1, Ordering::SeqCst) + 1;
        let name = format!("{call:?}");
        let name = name.split([' ', '{', '(']).next().unwrap_or("").to_string();
        let text = serde_json::to_string(&Request {
            client: self.client,
            seq,
            call,
        })
        .map_err(|e| format!("cannot encode the request: {e}"))?;
        self.request.publish(StringMsg { data: text })?;
        let (map, cv) = &*self.inbox;
        let deadline = Instant::now() + timeout;
        let answer = crate::ros2::wait_for(map, cv, deadline, Duration::from_millis(100), |m| {
            if let Some(r) = m.answers.remove(&seq) {
                return Some(r.map_err(|e| format!("the simulator refused {name}: {e}")));
            }
            let probe = self.probe.lock().unwrap_or_else(PoisonError::into_inner);
            match probe.as_ref().map(|p| p()) {
                Some(Err(e)) => Some(Err(format!("the simulator did not answer {name}: {e}"))),
                _ => None,
            }
        });
        answer.unwrap_or_else(|| {
            let unreadable = map
                .lock()
                .unwrap_or_else(PoisonError::into_inner)
                .unreadable
                .as_ref()
                .map(|(n, e)| {
                    format!(" ({n} replies on {REPLY_TOPIC} could not be read; the last: {e})")
                })
                .unwrap_or_default();
            Err(format!(
                "the simulator did not answer {name} within {:.1} s{unreadable}",
                timeout.as_secs_f64()
            ))
        })
    }
}
