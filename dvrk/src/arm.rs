//! The CRTK arm and jaw backend over ROS 2: [`Ros2Dvrk::connect`] meets the dVRK's arms
//! (`/PSM1`, `/PSM2`, ...), enables and homes them, and hands out [`Ros2Arm`]s and
//! [`Ros2Jaw`]s behind the `robot/` traits.
//!
//! A `move_cp` is "busy rises, then falls" on the arm's latched `operating_state`, within a
//! timeout, then a check that `measured_cp` ended within tolerance of the goal. Measurements
//! with a zero stamp (CRTK's "invalid") or older than a bound are refused; every `error` the
//! dVRK publishes during this connection fails the command under way (and the next one);
//! one it latched from before is kept apart. A motion that fails is stopped with `hold`.
//! Every command whose effect the dVRK shows is confirmed by that effect and sent again,
//! bounded, while it does not show (a first command can be lost: docs/dvrk.md).

use crate::msg::{self, Empty, Float64, JointState, OperatingState, PoseStamped, StringStamped};
use crate::ros2::{
    Bus, Matched, Ros2Options, Stamped, Topic, latched_qos, now_stamp, stream_qos, types,
};
use serde::{Deserialize, Serialize};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};
use stitch_robot::{Arm, Jaw, MotionTracker, MoveHandle, Pose, RobotError};

/// How the backend meets the dVRK and what it accepts. Times in seconds, SI units.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct DvrkConfig {
    /// The arms' namespaces: the right needle driver first, then the left.
    pub arms: [String; 2],
    /// How long to wait for the dVRK to match every command topic and publish its state.
    pub connect_timeout_s: f64,
    /// How long enabling and homing may take.
    pub state_timeout_s: f64,
    /// How long a move may take to report busy after it was sent.
    pub busy_rise_timeout_s: f64,
    /// How long a move may stay busy.
    pub move_timeout_s: f64,
    /// How long after busy falls the measured pose may take to reach the goal's tolerance.
    pub settle_timeout_s: f64,
    /// Measurements older than this (by stamp, or since they arrived) are refused.
    pub stale_after_s: f64,
    /// A read that finds the latest measurement missing or older than `stale_after_s` waits
    /// up to this long for a fresh one before refusing it, s.
    pub stale_wait_s: f64,
    /// Distance from the goal a finished move may end at, m.
    pub position_tolerance_m: f64,
    /// Angle from the goal a finished move may end at, rad.
    pub rotation_tolerance_rad: f64,
    /// Angle short of the goal an opening jaw may stop at, rad (a closing jaw stops on what
    /// it grasps, so closing is not checked).
    pub jaw_tolerance_rad: f64,
    /// `trajectory_j/set_ratio` sent at start: the fraction of the arm's top joint speed its
    /// trajectories use (low at a bench: 0.2).
    pub speed_ratio: f64,
    /// A command whose effect the dVRK has not shown (a new operating state, the latched
    /// `trajectory_j/ratio`, busy rising) within this is sent again, s.
    pub resend_after_s: f64,
    /// How many times in all a command is sent before its effect is given up on (1: never
    /// resent).
    pub max_sends: u32,
    /// The stereo camera's topics and what a capture accepts (`[camera]`).
    pub camera: crate::camera::CameraSettings,
}

impl Default for DvrkConfig {
    fn default() -> Self {
        Self {
            arms: ["PSM1".into(), "PSM2".into()],
            connect_timeout_s: 15.0,
            state_timeout_s: 60.0,
            busy_rise_timeout_s: 1.0,
            move_timeout_s: 30.0,
            settle_timeout_s: 0.5,
            stale_after_s: 0.25,
            stale_wait_s: 0.5,
            position_tolerance_m: 0.002,
            rotation_tolerance_rad: 2f64.to_radians(),
            jaw_tolerance_rad: 5f64.to_radians(),
            speed_ratio: 0.2,
            resend_after_s: 0.3,
            max_sends: 4,
            camera: crate::camera::CameraSettings::default(),
        }
    }
}

impl DvrkConfig {
    /// Refuse values the backend cannot use, naming them.
    pub fn validate(&self) -> Result<(), RobotError> {
        let bad = |what: &str, why: String| {
            Err(RobotError::InvalidConfig {
                what: format!("dvrk.{what}"),
                why,
            })
        };
        for (name, v) in [
            ("connect_timeout_s", self.connect_timeout_s),
            ("state_timeout_s", self.state_timeout_s),
            ("busy_rise_timeout_s", self.busy_rise_timeout_s),
            ("move_timeout_s", self.move_timeout_s),
            ("settle_timeout_s", self.settle_timeout_s),
            ("stale_after_s", self.stale_after_s),
            ("stale_wait_s", self.stale_wait_s),
            ("resend_after_s", self.resend_after_s),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= 3600.0) {
                return bad(name, format!("{v}; expected 0 to 3600 s"));
            }
        }
        for (name, v, max) in [
            ("position_tolerance_m", self.position_tolerance_m, 0.02),
            ("rotation_tolerance_rad", self.rotation_tolerance_rad, 0.5),
            ("jaw_tolerance_rad", self.jaw_tolerance_rad, 0.5),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= max) {
                return bad(name, format!("{v}; expected above 0, at most {max}"));
            }
        }
        if !(self.speed_ratio.is_finite() && self.speed_ratio > 0.0 && self.speed_ratio <= 1.0) {
            return bad(
                "speed_ratio",
                format!("{}; expected above 0, at most 1", self.speed_ratio),
            );
        }
        if !(1..=100).contains(&self.max_sends) {
            return bad(
                "max_sends",
                format!("{}; expected 1 to 100", self.max_sends),
            );
        }
        for a in &self.arms {
            if crate::ros2::topic_name(&format!("/{a}/measured_cp")).is_err() {
                return bad("arms", format!("{a:?} is not a ROS 2 namespace"));
            }
        }
        self.camera.validate()
    }
}

fn secs(s: f64) -> Duration {
    Duration::from_secs_f64(s)
}

