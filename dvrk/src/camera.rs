//! The stereo camera over ROS 2: left and right `sensor_msgs/Image` with their
//! `sensor_msgs/CameraInfo`, behind the `robot/` [`StereoCamera`] trait.
//!
//! [`Ros2Camera::connect`] reads the rectified pair's calibration from the two `camera_info`
//! topics (intrinsics from the left projection matrix P, the baseline from the right one's
//! `P[0][3] = −fx·B`) and takes the hand-eye calibration (the rectified left camera's frame
//! in the robot frame) from the configuration, since `camera_info` does not carry it. A
//! capture is the first left and right images that both arrived after the call, stamped
//! within [`CameraSettings::max_pair_skew_s`] of each other, fresh and non-zero, of the size
//! and calibration the camera connected with; each side's last few images are kept, so a
//! right stream that lags the left by a frame still pairs.
//!
//! A real camera streams; the simulator renders on demand, so a capture can first pull a
//! trigger ([`Trigger`]) that makes it render and publish one pair, and names that pair's
//! stamp.

use crate::msg::{self, CameraInfo, Image};
use crate::ros2::{Bus, Ros2Options, stamp_age_s, types};
use ros2_client::QosProfile;
use ros2_client::qos::{History, WhenFull};
use serde::{Deserialize, Serialize};
use std::sync::{Arc, Condvar, Mutex, MutexGuard, PoisonError};
use std::time::{Duration, Instant};
use stitch_robot::nalgebra;
use stitch_robot::{
    Clock, Pose, RgbImage, RobotError, StereoCalibration, StereoCamera, StereoFrame,
};

/// Where the stereo camera publishes and what a capture accepts. Times in seconds.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CameraSettings {
    /// The rectified left image (`sensor_msgs/Image`).
    pub left_image: String,
    /// The left camera's `sensor_msgs/CameraInfo`.
    pub left_info: String,
    /// The rectified right image.
    pub right_image: String,
    /// The right camera's `CameraInfo`.
    pub right_info: String,
    /// Subscribe best effort (`false`, the default: matches every publisher, reliable or
    /// not; a frame that loses a fragment on the way is dropped, not repaired, and the next
    /// one is taken) or reliable (matches reliable publishers only; repairs take up to a
    /// heartbeat period, about a second, for a large image).
    pub reliable: bool,
    /// How long a capture waits for its pair.
    pub capture_timeout_s: f64,
    /// Streamed images older than this by stamp are refused (a triggered pair is the one
    /// asked for).
    pub stale_after_s: f64,
    /// How far apart the left and right stamps of one pair may be.
    pub max_pair_skew_s: f64,
    /// The rectified left camera's frame in the robot frame (hand-eye calibration). Required
    /// on a real dVRK; against `stitch sim-node` the mock camera's own is the default.
    pub camera_to_robot: Option<HandEye>,
}

impl Default for CameraSettings {
    fn default() -> Self {
        Self {
            left_image: "/stereo/left/image_rect_color".into(),
            left_info: "/stereo/left/camera_info".into(),
            right_image: "/stereo/right/image_rect_color".into(),
            right_info: "/stereo/right/camera_info".into(),
            reliable: false,
            capture_timeout_s: 2.0,
            stale_after_s: 1.0,
            max_pair_skew_s: 0.02,
            camera_to_robot: None,
        }
    }
}

/// A hand-eye calibration as written in a configuration file.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct HandEye {
    /// The camera's origin in the robot frame, m.
    pub translation_m: [f64; 3],
    /// Its rotation, a unit quaternion (x, y, z, w) as ROS writes it.
    pub rotation_xyzw: [f64; 4],
}

impl HandEye {
    /// The pose, or why these numbers are not one.
    pub fn pose(&self) -> Result<Pose, String> {
        let [x, y, z, w] = self.rotation_xyzw;
        let t = self.translation_m;
        if !(t.iter().chain(&self.rotation_xyzw).all(|v| v.is_finite())) {
            return Err("not finite".into());
        }
        let q = nalgebra::Quaternion::new(w, x, y, z);
        if (q.norm() - 1.0).abs() > 1e-6 {
            return Err(format!(
                "rotation_xyzw {:?} has norm {}; expected a unit quaternion",
                self.rotation_xyzw,
                q.norm()
            ));
        }
        Ok(Pose::from_parts(
            nalgebra::Translation3::new(t[0], t[1], t[2]),
            nalgebra::UnitQuaternion::from_quaternion(q),
        ))
    }

