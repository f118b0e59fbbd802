//! [`Recorder`]: a run streamed to an MCAP file while it goes, by a writer thread behind a
//! queue.

use crate::RecorderError;
use crate::msgs::{
    CHANNELS, COMPRESSED_IMAGE, CompressedImage, Event, Log, MsgType, Qos, StepEnd, Transition,
    nanos, schema_text, stamp,
};
use crate::tap::{Shared, Tap};
use mcap::records::{MessageHeader, Metadata};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::atomic::Ordering;
use std::sync::{Arc, PoisonError};
use std::time::{Duration, Instant};
use stitch_engine::{Entry, JournalSink as Sink, Record};
use stitch_primitives::StepOutcome;
use stitch_robot::Clock;

/// What goes to the writer thread, in the order it is to be written.
#[derive(Debug)]
pub(crate) enum Item {
    /// An engine event.
    Record(Box<Record>),
    /// A message already encoded: telemetry, an estimate, a log line, a frame.
    Message {
        /// Topic.
        topic: Arc<str>,
        /// Its type.
        ty: &'static MsgType,
        /// How it is offered.
        qos: Qos,
        /// Log time, ns of run time.
        t_ns: u64,
        /// CDR bytes.
        bytes: Vec<u8>,
    },
    /// A stereo pair to encode (JPEG) and write, taken at `t_ns`.
    Frame {
        /// Run time, ns.
        t_ns: u64,
        /// Left and right views.
        views: Box<[stitch_robot::RgbImage; 2]>,
    },
    /// A metadata record.
    Metadata(Metadata),
    /// The run is over: write what is left and the summary.
    End,
}

/// A chunk is closed at least this often in run time: what a crash can lose.
pub const FLUSH_EVERY: Duration = Duration::from_millis(250);
/// On a robot, a chunk with anything in it is also closed this often in wall time (a write
/// every 100 ms costs nothing; what a `kill -9` loses stays under [`FLUSH_EVERY`] with the
/// queue's and the scheduler's delays on top).
pub const WALL_FLUSH_EVERY: Duration = Duration::from_millis(100);

/// What a recording says about its run, written first and flushed at once.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct RunInfo {
    /// The program and its version, e.g. `stitch 0.1.0`.
    pub program: String,
    /// The plan script's path, as given.
    pub plan_file: String,
    /// The plan script's text (attached as `plan.rhai`; its SHA-256 in the metadata).
    pub plan_text: String,
    /// The seed that decides a simulated run.
    pub seed: Option<u64>,
    /// `mock`, `scripted` or `ros2`.
    pub robot: String,
    /// The mock configuration file's text, if one was given (attached as `mock.toml`).
    pub mock_config: Option<String>,
    /// More of what decides the run, for `stitch replay` (perception, wound, steps per
    /// throw, ...): written into the `stitch_run` metadata beside the above.
    pub settings: BTreeMap<String, String>,
    /// More files the run read (an outcome schedule): name, media type, text.
    pub files: Vec<(String, String, String)>,
}

/// How a recording is written.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RecorderOptions {
    /// Also close a chunk every [`WALL_FLUSH_EVERY`] of wall time with anything unwritten (a run
    /// on a robot, whose records come in real time). Off on the mock: there, chunks close at
    /// points of simulated time only, so the same seed gives the same bytes.
    pub wall_flush: bool,
    /// Camera frames waiting for the writer may hold at most this many bytes; a frame that
    /// would pass it is dropped, counted and said (events and telemetry are never dropped).
    /// 0: the default, [`MAX_FRAME_QUEUE_BYTES`].
    pub max_frame_queue_bytes: usize,
    /// Record a stereo pair from the camera at most this often, in run time (`None`: no
    /// frames). Only runs whose estimator looks at images have frames.
    pub frame_period: Option<Duration>,
}

/// The default bound on camera frames waiting for the writer to encode them, bytes (raw
/// RGB: eight pairs of 1280×960 views).
pub const MAX_FRAME_QUEUE_BYTES: usize = 64 << 20;