/// `m` if it is valid and fresh: received, with a non-zero stamp, and no older than
/// `stale_after_s` by its stamp or since it arrived.
fn check_fresh<'a, T>(
    arm: &str,
    stale_after_s: f64,
    what: &str,
    m: &'a Option<(T, Instant)>,
    stamp: impl Fn(&T) -> msg::Time,
) -> Result<&'a T, RobotError> {
    let fault = |message: String| RobotError::Fault {
        arm: arm.to_string(),
        message,
    };
    let Some((msg, at)) = m else {
        return Err(fault(format!("no {what} received from the dVRK")));
    };
    let stamp = stamp(msg);
    if stamp.is_zero() {
        return Err(fault(format!(
            "{what} has a zero stamp: the dVRK marks invalid data so"
        )));
    }
    let age_s = crate::ros2::stamp_age_s(&stamp).max(at.elapsed().as_secs_f64());
    if age_s > stale_after_s {
        return Err(RobotError::Stale {
            arm: arm.to_string(),
            age_s,
        });
    }
    Ok(msg)
}

/// [`ArmLink::read_fresh`] over what the bus thread heard and the condition it signals.
fn read_fresh<T: Clone>(
    arm: &str,
    config: &DvrkConfig,
    (heard, changed): (&Mutex<Heard>, &Condvar),
    what: &str,
    pick: impl Fn(&Heard) -> &Option<(T, Instant)>,
    stamp: impl Fn(&T) -> msg::Time + Copy,
) -> Result<T, RobotError> {
    let deadline = Instant::now() + secs(config.stale_wait_s);
    let check = |h: &Heard| check_fresh(arm, config.stale_after_s, what, pick(h), stamp).cloned();
    // Wake at least every 20 ms: staleness is judged by the clock, not by messages.
    let tick = Duration::from_millis(20);
    let waited = crate::ros2::wait_for(heard, changed, deadline, tick, |h| match check(h) {
        Ok(m) => Some(Ok(m)),
        Err(RobotError::Stale { .. }) => None,
        Err(_) if pick(h).is_none() => None,
        Err(e) => Some(Err(e)),
    });
    match waited {
        Some(r) => r,
        None => check(&heard.lock().unwrap_or_else(PoisonError::into_inner)),
    }
}

/// What one arm has said, as the bus thread received it.
#[derive(Debug, Default)]
struct Heard {
    measured: Option<(PoseStamped, Instant)>,
    setpoint: Option<(PoseStamped, Instant)>,
    jaw: Option<(JointState, Instant)>,
    state: Option<OperatingState>,
    /// Operating states received so far.
    state_seq: u64,
    /// `state_seq` of the last busy one.
    busy_seq: u64,
    /// Every `error` message of this connection, in order.
    errors: Vec<String>,
    /// `error` messages written before this connection began (the console's latched
    /// history, delivered when we joined): not counted, but kept to be said.
    ignored: Vec<String>,
    /// The last `trajectory_j/ratio`, and when it arrived.
    ratio: Option<(f64, Instant)>,
    /// When the last latched message (operating state, error, ratio) arrived: the console's
    /// history of each comes in a burst when we join.
    latched_at: Option<Instant>,
    /// Errors already reported by a failed command.
    errors_reported: usize,
}

impl Heard {
    /// An `error` no command has reported yet, or a FAULT state.
    fn faulted(&self) -> bool {
        self.errors.len() > self.errors_reported
            || self.state.as_ref().is_some_and(|s| s.state == "FAULT")
    }
}

#[derive(Debug)]
struct ArmLink {
    name: String,
    config: DvrkConfig,
    /// When this connection began, s since the Unix epoch (before any subscription).
    started_s: f64,
    /// Commands sent again because their effect had not shown.
    resends: AtomicU64,
    heard: Mutex<Heard>,
    changed: Condvar,
    move_cp: Topic<PoseStamped>,
    servo_cp: Topic<PoseStamped>,
    hold: Topic<Empty>,
    state_command: Topic<StringStamped>,
    jaw_move_jp: Topic<JointState>,
    set_ratio: Topic<Float64>,
}

impl ArmLink {
    fn heard(&self) -> MutexGuard<'_, Heard> {
        self.heard.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Wait on `changed` until `done` says something, at most until `deadline`.
    fn wait_until<T>(
        &self,
        deadline: Instant,
        mut done: impl FnMut(&Heard) -> Option<T>,
    ) -> Option<T> {
        // Wake at least every 20 ms: staleness is judged by the clock, not by messages.
        let tick = Duration::from_millis(20);
        crate::ros2::wait_for(&self.heard, &self.changed, deadline, tick, |h| done(h))
    }

    fn fault(&self, message: String) -> RobotError {
        RobotError::Fault {
            arm: self.name.clone(),
            message,
        }
    }

    /// An `error` the dVRK published and no command has reported yet, or a FAULT state.
    fn new_error(&self, heard: &mut Heard) -> Option<RobotError> {
        if heard.errors.len() > heard.errors_reported {
            let text = heard.errors[heard.errors_reported..].join("; ");
            heard.errors_reported = heard.errors.len();
            return Some(self.fault(format!("the dVRK reported: {text}")));
        }
        match &heard.state {
            Some(s) if s.state == "FAULT" => {
                Some(self.fault("the arm is in FAULT (operating_state); re-enable it".into()))
            }
            _ => None,
        }
    }

    /// How long `measured_cp` has been silent, s, when longer than the stale bound: a dVRK
    /// streams it all the time, through moves too, so silence means it is gone.
    fn silent_s(&self, heard: &Heard) -> Option<f64> {
        heard
            .measured
            .as_ref()
            .map(|(_, at)| at.elapsed().as_secs_f64())
            .filter(|s| *s > self.config.stale_after_s)
    }

    /// The arm must be enabled and homed, with no unreported error, to take a command.
    fn ready(&self) -> Result<(), RobotError> {
        let mut heard = self.heard();
        if let Some(e) = self.new_error(&mut heard) {
            return Err(e);
        }
        match &heard.state {
            Some(s) if s.state == "ENABLED" && s.is_homed => Ok(()),
            Some(s) => Err(self.fault(format!(
                "the arm is {} (homed: {}); it takes commands only ENABLED and homed",
                s.state, s.is_homed
            ))),
            None => Err(self.fault("no operating_state heard from the dVRK".into())),
        }
    }