    /// The numbers of `pose`.
    pub fn from_pose(pose: &Pose) -> Self {
        let q = pose.rotation.quaternion();
        let t = pose.translation.vector;
        Self {
            translation_m: [t.x, t.y, t.z],
            rotation_xyzw: [q.i, q.j, q.k, q.w],
        }
    }
}

impl CameraSettings {
    /// Refuse values the camera cannot use, naming them (`dvrk.camera.<key>`).
    pub fn validate(&self) -> Result<(), RobotError> {
        let bad = |what: &str, why: String| {
            Err(RobotError::InvalidConfig {
                what: format!("dvrk.camera.{what}"),
                why,
            })
        };
        for (name, t) in [
            ("left_image", &self.left_image),
            ("left_info", &self.left_info),
            ("right_image", &self.right_image),
            ("right_info", &self.right_info),
        ] {
            if crate::ros2::topic_name(t).is_err() || !t.starts_with('/') {
                return bad(
                    name,
                    format!("{t:?}; expected an absolute ROS 2 topic name"),
                );
            }
        }
        for (name, v, max) in [
            ("capture_timeout_s", self.capture_timeout_s, 60.0),
            ("stale_after_s", self.stale_after_s, 60.0),
            ("max_pair_skew_s", self.max_pair_skew_s, 1.0),
        ] {
            if !(v.is_finite() && (0.0..=max).contains(&v))
                || (v == 0.0 && name != "max_pair_skew_s")
            {
                return bad(name, format!("{v}; expected above 0, at most {max} s"));
            }
        }
        if let Some(h) = &self.camera_to_robot
            && let Err(why) = h.pose()
        {
            return bad("camera_to_robot", why);
        }
        Ok(())
    }

    fn qos(&self) -> QosProfile {
        let q = QosProfile::publisher_default().history(History::KeepLast { depth: 1 });
        if self.reliable {
            q.reliability_reliable(WhenFull::DEFAULT)
        } else {
            q.reliability_best_effort()
        }
    }
}

/// QoS the simulator publishes images and camera info with: reliable (the pair must arrive
/// whole), the latest only (a 1280×960 pair is 7 MB).
pub fn publisher_qos() -> QosProfile {
    QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .history(History::KeepLast { depth: 1 })
}

/// An image as ROS sends it: 8-bit RGB, `step = 3 · width`.
pub fn image_msg(image: &RgbImage, stamp: msg::Time, frame_id: &str) -> Image {
    Image {
        header: msg::Header {
            stamp,
            frame_id: frame_id.into(),
        },
        height: image.height,
        width: image.width,
        encoding: "rgb8".into(),
        is_bigendian: 0,
        step: image.width * 3,
        data: image.data.clone(),
    }
}

/// An image from the wire as 8-bit RGB: `rgb8`, `bgr8`, `rgba8` or `bgra8`, any row padding;
/// anything else is refused with what it is.
pub fn rgb_from_image(m: &Image, topic: &str) -> Result<RgbImage, String> {
    let (bpp, order): (usize, [usize; 3]) = match m.encoding.as_str() {
        "rgb8" => (3, [0, 1, 2]),
        "bgr8" => (3, [2, 1, 0]),
        "rgba8" => (4, [0, 1, 2]),
        "bgra8" => (4, [2, 1, 0]),
        other => {
            return Err(format!(
                "{topic}: encoding {other:?}; expected rgb8, bgr8, rgba8 or bgra8 (colour is \
                 what finds the needle)"
            ));
        }
    };
    let (w, h, step) = (m.width as usize, m.height as usize, m.step as usize);
    if w == 0 || h == 0 || w > 16_384 || h > 16_384 {
        return Err(format!(
            "{topic}: image size {}×{}; expected 1 to 16384 pixels a side",
            m.width, m.height
        ));
    }
    if step < w * bpp {
        return Err(format!(
            "{topic}: step {step} bytes is less than a {w}-pixel {} row ({} bytes)",
            m.encoding,
            w * bpp
        ));
    }
    if m.data.len() != step * h {
        return Err(format!(
            "{topic}: {} bytes of data; step {step} × {h} rows needs {}",
            m.data.len(),
            step * h
        ));
    }
    let mut data = Vec::with_capacity(w * h * 3);
    if bpp == 3 && order == [0, 1, 2] && step == w * 3 {
        data.extend_from_slice(&m.data);
    } else {
        for row in m.data.chunks_exact(step) {
            for px in row[..w * bpp].chunks_exact(bpp) {
                data.extend(order.iter().map(|&c| px[c]));
            }
        }
    }
    Ok(RgbImage {
        width: m.width,
        height: m.height,
        data,
    })
}