/// What a finished recording held.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Engine events recorded.
    pub events: u64,
    /// Other messages recorded (telemetry, estimates, logs, frames).
    pub messages: u64,
    /// Camera frames recorded.
    pub frames: u64,
    /// Camera frames dropped because the writer was behind (never events nor telemetry).
    pub frames_dropped: u64,
    /// Chunks closed.
    pub chunks: u64,
}

/// A run being recorded. Hand [`Recorder::sink`] to the journal; [`Recorder::finish`] writes
/// the file's summary. Dropped without `finish`, or killed, the file is still readable up to
/// its last closed chunk (`stitch journal recover`).
#[derive(Debug)]
pub struct Recorder {
    shared: Arc<Shared>,
    thread: Option<std::thread::JoinHandle<Result<Stats, RecorderError>>>,
    path: PathBuf,
}

type McapWriter = mcap::Writer<Tracked>;

/// The file behind a buffer, knowing its own position, shared with the writer loop, which
/// alone decides when the buffer goes to the kernel ([`deliver`]).
///
/// The MCAP writer asks the position (`seek(Current(0))`) for every record it indexes; a
/// `BufWriter<File>` answers by flushing its buffer and asking the kernel, two system calls
/// a message (strace: 1,997 `lseek` and 1,213 `write` for a mock mission). And it flushes
/// its writer at every chunk it closes: the loop hands closed chunks to the kernel itself,
/// at every close on a robot, and on a simulated run at transitions, at the end and within
/// [`WALL_FLUSH_EVERY`] of wall time (370 `write`s a kinematic mission become ~45). Written
/// by hand: no crate does just this.
#[derive(Debug)]
struct Tracked {
    file: Arc<std::sync::Mutex<BufWriter<std::fs::File>>>,
    pos: u64,
}

impl std::io::Write for Tracked {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let n = self
            .file
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .write(buf)?;
        self.pos += n as u64;
        Ok(n)
    }
    fn flush(&mut self) -> std::io::Result<()> {
        // The loop delivers (see above); a closed chunk waits in the buffer until it does.
        Ok(())
    }
}

/// Hand everything written so far (closed chunks; the open one is in the MCAP writer's
/// memory) to the kernel.
fn deliver(file: &std::sync::Mutex<BufWriter<std::fs::File>>) -> std::io::Result<()> {
    use std::io::Write;
    file.lock().unwrap_or_else(PoisonError::into_inner).flush()
}

impl std::io::Seek for Tracked {
    fn seek(&mut self, to: std::io::SeekFrom) -> std::io::Result<u64> {
        match to {
            std::io::SeekFrom::Current(0) => Ok(self.pos),
            // The writer is made with seeking disabled: it only ever asks where it is.
            other => Err(std::io::Error::new(
                std::io::ErrorKind::Unsupported,
                format!("the recorder's file only appends (asked to seek {other:?})"),
            )),
        }
    }
}

fn mcap_err(path: &Path) -> impl Fn(mcap::McapError) -> RecorderError + '_ {
    move |e| RecorderError::Mcap {
        path: path.display().to_string(),
        why: e.to_string(),
    }
}