    /// A fresh measurement, refused when invalid or stale.
    fn fresh<'a, T>(
        &self,
        what: &str,
        m: &'a Option<(T, Instant)>,
        stamp: impl Fn(&T) -> msg::Time,
    ) -> Result<&'a T, RobotError> {
        check_fresh(&self.name, self.config.stale_after_s, what, m, stamp)
    }

    /// The latest measurement `pick` takes from what was heard, once fresh: one that is
    /// missing or older than the bound is waited for up to `stale_wait_s` (a busy host that
    /// delivered it late is not a dVRK gone silent), then refused as [`fresh`](Self::fresh)
    /// refuses it. Invalid data (a zero stamp) is refused at once.
    fn read_fresh<T: Clone>(
        &self,
        what: &str,
        pick: impl Fn(&Heard) -> &Option<(T, Instant)>,
        stamp: impl Fn(&T) -> msg::Time + Copy,
    ) -> Result<T, RobotError> {
        read_fresh(
            &self.name,
            &self.config,
            (&self.heard, &self.changed),
            what,
            pick,
            stamp,
        )
    }

    fn measured_cp(&self) -> Result<Pose, RobotError> {
        let m = self.read_fresh("measured_cp", |h| &h.measured, |m| m.header.stamp)?;
        crate::pose_from_msg(&m).map_err(|e| self.fault(format!("measured_cp: {e}")))
    }

    fn measured_jaw(&self) -> Result<f64, RobotError> {
        let m = self.read_fresh("jaw/measured_js", |h| &h.jaw, |m| m.header.stamp)?;
        match m.position.first() {
            Some(v) if v.is_finite() => Ok(*v),
            _ => Err(self.fault(format!(
                "jaw/measured_js has no finite position ({:?})",
                m.position
            ))),
        }
    }

    fn stamp() -> msg::Header {
        msg::Header {
            stamp: now_stamp(),
            frame_id: String::new(),
        }
    }

    fn send_hold(&self) -> Result<(), RobotError> {
        self.hold
            .publish(Empty::default())
            .map_err(|e| self.fault(e))
    }

    fn resent(&self) {
        self.resends.fetch_add(1, Ordering::Relaxed);
    }

    /// `hold`, confirmed: an arm that reports busy must report idle within
    /// `resend_after_s`, or the hold is sent again, up to `max_sends` times (holding twice is
    /// holding). An idle arm shows no effect of a hold, and needs none.
    fn hold(&self) -> Result<(), RobotError> {
        let busy = |h: &Heard| h.state.as_ref().is_some_and(|s| s.is_busy);
        let c = &self.config;
        let start = Instant::now();
        for sends in 1..=c.max_sends {
            if sends > 1 {
                self.resent();
            }
            self.send_hold()?;
            let until = Instant::now() + secs(c.resend_after_s);
            if self
                .wait_until(until, |h| (!busy(h)).then_some(()))
                .is_some()
            {
                return Ok(());
            }
        }
        Err(self.fault(format!(
            "hold: the arm still reports busy after {} sends over {:.2} s",
            c.max_sends,
            start.elapsed().as_secs_f64()
        )))
    }

    /// Send a command with `send` until `check` sees its effect: again every
    /// `resend_after_s` while the dVRK shows nothing, up to `max_sends` times in all; once it
    /// has answered (or the sends are spent), wait for the effect until `timeout`.
    fn confirmed(
        &self,
        what: &str,
        timeout: Duration,
        send: &dyn Fn() -> Result<(), RobotError>,
        check: &mut dyn FnMut(&Heard, &Sent) -> Check,
        describe: &dyn Fn(&Heard) -> String,
    ) -> Result<(), RobotError> {
        let c = &self.config;
        let first = Sent {
            state_seq: self.heard().state_seq,
            at: Instant::now(),
        };
        let deadline = first.at + timeout;
        let (mut sends, mut answered) = (0, false);
        loop {
            if !answered && sends < c.max_sends {
                if sends > 0 {
                    self.resent();
                }
                send()?;
                sends += 1;
            }
            let until = if answered || sends >= c.max_sends {
                deadline
            } else {
                deadline.min(Instant::now() + secs(c.resend_after_s))
            };
            let got = self.wait_until(until, |h| match check(h, &first) {
                Check::Waiting => None,
                Check::Answered if answered => None,
                other => Some(other),
            });
            match got {
                Some(Check::Done) => return Ok(()),
                Some(Check::Failed(e)) => return Err(self.fault(format!("{what}: {e}"))),
                Some(_) => answered = true,
                None if Instant::now() >= deadline => {
                    let heard = self.heard();
                    return Err(self.fault(format!(
                        "{what}: not done within {:.1} s, sent {sends} time(s){} ({})",
                        timeout.as_secs_f64(),
                        if answered {
                            ""
                        } else {
                            ": the dVRK never answered"
                        },
                        describe(&heard)
                    )));
                }
                None => {}
            }
        }
    }

    fn command_state(&self, command: &str) -> Result<(), RobotError> {
        self.state_command
            .publish(StringStamped {
                header: Self::stamp(),
                string: command.into(),
            })
            .map_err(|e| self.fault(e))
    }
}

/// What [`ArmLink::confirmed`] knew when it first sent a command.
struct Sent {
    state_seq: u64,
    at: Instant,
}

/// What the dVRK has shown of a command's effect so far.
enum Check {
    /// The effect: done.
    Done,
    /// The dVRK refused it or faulted.
    Failed(String),
    /// The dVRK answered (a new state) but the effect is not complete: no more sends.
    Answered,
    /// Nothing yet.
    Waiting,
}

/// Messages of a latched topic come no further apart than this in the burst of history the
/// console delivers when we join: its end is this long without one.
const LATCHED_QUIET: Duration = Duration::from_millis(100);

/// What an arm has said: see [`Ros2Dvrk::states`].
#[derive(Clone, Debug, PartialEq)]
pub struct ArmState {
    /// The arm, e.g. `PSM1`.
    pub name: String,
    /// Its last `operating_state`, if one came.
    pub operating: Option<OperatingState>,
    /// Every `error` of this connection, in order.
    pub errors: Vec<String>,
}

/// The dVRK over ROS 2: the bus and every arm it met.
#[derive(Debug)]
pub struct Ros2Dvrk {
    links: Vec<Arc<ArmLink>>,
    bus: Arc<Bus>,
}