/// The right camera's `P[0][3]` for `calibration`: `−fx·B`, nudged by a few units in the
/// last place so that `−P[0][3] / fx` gives back `B` exactly where some value does (the
/// baseline then crosses the wire bit for bit, and a simulated run stays the in-process
/// mock's twin), else as closely as any (one unit in B's last place).
fn right_tx(c: &StereoCalibration) -> f64 {
    let product = -c.fx * c.baseline_m;
    let miss = |p: f64| (-p / c.fx - c.baseline_m).abs();
    // Neighbours by bit pattern (`f64::next_up` is newer than the MSRV): for a finite
    // non-zero value, ±1 in its bits is one unit in the last place either way.
    let mut best = product;
    for k in 1..=8_u64 {
        for bits in [product.to_bits() - k, product.to_bits() + k] {
            let p = f64::from_bits(bits);
            if miss(p) < miss(best) {
                best = p;
            }
        }
    }
    best
}

/// The `camera_info` of one side of a rectified pair: K and P from the shared intrinsics,
/// R the identity, no distortion (the images are rectified), and for the right camera
/// `P[0][3] = −fx·B`.
pub fn camera_info_msg(
    c: &StereoCalibration,
    right: bool,
    stamp: msg::Time,
    frame_id: &str,
) -> CameraInfo {
    let tx = if right { right_tx(c) } else { 0.0 };
    CameraInfo {
        header: msg::Header {
            stamp,
            frame_id: frame_id.into(),
        },
        height: c.height,
        width: c.width,
        distortion_model: "plumb_bob".into(),
        d: vec![0.0; 5],
        k: [c.fx, 0.0, c.cx, 0.0, c.fy, c.cy, 0.0, 0.0, 1.0],
        r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p: [
            c.fx, 0.0, c.cx, tx, 0.0, c.fy, c.cy, 0.0, 0.0, 0.0, 1.0, 0.0,
        ],
        binning_x: 0,
        binning_y: 0,
        roi: msg::RegionOfInterest::default(),
    }
}

/// The rectified pair's calibration from its two `camera_info`s and the hand-eye pose, or
/// what about them this backend cannot use.
pub fn calibration_from_info(
    left: &CameraInfo,
    right: &CameraInfo,
    camera_to_robot: Pose,
) -> Result<StereoCalibration, String> {
    for (side, i) in [("left", left), ("right", right)] {
        if i.binning_x > 1 || i.binning_y > 1 {
            return Err(format!(
                "{side} camera_info: binning {}×{}; expected none",
                i.binning_x, i.binning_y
            ));
        }
        let roi = &i.roi;
        if roi.width != 0 && (roi.width, roi.height) != (i.width, i.height) {
            return Err(format!(
                "{side} camera_info: region of interest {}×{} at ({}, {}); expected the whole \
                 {}×{} image",
                roi.width, roi.height, roi.x_offset, roi.y_offset, i.width, i.height
            ));
        }
        if !i.p.iter().all(|v| v.is_finite()) || i.p[0] <= 0.0 || i.p[5] <= 0.0 {
            return Err(format!(
                "{side} camera_info: projection P {:?} has no positive focal lengths (is the \
                 camera calibrated?)",
                i.p
            ));
        }
        if i.p[7] != 0.0 {
            return Err(format!(
                "{side} camera_info: P[1][3] = {}; expected a horizontal pair (0)",
                i.p[7]
            ));
        }
    }
    if (left.width, left.height) != (right.width, right.height) {
        return Err(format!(
            "left camera_info is {}×{}, right {}×{}; a rectified pair has one size",
            left.width, left.height, right.width, right.height
        ));
    }
    let (l, r) = (&left.p, &right.p);
    let differ = |a: f64, b: f64| (a - b).abs() > 1e-6 * a.abs().max(1.0);
    for (name, a, b) in [
        ("fx", l[0], r[0]),
        ("fy", l[5], r[5]),
        ("cx", l[2], r[2]),
        ("cy", l[6], r[6]),
    ] {
        if differ(a, b) {
            return Err(format!(
                "the rectified pair's {name} differ (left {a}, right {b}): expected one set of \
                 intrinsics (rectify with zero disparity, e.g. OpenCV's CALIB_ZERO_DISPARITY)"
            ));
        }
    }
    if l[3] != 0.0 {
        return Err(format!(
            "left camera_info: P[0][3] = {}; expected 0 (the left camera is the pair's \
             origin){}",
            l[3],
            if r[3] == 0.0 {
                "; are left and right swapped?"
            } else {
                ""
            }
        ));
    }
    if r[3] >= 0.0 {
        return Err(format!(
            "right camera_info: P[0][3] = {}; expected −fx·baseline < 0 (are left and right \
             swapped?)",
            r[3]
        ));
    }
    let calibration = StereoCalibration {
        fx: l[0],
        fy: l[5],
        cx: l[2],
        cy: l[6],
        baseline_m: -r[3] / r[0],
        width: left.width,
        height: left.height,
        camera_to_robot,
    };
    calibration.validate().map_err(|e| e.to_string())?;
    Ok(calibration)
}

