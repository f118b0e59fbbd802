//! The ROS 2 side, over `ros2-client` (pure-Rust DDS, no ROS installation): a [`Bus`] (one
//! DDS participant and node on a chosen domain, its spinner and subscriptions on a background
//! thread) and the QoS profiles the dVRK's CRTK topics use.

use ros2_client::{
    Context, ContextOptions, MessageTypeName, Name, Node, NodeName, NodeOptions, Publisher,
    QosProfile,
    qos::{Durability, History, WhenFull},
};
use serde::Serialize;
use serde::de::DeserializeOwned;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// The ROS 2 distribution this build speaks (a cargo feature: `jazzy` by default, `humble`
/// or `galactic` with `--no-default-features --features ros2,humble`).
pub const DISTRIBUTION: &str = ros2_client::distributions::COMPILED_ROS_DISTRO.as_str();

/// Where to meet the dVRK.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Ros2Options {
    /// `ROS_DOMAIN_ID`, 0 to 232.
    pub domain_id: u16,
}

impl Ros2Options {
    /// From the environment: `ROS_DOMAIN_ID` (default 0); a bad value is an error naming it.
    pub fn from_env() -> Result<Self, String> {
        match std::env::var("ROS_DOMAIN_ID") {
            Err(_) => Ok(Self { domain_id: 0 }),
            Ok(v) => Self::domain(&v).map_err(|e| format!("ROS_DOMAIN_ID={v:?}: {e}")),
        }
    }

    /// A domain id from text: 0 to 232.
    pub fn domain(text: &str) -> Result<Self, String> {
        match text.trim().parse::<u16>() {
            Ok(d) if d <= 232 => Ok(Self { domain_id: d }),
            _ => Err("expected a ROS 2 domain id, 0 to 232".into()),
        }
    }
}

/// A DDS participant on the options' domain.
pub fn context(options: &Ros2Options) -> Result<Context, String> {
    Context::with_options(ContextOptions::new().domain_id(options.domain_id))
        .map_err(|e| format!("cannot join ROS 2 domain {}: {e:?}", options.domain_id))
}

/// State the dVRK latches (`operating_state`): reliable and transient-local, so a late
/// subscriber still gets the last one.
pub fn latched_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::TransientLocal)
        .history(History::KeepLast { depth: 1 })
}

/// Commands and measured state streams (`move_cp`, `measured_cp`, ...): reliable, the
/// latest few.
pub fn stream_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .history(History::KeepLast { depth: 10 })
}

/// A ROS 2 name from a full topic path, e.g. `/PSM1/jaw/measured_js`.
pub fn topic_name(full: &str) -> Result<Name, String> {
    Name::parse(full).map_err(|e| format!("bad ROS 2 topic name {full:?}: {e:?}"))
}

/// Seconds since the Unix epoch as a ROS stamp (the dVRK stamps with its system clock).
pub fn now_stamp() -> crate::msg::Time {
    let d = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .unwrap_or_default();
    crate::msg::Time {
        sec: i32::try_from(d.as_secs()).unwrap_or(i32::MAX),
        nanosec: d.subsec_nanos(),
    }
}

/// Age of a stamp against this machine's clock, s (negative: from the future).
pub fn stamp_age_s(stamp: &crate::msg::Time) -> f64 {
    now_stamp().as_secs_f64() - stamp.as_secs_f64()
}

/// Wait on `cv` until `done` says something about `state`, at most until `deadline`, waking
/// at least every `tick` (for conditions judged by the clock, such as staleness, not only by
/// messages). What the bus threads heard is waited on so, everywhere.
pub fn wait_for<S, T>(
    state: &std::sync::Mutex<S>,
    cv: &std::sync::Condvar,
    deadline: Instant,
    tick: Duration,
    mut done: impl FnMut(&mut S) -> Option<T>,
) -> Option<T> {
    let mut s = state
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    loop {
        if let Some(v) = done(&mut s) {
            return Some(v);
        }
        let now = Instant::now();
        if now >= deadline {
            return None;
        }
        s = cv
            .wait_timeout(s, (deadline - now).min(tick))
            .unwrap_or_else(std::sync::PoisonError::into_inner)
            .0;
    }
}

/// One DDS participant with one ROS 2 node, its spinner and every subscription's reader
/// running on a background thread. Publishing is synchronous; subscriptions call a handler.
pub struct Bus {
    node: Node,
    executor: Arc<smol::Executor<'static>>,
    stop: Option<async_channel::Sender<()>>,
    thread: Option<std::thread::JoinHandle<()>>,
    domain_id: u16,
    linger: Duration,
    // Kept alive as long as the node: the participant.
    context: Context,
    /// Discovery events, once asked for.
    discovery: Option<async_channel::Receiver<ros2_client::NodeEvent>>,
}

impl std::fmt::Debug for Bus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bus")
            .field("domain_id", &self.domain_id)
            .field("node", &self.node.fully_qualified_name())
            .finish_non_exhaustive()
    }
}