impl Ros2Dvrk {
    /// Meet the arms on `options`' domain: subscribe to their state (`operating_state`
    /// reliable and transient-local), wait until the dVRK has matched every command topic
    /// (a command sent earlier is silently lost), enable and home each arm, waiting on its
    /// operating state, set the trajectory speed ratio, and wait for a fresh `measured_cp`.
    pub fn connect(options: &Ros2Options, config: &DvrkConfig) -> Result<Self, RobotError> {
        config.validate()?;
        let setup = |why: String| RobotError::Fault {
            arm: "ROS 2".into(),
            message: why,
        };
        let mut bus = Bus::new(options, "engine").map_err(setup)?;
        bus.set_linger(crate::ros2::HOLD_LINGER);
        let mut links = Vec::new();
        for arm in &config.arms {
            links.push(link_and_listen(&mut bus, arm, config).map_err(setup)?);
        }
        let bus = Arc::new(bus);
        let deadline = Instant::now() + secs(config.connect_timeout_s);
        for l in &links {
            let topics: [(&str, &dyn Matched); 6] = [
                (l.move_cp.name(), &l.move_cp),
                (l.servo_cp.name(), &l.servo_cp),
                (l.hold.name(), &l.hold),
                (l.state_command.name(), &l.state_command),
                (l.jaw_move_jp.name(), &l.jaw_move_jp),
                (l.set_ratio.name(), &l.set_ratio),
            ];
            let left = deadline.saturating_duration_since(Instant::now());
            let missing = bus.wait_matched(&topics, left);
            if !missing.is_empty() {
                return Err(l.fault(format!(
                    "no dVRK subscribed to {} within {} s on ROS_DOMAIN_ID {} ({}): is the dVRK \
                     console (or `stitch sim-node`) running on this domain, reachable, and of a \
                     compatible ROS 2 distribution?",
                    missing.join(", "),
                    config.connect_timeout_s,
                    options.domain_id,
                    crate::ros2::DISTRIBUTION
                )));
            }
            if l.wait_until(deadline, |h| h.state.clone()).is_none() {
                return Err(l.fault(format!(
                    "no operating_state from /{} within {} s",
                    l.name, config.connect_timeout_s
                )));
            }
            // The current state is the last of the console's latched history: wait for the
            // burst to end before reading it.
            let quiet = l.wait_until(deadline, |h| {
                h.latched_at
                    .is_none_or(|t| t.elapsed() >= LATCHED_QUIET)
                    .then_some(())
            });
            if quiet.is_none() {
                return Err(l.fault(format!(
                    "the latched topics of /{} never fell quiet for {} ms within {} s",
                    l.name,
                    LATCHED_QUIET.as_millis(),
                    config.connect_timeout_s
                )));
            }
        }
        for l in &links {
            bring_up(l)?;
            set_ratio(l)?;
            let deadline = Instant::now() + secs(config.connect_timeout_s);
            let fresh = l.wait_until(deadline, |h| {
                h.measured
                    .as_ref()
                    .filter(|(m, at)| {
                        !m.header.stamp.is_zero()
                            && at.elapsed().as_secs_f64() <= config.stale_after_s
                    })
                    .map(|_| ())
            });
            if fresh.is_none() {
                return Err(l.fault(format!(
                    "no fresh measured_cp from /{} within {} s",
                    l.name, config.connect_timeout_s
                )));
            }
        }
        Ok(Self { links, bus })
    }

    /// Whether every arm's `measured_cp` arrived within `bound` (the dVRK streams it all the
    /// time): `Err` names the silent arm.
    pub fn alive(&self, bound: Duration) -> Result<(), String> {
        for l in &self.links {
            let silent = l.heard().measured.as_ref().map(|(_, at)| at.elapsed());
            match silent {
                Some(s) if s <= bound => {}
                Some(s) => {
                    return Err(format!(
                        "no measured_cp from /{} for {:.2} s: the dVRK (or sim-node) is gone",
                        l.name,
                        s.as_secs_f64()
                    ));
                }
                None => return Err(format!("no measured_cp from /{} yet", l.name)),
            }
        }
        Ok(())
    }

    /// How many commands were sent again because the dVRK had not shown their effect.
    pub fn resends(&self) -> u64 {
        self.links
            .iter()
            .map(|l| l.resends.load(Ordering::Relaxed))
            .sum()
    }

    /// The `error`s the console had latched from before this connection: delivered when we
    /// joined, not counted (each names its arm's topic), for the run to say.
    pub fn ignored_history(&self) -> Vec<String> {
        self.links
            .iter()
            .flat_map(|l| {
                let name = l.name.clone();
                l.heard()
                    .ignored
                    .iter()
                    .map(move |e| format!("/{name}/error: {e}"))
                    .collect::<Vec<_>>()
            })
            .collect()
    }

    /// What each arm has said so far: its name, its last operating state and every `error`
    /// of this connection, in order (for a recorder to record as they change).
    pub fn states(&self) -> Vec<ArmState> {
        self.links
            .iter()
            .map(|l| {
                let h = l.heard();
                ArmState {
                    name: l.name.clone(),
                    operating: h.state.clone(),
                    errors: h.errors.clone(),
                }
            })
            .collect()
    }

    /// Send `hold` to every arm (an interrupted run): each is told whatever another
    /// answered; what failed, by arm (nothing else can be done about it but say it).
    pub fn hold_all(&self) -> Vec<String> {
        self.links
            .iter()
            .filter_map(|l| l.hold().err().map(|e| e.to_string()))
            .collect()
    }

    /// The arm `i` of the configuration's list (0: the right needle driver).
    pub fn arm(&self, i: usize) -> Option<Ros2Arm> {
        self.links.get(i).map(|l| Ros2Arm {
            link: Arc::clone(l),
            _bus: Arc::clone(&self.bus),
        })
    }

    /// The jaw of arm `i`.
    pub fn jaw(&self, i: usize) -> Option<Ros2Jaw> {
        self.links.get(i).map(|l| Ros2Jaw {
            name: format!("{}/jaw", l.name),
            link: Arc::clone(l),
            _bus: Arc::clone(&self.bus),
        })
    }