/// Makes the camera publish a pair on demand (the simulator's; a real camera streams and
/// needs none).
pub trait Trigger: Send + Sync {
    /// Publish a new pair; its stamp.
    fn fire(&self) -> Result<msg::Time, String>;
    /// Publish the pair stamped `stamp` again: it did not arrive whole (a best-effort reader
    /// is not repaired). The same pair, so a simulated run stays deterministic.
    fn resend(&self, stamp: msg::Time) -> Result<(), String>;
}

/// How long a capture waits for a triggered pair before asking for it again.
pub const RESEND_AFTER: Duration = Duration::from_millis(250);

/// Images kept per side while a capture looks for a pair: a right stream that lags the left
/// by a frame or two still pairs with the left image of its own stamp, which a slot holding
/// only the latest would have overwritten (three 1080p images a side are about 19 MB).
const IMAGES_KEPT: usize = 3;

/// What the camera's topics said, as the bus thread received it.
#[derive(Debug, Default)]
struct Heard {
    /// Each side's latest images with when they arrived, oldest first.
    images: [std::collections::VecDeque<(Image, Instant)>; 2],
    infos: [Option<(CameraInfo, Instant)>; 2],
    unreadable: Option<String>,
}

/// The stereo camera over ROS 2.
pub struct Ros2Camera {
    calibration: StereoCalibration,
    settings: CameraSettings,
    heard: Arc<(Mutex<Heard>, Condvar)>,
    trigger: Option<Box<dyn Trigger>>,
    clock: Arc<dyn Clock>,
    _bus: Bus,
}

impl std::fmt::Debug for Ros2Camera {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Ros2Camera")
            .field("left_image", &self.settings.left_image)
            .field("right_image", &self.settings.right_image)
            .field("triggered", &self.trigger.is_some())
            .finish_non_exhaustive()
    }
}

fn camera_fault(message: String) -> RobotError {
    RobotError::Fault {
        arm: "stereo camera".into(),
        message,
    }
}