impl Bus {
    /// Join `options`' domain as node `/stitch/<name>`.
    pub fn new(options: &Ros2Options, name: &str) -> Result<Self, String> {
        let context = context(options)?;
        let node_name =
            NodeName::new("/stitch", name).map_err(|e| format!("bad node name {name:?}: {e:?}"))?;
        let mut node = context
            .new_node(
                node_name,
                NodeOptions::new()
                    .enable_rosout(false)
                    .start_parameter_services(false),
            )
            .map_err(|e| format!("cannot create ROS 2 node {name}: {e:?}"))?;
        let spinner = node
            .spinner()
            .map_err(|e| format!("cannot start ROS 2 node {name}: {e:?}"))?;
        let executor = Arc::new(smol::Executor::new());
        let who = name.to_string();
        executor
            .spawn(async move {
                // The spinner keeps this node in the ROS graph (`ros2 node list`); the topics
                // do not need it, so the run goes on, and says so on stderr.
                if let Err(e) = spinner.spin().await {
                    eprintln!(
                        "stitch: ROS 2 node {who}: its spinner stopped ({e:?}); its topics keep \
                         working, but ROS 2 tools may no longer list the node"
                    );
                }
            })
            .detach();
        let (stop, stopped) = async_channel::bounded::<()>(1);
        let ex = Arc::clone(&executor);
        let thread = std::thread::Builder::new()
            .name(format!("ros2-{name}"))
            .spawn(move || {
                smol::block_on(ex.run(async move {
                    let _ = stopped.recv().await;
                }));
            })
            .map_err(|e| format!("cannot start the ROS 2 thread: {e}"))?;
        Ok(Self {
            node,
            executor,
            stop: Some(stop),
            thread: Some(thread),
            domain_id: options.domain_id,
            linger: LINGER,
            context,
            discovery: None,
        })
    }

    /// How long the bus lingers when dropped ([`LINGER`] unless set): a bus that only
    /// listens needs none; one that sends the last `hold` needs time for its repair.
    pub fn set_linger(&mut self, linger: Duration) {
        self.linger = linger;
    }

    /// The domain id it joined.
    pub fn domain_id(&self) -> u16 {
        self.domain_id
    }

    /// Start taking note of discovery events (a participant, reader or writer found or
    /// lost), for [`Bus::discovery_events`].
    pub fn watch_discovery(&mut self) {
        self.discovery = self.node.status_receiver();
    }

    /// How many discovery events arrived since the last call (after [`Bus::watch_discovery`];
    /// 0 before). A burst may be counted short: ros2-client drops what a full channel of 8
    /// cannot take, so this says whether there was any, not how many.
    pub fn discovery_events(&self) -> usize {
        let Some(rx) = &self.discovery else {
            return 0;
        };
        std::iter::from_fn(|| rx.try_recv().ok()).count()
    }

    /// How many readers and writers of other participants its participant knows of now
    /// (RustDDS lists its own among the discovered ones: those are left out).
    pub fn remote_endpoints(&self) -> usize {
        use ros2_client::dds::rustdds::RTPSEntity;
        let dp = self.context.domain_participant();
        let own = dp.guid().prefix;
        let readers = dp.discovered_readers();
        let writers = dp.discovered_writers();
        readers
            .iter()
            .filter(|r| r.reader_proxy.remote_reader_guid.prefix != own)
            .count()
            + writers
                .iter()
                .filter(|w| w.writer_proxy.remote_writer_guid.prefix != own)
                .count()
    }

    fn topic(
        &self,
        full: &str,
        ty: (&str, &str),
        qos: &QosProfile,
    ) -> Result<ros2_client::dds::rustdds::Topic, String> {
        self.node
            .create_topic(&topic_name(full)?, MessageTypeName::new(ty.0, ty.1), qos)
            .map_err(|e| format!("cannot create topic {full}: {e:?}"))
    }

    /// A publisher on `full` of ROS type `ty` (package, name).
    pub fn publisher<M: Serialize>(
        &mut self,
        full: &str,
        ty: (&str, &str),
        qos: &QosProfile,
    ) -> Result<Topic<M>, String> {
        let topic = self.topic(full, ty, qos)?;
        let publisher = self
            .node
            .create_publisher::<M>(&topic, None)
            .map_err(|e| format!("cannot publish on {full}: {e:?}"))?;
        Ok(Topic {
            name: full.to_string(),
            publisher,
        })
    }

    /// Subscribe to `full`; `handler` runs on the bus thread for every message, with the
    /// message or why it could not be read (bad bytes are an error, never a panic).
    pub fn subscribe<M, F>(
        &mut self,
        full: &str,
        ty: (&str, &str),
        qos: &QosProfile,
        mut handler: F,
    ) -> Result<(), String>
    where
        M: DeserializeOwned + Send + Sync + 'static,
        F: FnMut(Result<M, String>) + Send + 'static,
    {
        self.subscribe_stamped(full, ty, qos, move |r: Result<Stamped<M>, String>| {
            handler(r.map(|s| s.message))
        })
    }