    /// Wait until every arm's `measured_cp` and `jaw/measured_js` stamped after now have
    /// arrived: after something moved the arms outside a motion command (a simulator's reset
    /// or a surgeon's recovery), so no reading from before is acted on.
    pub fn wait_fresh(&self, timeout: Duration) -> Result<(), RobotError> {
        let since = now_stamp().as_secs_f64();
        let deadline = Instant::now() + timeout;
        for l in &self.links {
            let newer = |t: &msg::Time| !t.is_zero() && t.as_secs_f64() >= since;
            let got = l.wait_until(deadline, |h| {
                let m = h
                    .measured
                    .as_ref()
                    .is_some_and(|(m, _)| newer(&m.header.stamp));
                let j = h.jaw.as_ref().is_some_and(|(m, _)| newer(&m.header.stamp));
                (m && j).then_some(())
            });
            if got.is_none() {
                return Err(l.fault(format!(
                    "no new measured_cp and jaw/measured_js within {:.1} s",
                    timeout.as_secs_f64()
                )));
            }
        }
        Ok(())
    }
}

/// Enable, then home, each confirmed by the operating state: resent while the dVRK answers
/// nothing (a first command can be lost: see [`ArmLink::confirmed`]), then waited on.
fn bring_up(l: &ArmLink) -> Result<(), RobotError> {
    let timeout = secs(l.config.state_timeout_s);
    let step = |command: &str, reached: &dyn Fn(&OperatingState) -> bool| {
        let already = l.heard().state.as_ref().is_some_and(reached);
        if already {
            return Ok(());
        }
        l.confirmed(
            command,
            timeout,
            &|| l.command_state(command),
            &mut |h, sent| {
                if let Some(e) = h.errors.get(h.errors_reported..).filter(|e| !e.is_empty()) {
                    return Check::Failed(format!("the dVRK reported: {}", e.join("; ")));
                }
                match &h.state {
                    Some(s) if reached(s) && !s.is_busy => Check::Done,
                    _ if h.state_seq > sent.state_seq => Check::Answered,
                    _ => Check::Waiting,
                }
            },
            &|h| format!("operating state {:?}", h.state),
        )
    };
    step("enable", &|s| s.state == "ENABLED")?;
    step("home", &|s| s.state == "ENABLED" && s.is_homed)
}

/// `trajectory_j/set_ratio`, confirmed by the dVRK's latched `trajectory_j/ratio` saying the
/// same after it was sent: a mission at the dVRK's own trajectory speed is refused.
fn set_ratio(l: &ArmLink) -> Result<(), RobotError> {
    let want = l.config.speed_ratio;
    l.confirmed(
        "trajectory_j/set_ratio",
        secs(l.config.connect_timeout_s),
        &|| {
            l.set_ratio
                .publish(Float64 { data: want })
                .map_err(|e| l.fault(e))
        },
        &mut |h, sent| match h.ratio {
            Some((r, at)) if at > sent.at && (r - want).abs() <= 1e-9 => Check::Done,
            _ => Check::Waiting,
        },
        &|h| match h.ratio {
            Some((r, _)) => format!("trajectory_j/ratio says {r}, not {want}"),
            None => "no trajectory_j/ratio heard: the dVRK 2.x console latches it".into(),
        },
    )
}

fn link(bus: &mut Bus, arm: &str, config: &DvrkConfig) -> Result<ArmLink, String> {
    let t = |topic: &str| format!("/{arm}/{topic}");
    let link = ArmLink {
        name: arm.to_string(),
        config: config.clone(),
        started_s: now_stamp().as_secs_f64(),
        resends: AtomicU64::new(0),
        heard: Mutex::new(Heard::default()),
        changed: Condvar::new(),
        move_cp: bus.publisher(&t("move_cp"), types::POSE_STAMPED, &stream_qos())?,
        servo_cp: bus.publisher(&t("servo_cp"), types::POSE_STAMPED, &stream_qos())?,
        hold: bus.publisher(&t("hold"), types::EMPTY, &stream_qos())?,
        state_command: bus.publisher(&t("state_command"), types::STRING_STAMPED, &stream_qos())?,
        jaw_move_jp: bus.publisher(&t("jaw/move_jp"), types::JOINT_STATE, &stream_qos())?,
        set_ratio: bus.publisher(&t("trajectory_j/set_ratio"), types::FLOAT64, &stream_qos())?,
    };
    Ok(link)
}

/// Subscribe `link`'s state topics; the handlers update what it heard.
fn listen(bus: &mut Bus, link: &Arc<ArmLink>) -> Result<(), String> {
    let arm = link.name.clone();
    let t = |topic: &str| format!("/{arm}/{topic}");
    fn on<M: Send + 'static>(
        link: &Arc<ArmLink>,
        apply: impl Fn(&mut Heard, M) + Send + 'static,
    ) -> impl FnMut(Result<M, String>) + Send + 'static {
        let link = Arc::clone(link);
        move |r| {
            {
                let mut heard = link.heard();
                match r {
                    Ok(m) => apply(&mut heard, m),
                    // A message from the dVRK that cannot be read is not dropped: it counts as
                    // an error, reported by the next command (as an `error` would be).
                    Err(e) => heard
                        .errors
                        .push(format!("a message it sent could not be read: {e}")),
                }
            }
            link.changed.notify_all();
        }
    }
    bus.subscribe(
        &t("measured_cp"),
        types::POSE_STAMPED,
        &stream_qos(),
        on(link, |h, m: PoseStamped| {
            h.measured = Some((m, Instant::now()))
        }),
    )?;
    bus.subscribe(
        &t("setpoint_cp"),
        types::POSE_STAMPED,
        &stream_qos(),
        on(link, |h, m: PoseStamped| {
            h.setpoint = Some((m, Instant::now()))
        }),
    )?;
    bus.subscribe(
        &t("jaw/measured_js"),
        types::JOINT_STATE,
        &stream_qos(),
        on(link, |h, m: JointState| h.jaw = Some((m, Instant::now()))),
    )?;
    bus.subscribe(
        &t("operating_state"),
        types::OPERATING_STATE,
        &latched_qos(),
        on(link, |h, m: OperatingState| {
            h.latched_at = Some(Instant::now());
            h.state_seq += 1;
            if m.is_busy {
                h.busy_seq = h.state_seq;
            }
            h.state = Some(m);
        }),
    )?;
    // Only errors of this connection count. The console latches `error` (transient local,
    // depth 100) and RustDDS hands even a volatile reader the writer's history, so an error
    // is judged by when its writer wrote it (the DDS source timestamp): before this
    // connection began (less the clock tolerance the stale bound already grants the dVRK's
    // stamps) it is history. One with no source timestamp counts: better a spurious failure
    // than a missed fault.
    let (started_s, tolerance_s) = (link.started_s, link.config.stale_after_s);
    bus.subscribe_stamped(
        &t("error"),
        types::STRING,
        &stream_qos(),
        on(link, move |h, m: Stamped<msg::StringMsg>| {
            h.latched_at = Some(Instant::now());
            match m.source_s {
                Some(at) if at < started_s - tolerance_s => h.ignored.push(format!(
                    "{} (written {:.1} s before this connection)",
                    m.message.data,
                    started_s - at
                )),
                _ => h.errors.push(m.message.data),
            }
        }),
    )?;
    bus.subscribe(
        &t("trajectory_j/ratio"),
        types::FLOAT64,
        &latched_qos(),
        on(link, |h, m: Float64| {
            h.latched_at = Some(Instant::now());
            h.ratio = Some((m.data, Instant::now()));
        }),
    )?;
    Ok(())
}