impl Ros2Camera {
    /// Subscribe to the pair's images and camera info on `options`' domain and wait, at most
    /// `timeout`, for both `camera_info`s; the calibration is theirs with `camera_to_robot`.
    /// Captures stamp frames on `clock` (the run's).
    pub fn connect(
        options: &Ros2Options,
        settings: &CameraSettings,
        camera_to_robot: Pose,
        trigger: Option<Box<dyn Trigger>>,
        clock: Arc<dyn Clock>,
        timeout: Duration,
    ) -> Result<Self, RobotError> {
        settings.validate()?;
        let mut bus = Bus::new(options, "stereo_camera").map_err(camera_fault)?;
        // It only listens: nothing to deliver when dropped.
        bus.set_linger(Duration::ZERO);
        let heard: Arc<(Mutex<Heard>, Condvar)> = Arc::default();
        let qos = settings.qos();
        for (side, (image, info)) in [
            (&settings.left_image, &settings.left_info),
            (&settings.right_image, &settings.right_info),
        ]
        .into_iter()
        .enumerate()
        {
            let keep_image = move |h: &mut Heard, m| {
                let kept = &mut h.images[side];
                if kept.len() == IMAGES_KEPT {
                    kept.pop_front();
                }
                kept.push_back((m, Instant::now()));
            };
            let keep_info = move |h: &mut Heard, m| h.infos[side] = Some((m, Instant::now()));
            bus.subscribe::<Image, _>(image, types::IMAGE, &qos, keeper(&heard, keep_image))
                .map_err(camera_fault)?;
            bus.subscribe::<CameraInfo, _>(
                info,
                types::CAMERA_INFO,
                &qos,
                keeper(&heard, keep_info),
            )
            .map_err(camera_fault)?;
        }
        let deadline = Instant::now() + timeout;
        let infos = wait(&heard, deadline, |h| match &h.infos {
            [Some((l, _)), Some((r, _))] => Some((l.clone(), r.clone())),
            _ => None,
        });
        let Some((left, right)) = infos else {
            let h = lock(&heard);
            let missing: Vec<&str> = [&settings.left_info, &settings.right_info]
                .iter()
                .zip(&h.infos)
                .filter(|(_, i)| i.is_none())
                .map(|(t, _)| t.as_str())
                .collect();
            return Err(camera_fault(format!(
                "no camera_info on {} within {:.0} s on ROS_DOMAIN_ID {}: is the stereo \
                 camera's driver running{}?{}",
                missing.join(" and "),
                timeout.as_secs_f64(),
                options.domain_id,
                if settings.reliable {
                    " and publishing reliable (a best-effort publisher needs \
                     dvrk.camera.reliable = false)"
                } else {
                    " (and are the topic names right: dvrk.camera.left_info, right_info)"
                },
                h.unreadable
                    .as_ref()
                    .map(|e| format!(" (last unreadable message: {e})"))
                    .unwrap_or_default()
            )));
        };
        let calibration = calibration_from_info(&left, &right, camera_to_robot)
            .map_err(|e| camera_fault(format!("unusable calibration: {e}")))?;
        Ok(Self {
            calibration,
            settings: settings.clone(),
            heard,
            trigger,
            clock,
            _bus: bus,
        })
    }

    /// Whether a pair's `camera_info`s still say the calibration the camera connected with.
    fn same_calibration(&self, h: &Heard) -> Result<(), String> {
        if let [Some((l, _)), Some((r, _))] = &h.infos {
            let now = calibration_from_info(l, r, self.calibration.camera_to_robot)?;
            if now != self.calibration {
                return Err(format!(
                    "the camera's calibration changed since it connected (fx {} → {}, \
                     baseline {} → {} m, {}×{} → {}×{}); reconnect to use the new one",
                    self.calibration.fx,
                    now.fx,
                    self.calibration.baseline_m,
                    now.baseline_m,
                    self.calibration.width,
                    self.calibration.height,
                    now.width,
                    now.height
                ));
            }
        }
        Ok(())
    }
}

/// A subscription handler that keeps each message with `keep` (or the reason it could not be
/// read) and wakes the waiters.
fn keeper<M>(
    heard: &Arc<(Mutex<Heard>, Condvar)>,
    keep: impl Fn(&mut Heard, M) + Send + 'static,
) -> impl FnMut(Result<M, String>) + Send + 'static {
    let heard = Arc::clone(heard);
    move |r| {
        let mut h = lock(&heard);
        match r {
            Ok(m) => keep(&mut h, m),
            Err(e) => h.unreadable = Some(e),
        }
        heard.1.notify_all();
    }
}

fn lock(heard: &Arc<(Mutex<Heard>, Condvar)>) -> MutexGuard<'_, Heard> {
    heard.0.lock().unwrap_or_else(PoisonError::into_inner)
}

/// Wait on the camera's messages until `done` says something, at most until `deadline`.
fn wait<T>(
    heard: &Arc<(Mutex<Heard>, Condvar)>,
    deadline: Instant,
    mut done: impl FnMut(&Heard) -> Option<T>,
) -> Option<T> {
    let tick = Duration::from_millis(20);
    crate::ros2::wait_for(&heard.0, &heard.1, deadline, tick, |h| done(h))
}

impl StereoCamera for Ros2Camera {
    fn calibration(&self) -> &StereoCalibration {
        &self.calibration
    }