impl Recorder {
    /// Create `path` and write the run's metadata and attachments, flushed, before anything
    /// runs (an error here stops the run before it starts).
    pub fn create(
        path: &Path,
        info: &RunInfo,
        options: RecorderOptions,
    ) -> Result<Self, RecorderError> {
        let file = std::fs::File::create(path).map_err(|error| RecorderError::Io {
            path: path.display().to_string(),
            error,
        })?;
        let err = mcap_err(path);
        let file = Arc::new(std::sync::Mutex::new(BufWriter::with_capacity(
            1 << 16,
            file,
        )));
        let mut w = mcap::WriteOptions::new()
            .profile("ros2")
            .library(info.program.clone())
            .compression(None)
            .chunk_size(None)
            // A chunk is built in memory and written once when closed, instead of written as
            // it grows and its header patched by seeking back: one write per chunk, not ~9
            // system calls (measured with strace).
            .disable_seeking(true)
            .create(Tracked {
                file: Arc::clone(&file),
                pos: 0,
            })
            .map_err(&err)?;
        let mut meta = info.settings.clone();
        meta.insert("program".to_string(), info.program.clone());
        meta.insert("plan_file".to_string(), info.plan_file.clone());
        meta.insert(
            "plan_sha256".to_string(),
            hex(&Sha256::digest(info.plan_text.as_bytes())),
        );
        meta.insert(
            "seed".to_string(),
            info.seed.map(|s| s.to_string()).unwrap_or_default(),
        );
        meta.insert("robot".to_string(), info.robot.clone());
        meta.insert(
            "frame_period_s".to_string(),
            options
                .frame_period
                .map(|p| p.as_secs_f64().to_string())
                .unwrap_or_default(),
        );
        w.write_metadata(&Metadata {
            name: "stitch_run".into(),
            metadata: meta,
        })
        .map_err(&err)?;
        let mut attach = |name: &str, media_type: &str, data: &str| {
            w.attach(&mcap::Attachment {
                log_time: 0,
                create_time: 0,
                name: name.into(),
                media_type: media_type.into(),
                data: std::borrow::Cow::Borrowed(data.as_bytes()),
            })
        };
        attach("plan.rhai", "text/plain", &info.plan_text).map_err(&err)?;
        if let Some(config) = &info.mock_config {
            attach("mock.toml", "application/toml", config).map_err(&err)?;
        }
        for (name, media_type, text) in &info.files {
            attach(name, media_type, text).map_err(&err)?;
        }
        // Each channel (with its schema) is added in the chunk of its first message: a chunk
        // of schemas and channels alone has no message index, and the indexed reader that
        // Foxglove and Lichtblick use (`@mcap/core`) refuses a file with one.
        let channels = Channels::default();
        w.flush().map_err(&err)?;
        deliver(&file).map_err(|error| RecorderError::Io {
            path: path.display().to_string(),
            error,
        })?;
        // Events and telemetry are never dropped and the engine never waits on the disk, so
        // their queue is unbounded (a mission's messages are a few thousand); only camera
        // frames are bounded (`Shared::admit_frame`).
        let shared = Arc::new(Shared::new(options));
        let owned = path.to_path_buf();
        let for_writer = Arc::clone(&shared);
        let thread = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || {
                let result = write_loop(w, channels, &file, &owned, options, &for_writer);
                if let Err(e) = &result {
                    // Said at once, not only when the run ends: on a robot the run goes on,
                    // and the person at it must know that it is no longer recorded.
                    eprintln!("the flight recorder stopped, the run goes on unrecorded: {e}");
                }
                // Stopped, by the end or by an error: nothing more is queued, and a camera
                // waiting for room in the frame queue is let go.
                for_writer.end();
                result
            })
            .map_err(|error| RecorderError::Io {
                path: path.display().to_string(),
                error,
            })?;
        Ok(Self {
            shared,
            thread: Some(thread),
            path: path.to_path_buf(),
        })
    }

    /// The journal's sink: each record is queued for the writer, never waited on. Once the
    /// writer has failed, records are no longer kept; `finish` says why. It also tells the
    /// taps which step is running (the step an estimate was asked for).
    pub fn sink(&self) -> Sink {
        let shared = Arc::clone(&self.shared);
        Box::new(move |r: &Record| {
            match &r.entry {
                Entry::StepStart {
                    throw,
                    step,
                    primitive,
                    attempt,
                } => {
                    *shared.step.lock().unwrap_or_else(PoisonError::into_inner) =
                        format!("t{throw} s{step} {primitive} a{attempt}");
                }
                Entry::StepEnd { .. } => {
                    shared
                        .step
                        .lock()
                        .unwrap_or_else(PoisonError::into_inner)
                        .clear();
                }
                _ => {}
            }
            shared.send(Item::Record(Box::new(r.clone())));
        })
    }

    /// A tap on the robot, stamping with `clock` (the run's): wraps arms, jaws, the
    /// estimator and cameras so what they measure and are told is recorded, and samples a
    /// real robot's state.
    pub fn tap(&self, clock: Arc<dyn Clock>) -> Tap {
        Tap::new(Arc::clone(&self.shared), clock)
    }

    /// The file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Close the queue, let the writer write what is left and the summary, and say what it
    /// recorded. Every sink must be gone (the journal drops its own when the run ends).
    pub fn finish(mut self) -> Result<Stats, RecorderError> {
        self.shared.end();
        match self.thread.take().map(std::thread::JoinHandle::join) {
            Some(Ok(r)) => r,
            Some(Err(_)) => Err(RecorderError::Stopped("the writer thread panicked".into())),
            None => Err(RecorderError::Stopped("already finished".into())),
        }
    }
}