// `link` builds the publishers, `listen` the subscriptions; both before the bus is shared.
fn link_and_listen(bus: &mut Bus, arm: &str, config: &DvrkConfig) -> Result<Arc<ArmLink>, String> {
    let l = Arc::new(link(bus, arm, config)?);
    listen(bus, &l)?;
    Ok(l)
}

/// What a tracked motion is for.
#[derive(Clone, Copy, Debug)]
enum Goal {
    Pose(Pose),
    Jaw { angle_rad: f64, opening: bool },
}

/// One motion: the operating-state messages before it was sent, when it was sent, its goal.
#[derive(Debug)]
struct Motion {
    link: Arc<ArmLink>,
    goal: Goal,
    state_seq: u64,
    sent_stamp: f64,
    sent: Instant,
}

impl Motion {
    fn start(link: &Arc<ArmLink>, goal: Goal) -> Self {
        let state_seq = link.heard().state_seq;
        Self {
            link: Arc::clone(link),
            goal,
            state_seq,
            sent_stamp: now_stamp().as_secs_f64(),
            sent: Instant::now(),
        }
    }

    /// Send the motion's command (again, when busy has not risen: the same goal).
    fn send(&self) -> Result<(), RobotError> {
        let l = &self.link;
        match self.goal {
            Goal::Pose(goal) => l
                .move_cp
                .publish(crate::pose_to_msg(&goal, now_stamp(), "")),
            Goal::Jaw { angle_rad, .. } => l.jaw_move_jp.publish(JointState {
                header: ArmLink::stamp(),
                name: vec!["jaw".into()],
                position: vec![angle_rad],
                velocity: vec![],
                effort: vec![],
            }),
        }
        .map_err(|e| l.fault(e))
    }

    /// Whether a measurement stamped at or after `idle_s` (the idle state's stamp) is at the
    /// goal.
    fn within(&self, heard: &Heard, idle_s: f64) -> Option<Result<(), String>> {
        let c = &self.link.config;
        match self.goal {
            Goal::Pose(goal) => {
                let (m, at) = heard.measured.as_ref()?;
                if *at < self.sent
                    || m.header.stamp.is_zero()
                    || m.header.stamp.as_secs_f64() < idle_s
                {
                    return None;
                }
                let pose = match crate::pose_from_msg(m) {
                    Ok(p) => p,
                    Err(e) => return Some(Err(format!("measured_cp: {e}"))),
                };
                let d = (pose.translation.vector - goal.translation.vector).norm();
                let a = pose.rotation.angle_to(&goal.rotation);
                (d <= c.position_tolerance_m && a <= c.rotation_tolerance_rad).then_some(Ok(()))
            }
            Goal::Jaw { angle_rad, opening } => {
                let (m, at) = heard.jaw.as_ref()?;
                if *at < self.sent
                    || m.header.stamp.is_zero()
                    || m.header.stamp.as_secs_f64() < idle_s
                {
                    return None;
                }
                let v = *m.position.first()?;
                (!opening || v >= angle_rad - c.jaw_tolerance_rad).then_some(Ok(()))
            }
        }
    }

    fn describe_miss(&self, heard: &Heard) -> String {
        match self.goal {
            Goal::Pose(goal) => match heard
                .measured
                .as_ref()
                .map(|(m, _)| crate::pose_from_msg(m))
            {
                Some(Ok(p)) => format!(
                    "ended {:.2} mm and {:.2}° from the goal (tolerance {:.2} mm, {:.2}°)",
                    (p.translation.vector - goal.translation.vector).norm() * 1e3,
                    p.rotation.angle_to(&goal.rotation).to_degrees(),
                    self.link.config.position_tolerance_m * 1e3,
                    self.link.config.rotation_tolerance_rad.to_degrees()
                ),
                Some(Err(e)) => format!("measured_cp: {e}"),
                None => "no measured_cp".into(),
            },
            Goal::Jaw { angle_rad, .. } => format!(
                "jaw at {:?} rad, goal {angle_rad:.3} rad",
                heard.jaw.as_ref().map(|(m, _)| m.position.clone())
            ),
        }
    }

    /// Wait until `until` for busy to rise, or a newer idle state (`Ok(Some(its stamp))`),
    /// or an error (`Err(None)`), or silence (`Err(Some(silent s))`).
    #[allow(clippy::type_complexity)]
    fn rose(&self, until: Instant) -> Option<Result<Option<f64>, Option<f64>>> {
        let l = &self.link;
        l.wait_until(until, |h| {
            if h.faulted() {
                return Some(Err(None));
            }
            if let Some(silent_s) = l.silent_s(h) {
                return Some(Err(Some(silent_s)));
            }
            let newer = h.state_seq > self.state_seq;
            let busy = h.busy_seq > self.state_seq;
            let idle_after = h
                .state
                .as_ref()
                .filter(|s| newer && !s.is_busy && s.header.stamp.as_secs_f64() >= self.sent_stamp);
            match (busy, idle_after) {
                (_, Some(s)) => Some(Ok(Some(s.header.stamp.as_secs_f64()))),
                (true, None) => Some(Ok(None)),
                _ => None,
            }
        })
    }