    fn capture(&self) -> Result<StereoFrame, RobotError> {
        let s = &self.settings;
        let asked = Instant::now();
        let refused = |e: String| camera_fault(format!("capture refused: {e}"));
        let expected = match &self.trigger {
            Some(t) => Some(t.fire().map_err(refused)?),
            None => None,
        };
        let deadline = asked + Duration::from_secs_f64(s.capture_timeout_s);
        let matching = |h: &Heard| find_pair(h, asked, expected.as_ref(), s.max_pair_skew_s);
        let pair = match (&self.trigger, expected) {
            (Some(t), Some(stamp)) => loop {
                let until = (Instant::now() + RESEND_AFTER).min(deadline);
                if let Some(p) = wait(&self.heard, until, matching) {
                    break Some(p);
                }
                if Instant::now() >= deadline {
                    break None;
                }
                t.resend(stamp).map_err(refused)?;
            },
            _ => wait(&self.heard, deadline, matching),
        };
        let Some((left, right)) = pair else {
            let h = lock(&self.heard);
            let got = |i: usize, topic: &str| match h.images[i].back() {
                None => format!("nothing on {topic}"),
                Some((m, at)) => format!(
                    "{topic} last stamped {:.3} s, arrived {:.3} s ago",
                    m.header.stamp.as_secs_f64(),
                    at.elapsed().as_secs_f64()
                ),
            };
            return Err(camera_fault(format!(
                "no {}pair within {:.1} s ({}; {}){}",
                if expected.is_some() {
                    "triggered "
                } else {
                    "fresh, matching "
                },
                s.capture_timeout_s,
                got(0, &s.left_image),
                got(1, &s.right_image),
                h.unreadable
                    .as_ref()
                    .map(|e| format!("; last unreadable message: {e}"))
                    .unwrap_or_default()
            )));
        };
        if left.header.stamp.is_zero() || right.header.stamp.is_zero() {
            return Err(camera_fault(
                "image with a zero stamp: invalid data is marked so".into(),
            ));
        }
        let age_s = stamp_age_s(&left.header.stamp).max(stamp_age_s(&right.header.stamp));
        // A triggered pair is the one asked for, however long it took to arrive whole.
        if expected.is_none() && age_s > s.stale_after_s {
            return Err(RobotError::Stale {
                arm: "stereo camera".into(),
                age_s,
            });
        }
        self.same_calibration(&lock(&self.heard))
            .map_err(camera_fault)?;
        let c = &self.calibration;
        let images = [(&left, &s.left_image), (&right, &s.right_image)].map(|(m, topic)| {
            let image = rgb_from_image(m, topic)?;
            if (image.width, image.height) != (c.width, c.height) {
                return Err(format!(
                    "{topic}: image is {}×{}; its camera_info says {}×{}",
                    image.width, image.height, c.width, c.height
                ));
            }
            Ok(image)
        });
        let [l, r] = images;
        let (l, r) = (l.map_err(camera_fault)?, r.map_err(camera_fault)?);
        Ok(StereoFrame {
            stamp: self
                .clock
                .now()
                .saturating_sub(Duration::from_secs_f64(age_s.max(0.0))),
            left: l,
            right: r,
        })
    }
}