impl Drop for Recorder {
    fn drop(&mut self) {
        // Not finished (an error path): the writer still writes what it has and closes the
        // file; its result has nobody to go to.
        self.shared.end();
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// Where a recorded stereo pair's views go.
pub const FRAME_TOPICS: [&str; 2] = [
    "/stitch/camera/left/image/compressed",
    "/stitch/camera/right/image/compressed",
];

/// JPEG quality of recorded frames (a rendered 1280×960 view: ~0.2 MB; as PNG, ~2 MB and
/// four times the encoding time).
pub const JPEG_QUALITY: u8 = 90;

/// `view` as JPEG (deterministic: the same pixels, the same bytes).
fn jpeg(view: &stitch_robot::RgbImage) -> Result<Vec<u8>, String> {
    let expected = view.width as usize * view.height as usize * 3;
    if view.data.len() != expected {
        return Err(format!(
            "{}×{} with {} bytes",
            view.width,
            view.height,
            view.data.len()
        ));
    }
    let mut out = Vec::new();
    image::codecs::jpeg::JpegEncoder::new_with_quality(&mut out, JPEG_QUALITY)
        .encode(
            &view.data,
            view.width,
            view.height,
            image::ExtendedColorType::Rgb8,
        )
        .map_err(|e| e.to_string())?;
    Ok(out)
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

/// The tag serde writes for `value` under `field` (an event's `event`, a failure's `kind`:
/// `step_end`, `no_progress`, ...), as the journal names it.
fn serde_tag<T: serde::Serialize>(value: &T, field: &str) -> String {
    match serde_json::to_value(value) {
        Ok(serde_json::Value::Object(m)) => m
            .get(field)
            .and_then(|v| v.as_str())
            .unwrap_or("unknown")
            .to_string(),
        _ => "unknown".into(),
    }
}

/// Channel and schema ids by topic and type name, added as their first message comes.
#[derive(Debug, Default)]
struct Channels {
    schemas: BTreeMap<&'static str, u16>,
    channels: BTreeMap<Arc<str>, (u16, u32)>,
}

impl Channels {
    /// The channel of `topic` (added, with its schema, if new), and its next sequence number.
    fn id(
        &mut self,
        w: &mut McapWriter,
        topic: &str,
        ty: &'static MsgType,
        qos: Qos,
    ) -> Result<(u16, u32), mcap::McapError> {
        if let Some((id, seq)) = self.channels.get_mut(topic) {
            *seq += 1;
            return Ok((*id, *seq - 1));
        }
        let schema = match self.schemas.get(ty.name) {
            Some(s) => *s,
            None => {
                let s = w.add_schema(ty.name, "ros2msg", schema_text(ty).as_bytes())?;
                self.schemas.insert(ty.name, s);
                s
            }
        };
        let mut m = BTreeMap::new();
        m.insert("offered_qos_profiles".to_string(), qos.yaml());
        let id = w.add_channel(schema, topic, "cdr", &m)?;
        self.channels.insert(topic.into(), (id, 1));
        Ok((id, 0))
    }
}

fn write_loop(
    mut w: McapWriter,
    mut channels: Channels,
    file: &std::sync::Mutex<BufWriter<std::fs::File>>,
    path: &Path,
    options: RecorderOptions,
    shared: &Shared,
) -> Result<Stats, RecorderError> {
    let err = mcap_err(path);
    let io = |error: std::io::Error| RecorderError::Io {
        path: path.display().to_string(),
        error,
    };
    // Closed chunks not yet handed to the kernel, and when it last had everything.
    let (mut undelivered, mut delivered_at) = (false, Instant::now());
    let message = |why: String| RecorderError::Message {
        path: path.display().to_string(),
        why,
    };
    let mut stats = Stats::default();
    let flush_ns = FLUSH_EVERY.as_nanos() as u64;
    let (mut flushed_ns, mut dirty) = (0u64, false);
    let mut wall = Instant::now();
    let mut last_t = 0u64;
    let mut said_dropped = 0u64;
    let mut put = |w: &mut McapWriter,
                   topic: &str,
                   ty: &'static MsgType,
                   qos: Qos,
                   t: u64,
                   bytes: &[u8]|
     -> Result<(), mcap::McapError> {
        let (channel_id, sequence) = channels.id(w, topic, ty, qos)?;
        w.write_to_known_channel(
            &MessageHeader {
                channel_id,
                sequence,
                log_time: t,
                publish_time: t,
            },
            bytes,
        )
    };
    let mut pending = std::collections::VecDeque::new();
    loop {
        if pending.is_empty() {
            let timeout = if options.wall_flush {
                Some(WALL_FLUSH_EVERY.saturating_sub(wall.elapsed()))
            } else {
                undelivered.then(|| WALL_FLUSH_EVERY.saturating_sub(delivered_at.elapsed()))
            };
            pending.extend(shared.queue.take(timeout));
        }
        let Some(item) = pending.pop_front() else {
            // Nothing came for a while: on a robot close the open chunk (wall time), on a
            // simulated run only hand over the closed ones (its chunks are cut in run time).
            if dirty && options.wall_flush {
                w.flush().map_err(&err)?;
                stats.chunks += 1;
                dirty = false;
            }
            deliver(file).map_err(io)?;
            (undelivered, delivered_at) = (false, Instant::now());
            wall = Instant::now();
            continue;
        };
        // Frames dropped since the last word about it: said on /rosout (at most once per
        // chunk), counted in the summary's metadata.
        let dropped = shared.frames_dropped.load(Ordering::Relaxed);
        if dropped > said_dropped {
            let log = Log {
                stamp: crate::msgs::stamp_ns(last_t),
                level: Log::WARN,
                name: "recorder".into(),
                msg: format!(
                    "{} camera frame(s) dropped: the writer was behind ({} in all)",
                    dropped - said_dropped,
                    dropped
                ),
                file: String::new(),
                function: String::new(),
                line: 0,
            };
            let bytes = stitch_dvrk::encode(&log, crate::msgs::LOG.name)
                .map_err(|e| message(e.to_string()))?;
            put(
                &mut w,
                "/rosout",
                &crate::msgs::LOG,
                Qos::Stream,
                last_t,
                &bytes,
            )
            .map_err(&err)?;
            said_dropped = dropped;
        }
        let (t, transition, end) = match item {
            Item::End => break,
            Item::Metadata(m) => {
                w.write_metadata(&m).map_err(&err)?;
                (last_t, true, false)
            }
            Item::Frame { t_ns, views } => {
                let size = views[0].data.len() + views[1].data.len();
                for (view, topic) in views.iter().zip(FRAME_TOPICS) {
                    let msg = CompressedImage {
                        header: stitch_dvrk::msg::Header {
                            stamp: crate::msgs::stamp_ns(t_ns),
                            frame_id: "camera_left".into(),
                        },
                        format: "jpeg".into(),
                        data: jpeg(view).map_err(|e| message(format!("{topic}: JPEG: {e}")))?,
                    };
                    let bytes = stitch_dvrk::encode(&msg, COMPRESSED_IMAGE.name)
                        .map_err(|e| message(e.to_string()))?;
                    put(&mut w, topic, &COMPRESSED_IMAGE, Qos::Stream, t_ns, &bytes)
                        .map_err(&err)?;
                    stats.messages += 1;
                }
                shared.frame_written(size);
                stats.frames += 1;
                (t_ns, false, false)
            }
            Item::Message {
                topic,
                ty,
                qos,
                t_ns,
                bytes,
            } => {
                put(&mut w, &topic, ty, qos, t_ns, &bytes).map_err(&err)?;
                stats.messages += 1;
                (t_ns, false, false)
            }
            Item::Record(r) => {
                let t = nanos(r.t_s);
                let json = serde_json::to_string(&r)
                    .map_err(|e| message(format!("record {}: {e}", r.seq)))?;
                let event = Event {
                    stamp: stamp(r.t_s),
                    seq: r.seq,
                    event: serde_tag(&r.entry, "event"),
                    record_json: json,
                };
                let bytes = stitch_dvrk::encode(&event, crate::msgs::EVENT.name)
                    .map_err(|e| message(e.to_string()))?;
                put(
                    &mut w,
                    CHANNELS[0].topic,
                    CHANNELS[0].ty,
                    CHANNELS[0].qos,
                    t,
                    &bytes,
                )
                .map_err(&err)?;
                stats.events += 1;
                let transition = if let Entry::Transition { from, to } = &r.entry {
                    let bytes = stitch_dvrk::encode(
                        &Transition {
                            stamp: stamp(r.t_s),
                            seq: r.seq,
                            from_state: from.clone(),
                            to_state: to.clone(),
                        },
                        crate::msgs::TRANSITION.name,
                    )
                    .map_err(|e| message(e.to_string()))?;
                    put(
                        &mut w,
                        CHANNELS[1].topic,
                        CHANNELS[1].ty,
                        CHANNELS[1].qos,
                        t,
                        &bytes,
                    )
                    .map_err(&err)?;
                    true
                } else {
                    false
                };
                if let Entry::StepEnd {
                    throw,
                    step,
                    primitive,
                    attempt,
                    outcome,
                } = &r.entry
                {
                    let m = outcome.measured();
                    let v = |x: Option<f64>| x.unwrap_or(f64::NAN);
                    let msg = StepEnd {
                        stamp: stamp(r.t_s),
                        seq: r.seq,
                        throw_index: u32::try_from(*throw).unwrap_or(u32::MAX),
                        step: u32::try_from(*step).unwrap_or(u32::MAX),
                        attempt: *attempt,
                        primitive: primitive.clone(),
                        ok: matches!(outcome, StepOutcome::Succeeded { .. }),
                        failure: match outcome {
                            StepOutcome::Succeeded { .. } => String::new(),
                            StepOutcome::Failed(f) => serde_tag(&f.kind, "kind"),
                            StepOutcome::Interrupted { .. } => "interrupted".into(),
                        },
                        entry_error_m: v(m.entry_error_m),
                        exit_error_m: v(m.exit_error_m),
                        endpoint_travel_m: v(m.endpoint_travel_m),
                        normal_change_rad: v(m.normal_change_rad),
                        thread_used_m: v(m.thread_used_m),
                        thread_left_m: v(m.thread_left_m),
                        thread_clearance_m: v(m.thread_clearance_m),
                    };
                    let bytes = stitch_dvrk::encode(&msg, crate::msgs::STEP_END.name)
                        .map_err(|e| message(e.to_string()))?;
                    put(
                        &mut w,
                        CHANNELS[2].topic,
                        CHANNELS[2].ty,
                        CHANNELS[2].qos,
                        t,
                        &bytes,
                    )
                    .map_err(&err)?;
                }
                (t, transition, matches!(r.entry, Entry::Finished { .. }))
            }
        };
        last_t = last_t.max(t);
        dirty = true;
        let wall_due = options.wall_flush && wall.elapsed() >= WALL_FLUSH_EVERY;
        if transition || end || wall_due || t >= flushed_ns + flush_ns {
            w.flush().map_err(&err)?;
            stats.chunks += 1;
            flushed_ns = flushed_ns.max(t);
            dirty = false;
            wall = Instant::now();
            if options.wall_flush || transition || end || delivered_at.elapsed() >= WALL_FLUSH_EVERY
            {
                deliver(file).map_err(io)?;
                (undelivered, delivered_at) = (false, Instant::now());
            } else {
                undelivered = true;
            }
        }
    }
    stats.frames_dropped = shared.frames_dropped.load(Ordering::Relaxed);
    let mut summary = BTreeMap::new();
    for (k, v) in [
        ("events", stats.events),
        ("messages", stats.messages),
        ("frames", stats.frames),
        ("frames_dropped", stats.frames_dropped),
    ] {
        summary.insert(k.to_string(), v.to_string());
    }
    w.write_metadata(&Metadata {
        name: "stitch_recording".into(),
        metadata: summary,
    })
    .map_err(&err)?;
    w.finish().map_err(&err)?;
    deliver(file).map_err(io)?;
    Ok(stats)
}