    /// Busy up, then down, within the timeouts; then the goal within tolerance.
    fn run(&self) -> Result<(), RobotError> {
        let l = &self.link;
        let c = &l.config;
        let what = match self.goal {
            Goal::Pose(_) => "move_cp",
            Goal::Jaw { .. } => "jaw/move_jp",
        };
        // 1. Busy rises (or a newer idle state already reports the move done), unless an
        //    error comes first; while neither shows, the command is sent again every
        //    `resend_after_s`, up to `max_sends` times, within the rise timeout.
        let rise = self.sent + secs(c.busy_rise_timeout_s);
        let mut sends = 1;
        let rose = loop {
            let until = if sends < c.max_sends {
                rise.min(Instant::now() + secs(c.resend_after_s))
            } else {
                rise
            };
            let got = self.rose(until);
            if got.is_some() || Instant::now() >= rise {
                break got;
            }
            if sends < c.max_sends {
                l.resent();
                self.send()?;
                sends += 1;
            }
        };
        let idle_already = match rose {
            Some(Ok(idle)) => idle,
            Some(Err(None)) => {
                let e = l.new_error(&mut l.heard());
                return Err(e.unwrap_or_else(|| l.fault(format!("{what}: failed"))));
            }
            Some(Err(Some(silent_s))) => {
                let _ = l.hold();
                return Err(l.fault(format!(
                    "{what}: the dVRK went silent before the move began (no measured_cp for \
                     {silent_s:.2} s, bound {} s): holding",
                    c.stale_after_s
                )));
            }
            None => {
                // No busy at all: done only if already there (a move to where it is).
                let heard = l.heard();
                if self.within(&heard, 0.0).is_some_and(|r| r.is_ok()) {
                    return Ok(());
                }
                let miss = self.describe_miss(&heard);
                drop(heard);
                let _ = l.hold();
                return Err(l.fault(format!(
                    "{what}: the arm never reported busy within {} s ({sends} sends) and is not \
                     at the goal ({miss}): the command was lost or refused; holding",
                    c.busy_rise_timeout_s
                )));
            }
        };
        // 2. Busy falls.
        let limit = secs(c.move_timeout_s);
        let fall = self.sent + limit;
        let fell = match idle_already {
            Some(idle) => Some(Ok(idle)),
            None => l.wait_until(fall, |h| {
                if h.faulted() {
                    return Some(Err(None));
                }
                if let Some(silent_s) = l.silent_s(h) {
                    return Some(Err(Some(silent_s)));
                }
                h.state
                    .as_ref()
                    .filter(|s| !s.is_busy)
                    .map(|s| Ok(s.header.stamp.as_secs_f64()))
            }),
        };
        let idle_s = match fell {
            Some(Ok(idle)) => idle,
            Some(Err(Some(silent_s))) => {
                let _ = l.hold();
                return Err(l.fault(format!(
                    "{what}: the dVRK went silent mid-move (no measured_cp for {silent_s:.2} s, \
                     bound {} s): holding",
                    c.stale_after_s
                )));
            }
            Some(Err(None)) => {
                let _ = l.hold();
                let e = l.new_error(&mut l.heard());
                return Err(e.unwrap_or_else(|| l.fault(format!("{what}: failed"))));
            }
            None => {
                let _ = l.hold();
                return Err(RobotError::Timeout {
                    arm: l.name.clone(),
                    after_s: limit.as_secs_f64(),
                });
            }
        };
        // 3. A measurement taken after the arm went idle is at the goal (measurements and
        //    states travel on different topics: either may arrive first).
        let settle = Instant::now() + secs(c.settle_timeout_s);
        let settled = l.wait_until(settle, |h| self.within(h, idle_s));
        match settled {
            Some(Ok(())) => Ok(()),
            Some(Err(e)) => Err(l.fault(format!("{what}: {e}"))),
            None => {
                let heard = l.heard();
                // Say stale or invalid data for what it is.
                let fresh = match self.goal {
                    Goal::Pose(_) => l
                        .fresh("measured_cp", &heard.measured, |m| m.header.stamp)
                        .map(|_| ()),
                    Goal::Jaw { .. } => l
                        .fresh("jaw/measured_js", &heard.jaw, |m| m.header.stamp)
                        .map(|_| ()),
                };
                fresh?;
                Err(l.fault(format!(
                    "{what}: busy fell but the arm {}",
                    self.describe_miss(&heard)
                )))
            }
        }
    }
}

/// A motion verified by a thread of its own, so that its caller can wait in slices and act
/// between them (a supervisor's command mid-move stops it with a hold): the verification
/// (busy up, busy down, at the goal) runs once, whole, as a single wait would run it.
#[derive(Debug)]
struct Watched {
    motion: Arc<Motion>,
    result: Arc<Verdict>,
    started: std::sync::Once,
}

/// A motion's verdict, once its check has run, and a signal for those waiting on it.
type Verdict = (Mutex<Option<Result<(), RobotError>>>, Condvar);

impl Watched {
    fn new(motion: Motion) -> Self {
        Self {
            motion: Arc::new(motion),
            result: Arc::new((Mutex::new(None), Condvar::new())),
            started: std::sync::Once::new(),
        }
    }

    fn start(&self) {
        self.started.call_once(|| {
            let motion = Arc::clone(&self.motion);
            let result = Arc::clone(&self.result);
            let verify = move || {
                let r = motion.run();
                let (slot, ready) = &*result;
                *slot.lock().unwrap_or_else(PoisonError::into_inner) = Some(r);
                ready.notify_all();
            };
            // Without a thread, the first wait verifies the motion whole.
            let spawned = std::thread::Builder::new()
                .name("dvrk-motion".into())
                .spawn(verify.clone());
            if spawned.is_err() {
                verify();
            }
        });
    }
}

impl MotionTracker for Watched {
    fn is_busy(&self) -> bool {
        self.result
            .0
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .is_none()
    }

    fn wait(&self, timeout: Duration) -> Result<(), RobotError> {
        self.start();
        let (slot, ready) = &*self.result;
        let guard = slot.lock().unwrap_or_else(PoisonError::into_inner);
        // A day is as long as forever here, and keeps the deadline representable.
        let limit = timeout.min(Duration::from_secs(86_400));
        let (guard, _) = ready
            .wait_timeout_while(guard, limit, |r| r.is_none())
            .unwrap_or_else(PoisonError::into_inner);
        match guard.as_ref() {
            Some(r) => r.clone(),
            None => Err(RobotError::Timeout {
                arm: self.motion.link.name.clone(),
                after_s: timeout.as_secs_f64(),
            }),
        }
    }