    /// [`Bus::subscribe`], with each message's DDS source timestamp (when its writer sent
    /// it, by the writer's clock).
    pub fn subscribe_stamped<M, F>(
        &mut self,
        full: &str,
        ty: (&str, &str),
        qos: &QosProfile,
        mut handler: F,
    ) -> Result<(), String>
    where
        M: DeserializeOwned + Send + Sync + 'static,
        F: FnMut(Result<Stamped<M>, String>) + Send + 'static,
    {
        use futures::StreamExt;
        let topic = self.topic(full, ty, qos)?;
        let subscription = self
            .node
            .create_subscription::<M>(&topic, None)
            .map_err(|e| format!("cannot subscribe to {full}: {e:?}"))?;
        let name = full.to_string();
        self.executor
            .spawn(async move {
                let stream = subscription.async_stream();
                futures::pin_mut!(stream);
                while let Some(r) = stream.next().await {
                    handler(
                        r.map(|(message, info)| Stamped {
                            message,
                            source_s: info.source_timestamp().map(|t| t.to_nanos() as f64 * 1e-9),
                        })
                        .map_err(|e| format!("{name}: unreadable message: {e:?}")),
                    );
                }
            })
            .detach();
        Ok(())
    }

    /// How many remote readers `topic` has matched.
    pub fn readers<M: Serialize>(&self, topic: &Topic<M>) -> usize {
        topic.publisher.get_subscription_count(&self.node)
    }

    /// Wait until every topic in `topics` has a matched reader, at most `timeout`; the
    /// names of those still unmatched otherwise. A command sent before the dVRK's side
    /// matched its topic is silently lost, so nothing is sent before this returns.
    pub fn wait_matched(&self, topics: &[(&str, &dyn Matched)], timeout: Duration) -> Vec<String> {
        let deadline = Instant::now() + timeout;
        loop {
            let missing: Vec<String> = topics
                .iter()
                .filter(|(_, t)| t.matched(&self.node) == 0)
                .map(|(n, _)| (*n).to_string())
                .collect();
            if missing.is_empty() || Instant::now() >= deadline {
                return missing;
            }
            std::thread::sleep(Duration::from_millis(10));
        }
    }
}

/// A message as it arrived, with its DDS source timestamp.
#[derive(Debug)]
pub struct Stamped<M> {
    /// The message.
    pub message: M,
    /// When its writer wrote it, s since the Unix epoch by the writer's clock (RTPS
    /// `INFO_TS`); `None` when the writer sent none.
    pub source_s: Option<f64>,
}

/// How long a bus lingers when dropped, so its reliable writers can still deliver (and
/// repeat, if lost) the last commands.
pub const LINGER: Duration = Duration::from_millis(200);

/// How long the arms' bus lingers: a lost final `hold` is repaired after the writer's next
/// heartbeat (RustDDS: every 100 ms while unacknowledged) and the reader's request, so five
/// of them, on a loaded machine.
pub const HOLD_LINGER: Duration = Duration::from_millis(500);

impl Drop for Bus {
    fn drop(&mut self) {
        std::thread::sleep(self.linger);
        self.node.stop_spinner();
        if let Some(stop) = self.stop.take() {
            let _ = stop.try_send(());
        }
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// A topic this node publishes on.
pub struct Topic<M: Serialize> {
    name: String,
    publisher: Publisher<M>,
}

impl<M: Serialize> std::fmt::Debug for Topic<M> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Topic").field("name", &self.name).finish()
    }
}

impl<M: Serialize> Topic<M> {
    /// The full topic name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Publish one message.
    pub fn publish(&self, message: M) -> Result<(), String> {
        self.publisher
            .publish(message)
            .map_err(|e| format!("cannot publish on {}: {e}", self.name))
    }
}

/// Something whose matched remote readers can be counted.
pub trait Matched {
    /// Matched remote readers.
    fn matched(&self, node: &Node) -> usize;
}

impl<M: Serialize> Matched for Topic<M> {
    fn matched(&self, node: &Node) -> usize {
        self.publisher.get_subscription_count(node)
    }
}

/// ROS types of the messages in [`crate::msg`].
pub mod types {
    /// `geometry_msgs/PoseStamped`.
    pub const POSE_STAMPED: (&str, &str) = ("geometry_msgs", "PoseStamped");
    /// `sensor_msgs/JointState`.
    pub const JOINT_STATE: (&str, &str) = ("sensor_msgs", "JointState");
    /// `crtk_msgs/OperatingState`.
    pub const OPERATING_STATE: (&str, &str) = ("crtk_msgs", "OperatingState");
    /// `crtk_msgs/StringStamped`.
    pub const STRING_STAMPED: (&str, &str) = ("crtk_msgs", "StringStamped");
    /// `std_msgs/String`.
    pub const STRING: (&str, &str) = ("std_msgs", "String");
    /// `std_msgs/Empty`.
    pub const EMPTY: (&str, &str) = ("std_msgs", "Empty");
    /// `std_msgs/Float64`.
    pub const FLOAT64: (&str, &str) = ("std_msgs", "Float64");
    /// `sensor_msgs/Image`.
    pub const IMAGE: (&str, &str) = ("sensor_msgs", "Image");
    /// `sensor_msgs/CameraInfo`.
    pub const CAMERA_INFO: (&str, &str) = ("sensor_msgs", "CameraInfo");
}