/// The newest left and right images that make a pair: both stamped `expected` when a trigger
/// named the stamp; otherwise both arrived at or after `asked`, stamped within `max_skew_s`
/// of each other (of those, the pair with the newest left image, and for it the right image
/// closest in stamp).
fn find_pair(
    h: &Heard,
    asked: Instant,
    expected: Option<&msg::Time>,
    max_skew_s: f64,
) -> Option<(Image, Image)> {
    let [lefts, rights] = &h.images;
    lefts.iter().rev().find_map(|(l, lt)| {
        let candidates = rights.iter().filter(|(r, rt)| match expected {
            Some(t) => l.header.stamp == *t && r.header.stamp == *t,
            None => *lt >= asked && *rt >= asked,
        });
        let skew = |r: &Image| (l.header.stamp.as_secs_f64() - r.header.stamp.as_secs_f64()).abs();
        candidates
            .map(|(r, _)| r)
            .filter(|r| expected.is_some() || skew(r) <= max_skew_s)
            .min_by(|a, b| skew(a).total_cmp(&skew(b)))
            .map(|r| (l.clone(), r.clone()))
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn calibration(fx: f64, baseline_m: f64) -> StereoCalibration {
        StereoCalibration {
            fx,
            fy: fx + 0.5,
            cx: 640.25,
            cy: 479.5,
            baseline_m,
            width: 1280,
            height: 960,
            camera_to_robot: Pose::identity(),
        }
    }

    fn infos(c: &StereoCalibration) -> (CameraInfo, CameraInfo) {
        let t = msg::Time { sec: 5, nanosec: 0 };
        (
            camera_info_msg(c, false, t, "l"),
            camera_info_msg(c, true, t, "r"),
        )
    }

    #[test]
    fn a_right_stream_a_frame_behind_still_pairs_with_the_left_image_of_its_stamp() {
        let img = |sec: i32, nanosec: u32, id: &str| {
            let px = RgbImage {
                width: 2,
                height: 1,
                data: vec![0; 6],
            };
            image_msg(&px, msg::Time { sec, nanosec }, id)
        };
        let asked = Instant::now();
        let later = asked + Duration::from_millis(10);
        let mut h = Heard::default();
        // Left frames 1 and 2 are in before right frame 1: the latest left alone pairs with
        // nothing.
        h.images[0].extend([(img(1, 0, "l1"), later), (img(1, 500_000_000, "l2"), later)]);
        h.images[1].push_back((img(1, 0, "r1"), later));
        let (l, r) = find_pair(&h, asked, None, 0.05).expect("the pair of stamp 1 s");
        assert_eq!(
            (l.header.frame_id.as_str(), r.header.frame_id.as_str()),
            ("l1", "r1")
        );
        // Right frame 2 arrives: the newest pair wins.
        h.images[1].push_back((img(1, 500_000_000, "r2"), later));
        let (l, r) = find_pair(&h, asked, None, 0.05).expect("the pair of stamp 1.5 s");
        assert_eq!(
            (l.header.frame_id.as_str(), r.header.frame_id.as_str()),
            ("l2", "r2")
        );
        // Images that arrived before the capture was asked for are not fresh.
        assert!(find_pair(&h, later + Duration::from_millis(1), None, 0.05).is_none());
        // Stamps further apart than the skew allowed make no pair.
        let mut apart = Heard::default();
        apart.images[0].push_back((img(2, 0, "l"), later));
        apart.images[1].push_back((img(1, 0, "r"), later));
        assert!(find_pair(&apart, asked, None, 0.05).is_none());
        // A triggered capture takes the images of the stamp it asked for, whenever they came.
        let t = msg::Time { sec: 1, nanosec: 0 };
        let (l, r) = find_pair(&h, later + Duration::from_secs(1), Some(&t), 0.0)
            .expect("the triggered pair");
        assert_eq!(
            (l.header.frame_id.as_str(), r.header.frame_id.as_str()),
            ("l1", "r1")
        );
    }

    #[test]
    fn a_calibration_crosses_camera_info_bit_for_bit() {
        // Focal lengths and baselines a lab has, some whose −fx·B does not divide back.
        for fx in [800.0, 1000.3, 1200.0, 1523.7, 2048.9, 613.1] {
            for b in [0.0038, 0.004, 0.0052, 0.04, 0.0613, 0.1, 0.12345] {
                let c = calibration(fx, b);
                let (l, r) = infos(&c);
                let back = calibration_from_info(&l, &r, Pose::identity()).expect("usable");
                let ulp = f64::from_bits(b.to_bits() + 1) - b;
                assert!(
                    (back.baseline_m - b).abs() <= ulp,
                    "fx {fx}, baseline {b}: {}",
                    back.baseline_m
                );
                assert_eq!(
                    StereoCalibration {
                        baseline_m: b,
                        ..back
                    },
                    c
                );
            }
        }
        // The mock's camera (1200 px, 4 cm) crosses exactly.
        let c = calibration(1200.0, 0.04);
        let (l, r) = infos(&c);
        assert_eq!(calibration_from_info(&l, &r, Pose::identity()), Ok(c));
    }

    #[test]
    fn pairs_this_backend_cannot_use_are_refused_with_why() {
        let c = calibration(1200.0, 0.04);
        let id = Pose::identity();
        let (l, r) = infos(&c);
        let e = calibration_from_info(&r, &l, id).expect_err("swapped");
        assert!(e.contains("swapped"), "{e}");
        let mut r2 = r.clone();
        r2.p[2] += 3.0;
        let e = calibration_from_info(&l, &r2, id).expect_err("cx");
        assert!(
            e.contains("cx differ") && e.contains("ZERO_DISPARITY"),
            "{e}"
        );
        let mut r2 = r.clone();
        r2.width = 640;
        let e = calibration_from_info(&l, &r2, id).expect_err("size");
        assert!(e.contains("one size"), "{e}");
        let mut l2 = l.clone();
        l2.binning_x = 2;
        assert!(
            calibration_from_info(&l2, &r, id)
                .unwrap_err()
                .contains("binning")
        );
        let mut l2 = l.clone();
        l2.roi.width = 100;
        l2.roi.height = 100;
        assert!(
            calibration_from_info(&l2, &r, id)
                .unwrap_err()
                .contains("region")
        );
        let mut l2 = l.clone();
        l2.p = [0.0; 12];
        assert!(
            calibration_from_info(&l2, &r, id)
                .unwrap_err()
                .contains("calibrated")
        );
        let mut r2 = r.clone();
        r2.p[7] = 5.0;
        assert!(
            calibration_from_info(&l, &r2, id)
                .unwrap_err()
                .contains("horizontal")
        );
        let mut r2 = r;
        r2.p[3] = -1200.0 * 2.0;
        let e = calibration_from_info(&l, &r2, id).expect_err("2 m baseline");
        assert!(e.contains("baseline"), "{e}");
    }

    fn image(encoding: &str, width: u32, height: u32, step: u32, data: Vec<u8>) -> Image {
        Image {
            header: msg::Header::default(),
            height,
            width,
            encoding: encoding.into(),
            is_bigendian: 0,
            step,
            data,
        }
    }

    #[test]
    fn images_convert_to_rgb_from_every_8_bit_colour_encoding() {
        let rgb = RgbImage {
            width: 2,
            height: 1,
            data: vec![1, 2, 3, 4, 5, 6],
        };
        let m = image_msg(&rgb, msg::Time::default(), "f");
        assert_eq!((m.encoding.as_str(), m.step), ("rgb8", 6));
        assert_eq!(rgb_from_image(&m, "/t").expect("rgb8"), rgb);
        let bgr = image("bgr8", 2, 1, 7, vec![3, 2, 1, 6, 5, 4, 0xFF]);
        assert_eq!(rgb_from_image(&bgr, "/t").expect("bgr8 padded"), rgb);
        let rgba = image("rgba8", 2, 1, 8, vec![1, 2, 3, 9, 4, 5, 6, 9]);
        assert_eq!(rgb_from_image(&rgba, "/t").expect("rgba8"), rgb);
        let bgra = image("bgra8", 2, 1, 8, vec![3, 2, 1, 9, 6, 5, 4, 9]);
        assert_eq!(rgb_from_image(&bgra, "/t").expect("bgra8"), rgb);
    }

    #[test]
    fn unusable_images_are_refused_naming_the_topic() {
        let e = rgb_from_image(&image("mono8", 2, 1, 2, vec![0, 0]), "/left").unwrap_err();
        assert!(e.starts_with("/left: encoding \"mono8\""), "{e}");
        let e = rgb_from_image(&image("rgb8", 2, 2, 6, vec![0; 11]), "/left").unwrap_err();
        assert!(e.contains("11 bytes") && e.contains("needs 12"), "{e}");
        let e = rgb_from_image(&image("rgb8", 2, 1, 5, vec![0; 5]), "/left").unwrap_err();
        assert!(e.contains("step 5"), "{e}");
        let e = rgb_from_image(&image("rgb8", 0, 1, 0, vec![]), "/left").unwrap_err();
        assert!(e.contains("image size 0×1"), "{e}");
    }

    #[test]
    fn settings_are_checked_with_their_names() {
        assert!(CameraSettings::default().validate().is_ok());
        let s = CameraSettings {
            left_image: "no slash".into(),
            ..CameraSettings::default()
        };
        let e = s.validate().unwrap_err().to_string();
        assert!(e.contains("dvrk.camera.left_image"), "{e}");
        let s = CameraSettings {
            capture_timeout_s: 0.0,
            ..CameraSettings::default()
        };
        assert!(
            s.validate()
                .unwrap_err()
                .to_string()
                .contains("capture_timeout_s")
        );
        let s = CameraSettings {
            camera_to_robot: Some(HandEye {
                translation_m: [0.0; 3],
                rotation_xyzw: [0.0, 0.0, 0.0, 2.0],
            }),
            ..CameraSettings::default()
        };
        let e = s.validate().unwrap_err().to_string();
        assert!(
            e.contains("camera_to_robot") && e.contains("unit quaternion"),
            "{e}"
        );
        let p = Pose::from_parts(
            nalgebra::Translation3::new(0.1, -0.2, 0.3),
            nalgebra::UnitQuaternion::from_euler_angles(0.3, -1.2, 2.0),
        );
        let back = HandEye::from_pose(&p).pose().expect("a pose");
        assert!((back.translation.vector - p.translation.vector).norm() < 1e-15);
        assert!(back.rotation.angle_to(&p.rotation) < 1e-12);
    }
}