    fn stop(&self) -> Result<(), RobotError> {
        self.motion.link.hold()
    }
}

/// One dVRK arm (a PSM) over ROS 2.
#[derive(Debug, Clone)]
pub struct Ros2Arm {
    link: Arc<ArmLink>,
    _bus: Arc<Bus>,
}

impl Arm for Ros2Arm {
    fn name(&self) -> &str {
        &self.link.name
    }

    fn measured_cp(&self) -> Result<Pose, RobotError> {
        self.link.measured_cp()
    }

    fn setpoint_cp(&self) -> Result<Pose, RobotError> {
        let m = self
            .link
            .read_fresh("setpoint_cp", |h| &h.setpoint, |m| m.header.stamp)?;
        crate::pose_from_msg(&m).map_err(|e| self.link.fault(format!("setpoint_cp: {e}")))
    }

    fn move_cp(&self, goal: &Pose) -> Result<MoveHandle, RobotError> {
        stitch_robot::finite_pose(&self.link.name, goal)?;
        self.link.ready()?;
        let motion = Motion::start(&self.link, Goal::Pose(*goal));
        motion.send()?;
        Ok(MoveHandle::new(Arc::new(Watched::new(motion))))
    }

    fn servo_cp(&self, goal: &Pose) -> Result<(), RobotError> {
        stitch_robot::finite_pose(&self.link.name, goal)?;
        self.link.ready()?;
        self.link
            .servo_cp
            .publish(crate::pose_to_msg(goal, now_stamp(), ""))
            .map_err(|e| self.link.fault(e))
    }

    fn hold(&self) -> Result<(), RobotError> {
        self.link.hold()
    }
}

/// One PSM's jaw over ROS 2 (`jaw/move_jp`, `jaw/measured_js`).
#[derive(Debug, Clone)]
pub struct Ros2Jaw {
    name: String,
    link: Arc<ArmLink>,
    _bus: Arc<Bus>,
}

impl Jaw for Ros2Jaw {
    fn name(&self) -> &str {
        &self.name
    }

    fn measured_jp(&self) -> Result<f64, RobotError> {
        self.link.measured_jaw()
    }

    fn move_jp(&self, angle_rad: f64) -> Result<MoveHandle, RobotError> {
        if !angle_rad.is_finite() {
            return Err(RobotError::NonFinite {
                arm: self.name.clone(),
                what: "jaw angle".into(),
            });
        }
        self.link.ready()?;
        let before = self.link.measured_jaw()?;
        let motion = Motion::start(
            &self.link,
            Goal::Jaw {
                angle_rad,
                opening: angle_rad > before,
            },
        );
        motion.send()?;
        Ok(MoveHandle::new(Arc::new(Watched::new(motion))))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn measured_at(age_s: f64) -> Option<(PoseStamped, Instant)> {
        let t = now_stamp().as_secs_f64() - age_s;
        let stamp = msg::Time {
            sec: t.floor() as i32,
            nanosec: (t.fract() * 1e9) as u32,
        };
        let mut m = PoseStamped::default();
        m.header.stamp = stamp;
        m.pose.orientation.w = 1.0;
        Some((m, Instant::now()))
    }

    fn read(heard: &Mutex<Heard>, cv: &Condvar) -> Result<PoseStamped, RobotError> {
        read_fresh(
            "PSM1",
            &DvrkConfig::default(),
            (heard, cv),
            "measured_cp",
            |h| &h.measured,
            |m| m.header.stamp,
        )
    }

    #[test]
    fn a_measurement_delivered_late_is_waited_for_and_one_that_stays_stale_is_refused() {
        // Stale now (0.4 s old, bound 0.25 s); a fresh one arrives 100 ms later, within
        // the 0.5 s wait: the read returns the fresh one.
        let shared = Arc::new((
            Mutex::new(Heard {
                measured: measured_at(0.4),
                ..Heard::default()
            }),
            Condvar::new(),
        ));
        let other = Arc::clone(&shared);
        let late = std::thread::spawn(move || {
            std::thread::sleep(Duration::from_millis(100));
            other.0.lock().expect("lock").measured = measured_at(0.0);
            other.1.notify_all();
        });
        let m = read(&shared.0, &shared.1).expect("the late measurement");
        assert!(crate::ros2::stamp_age_s(&m.header.stamp) < 0.25);
        late.join().expect("thread");
        // Nothing newer comes: refused as stale once the wait is over, not before.
        let stale = Mutex::new(Heard {
            measured: measured_at(0.4),
            ..Heard::default()
        });
        let t0 = Instant::now();
        let e = read(&stale, &Condvar::new()).expect_err("stale");
        assert!(matches!(e, RobotError::Stale { .. }), "{e}");
        assert!(
            t0.elapsed() >= Duration::from_millis(450),
            "{:?}",
            t0.elapsed()
        );
        // Invalid data (a zero stamp) is refused at once.
        let mut zero = measured_at(0.0);
        if let Some((m, _)) = zero.as_mut() {
            m.header.stamp = msg::Time::default();
        }
        let t0 = Instant::now();
        let e = read(
            &Mutex::new(Heard {
                measured: zero,
                ..Heard::default()
            }),
            &Condvar::new(),
        )
        .expect_err("zero stamp");
        assert!(e.to_string().contains("zero stamp"), "{e}");
        assert!(t0.elapsed() < Duration::from_millis(200));
    }

    #[test]
    fn the_defaults_are_valid_and_bad_values_are_named() {
        DvrkConfig::default().validate().expect("defaults");
        for (config, name) in [
            (
                DvrkConfig {
                    stale_after_s: 0.0,
                    ..DvrkConfig::default()
                },
                "dvrk.stale_after_s",
            ),
            (
                DvrkConfig {
                    speed_ratio: 1.5,
                    ..DvrkConfig::default()
                },
                "dvrk.speed_ratio",
            ),
            (
                DvrkConfig {
                    position_tolerance_m: f64::NAN,
                    ..DvrkConfig::default()
                },
                "dvrk.position_tolerance_m",
            ),
            (
                DvrkConfig {
                    arms: ["PSM1".into(), "bad name!".into()],
                    ..DvrkConfig::default()
                },
                "dvrk.arms",
            ),
        ] {
            let e = config.validate().expect_err(name).to_string();
            assert!(e.contains(name), "{e}");
        }
    }
}
