//! [`Recorder`]: a run streamed to an MCAP file while it goes, by a writer thread behind a
//! queue.

use crate::RecorderError;
use crate::msgs::{CHANNELS, Event, Transition, nanos, schema_text, stamp};
use mcap::records::{MessageHeader, Metadata};
use sha2::{Digest, Sha256};
use std::collections::BTreeMap;
use std::io::BufWriter;
use std::path::{Path, PathBuf};
use std::sync::mpsc::{Receiver, RecvTimeoutError, Sender, channel};
use std::time::{Duration, Instant};
use stitch_engine::{Entry, JournalSink as Sink, Record};

/// A chunk is closed at least this often, in run time (and in wall time on a robot): what a
/// crash can lose.
pub const FLUSH_EVERY: Duration = Duration::from_millis(250);

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
}

/// How a recording is written.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RecorderOptions {
    /// Also close a chunk every [`FLUSH_EVERY`] of wall time with anything unwritten (a run
    /// on a robot, whose records come in real time). Off on the mock: there, chunks close at
    /// points of simulated time only, so the same seed gives the same bytes.
    pub wall_flush: bool,
}

/// What a finished recording held.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Stats {
    /// Engine events recorded.
    pub events: u64,
    /// Chunks closed.
    pub chunks: u64,
}

/// A run being recorded. Hand [`Recorder::sink`] to the journal; [`Recorder::finish`] writes
/// the file's summary. Dropped without `finish`, or killed, the file is still readable up to
/// its last closed chunk (`stitch journal recover`).
#[derive(Debug)]
pub struct Recorder {
    tx: Option<Sender<Record>>,
    thread: Option<std::thread::JoinHandle<Result<Stats, RecorderError>>>,
    path: PathBuf,
}

type McapWriter = mcap::Writer<BufWriter<std::fs::File>>;

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
        let file = std::fs::File::create(path).map_err(|source| RecorderError::Io {
            path: path.display().to_string(),
            source,
        })?;
        let err = mcap_err(path);
        let mut w = mcap::WriteOptions::new()
            .profile("ros2")
            .library(info.program.clone())
            .compression(None)
            .chunk_size(None)
            // A chunk is built in memory and written once when closed, instead of written as
            // it grows and its header patched by seeking back: one write per chunk, not ~9
            // system calls (measured with strace).
            .disable_seeking(true)
            .create(BufWriter::new(file))
            .map_err(&err)?;
        let mut meta = BTreeMap::new();
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
        let mut ids = Vec::new();
        for c in &CHANNELS {
            let schema = w
                .add_schema(c.schema, "ros2msg", schema_text(c).as_bytes())
                .map_err(&err)?;
            let mut m = BTreeMap::new();
            m.insert("offered_qos_profiles".to_string(), c.qos.to_string());
            ids.push(w.add_channel(schema, c.topic, "cdr", &m).map_err(&err)?);
        }
        w.flush().map_err(&err)?;
        // Events are never dropped and the engine never waits on the disk, so their queue is
        // unbounded: a run's events are few (hundreds), and a bounded channel's slots are
        // allocated up front (4,096 records: perf stat's task-clock for a mock mission went
        // from 6.5 to 6.1 ms without them).
        let (tx, rx) = channel();
        let owned = path.to_path_buf();
        let thread = std::thread::Builder::new()
            .name("recorder".into())
            .spawn(move || write_loop(w, &ids, &rx, &owned, options))
            .map_err(|source| RecorderError::Io {
                path: path.display().to_string(),
                source,
            })?;
        Ok(Self {
            tx: Some(tx),
            thread: Some(thread),
            path: path.to_path_buf(),
        })
    }

    /// The journal's sink: each record is queued for the writer, never waited on. Once the
    /// writer has failed, records are no longer kept; `finish` says why.
    pub fn sink(&self) -> Sink {
        let tx = self.tx.clone();
        Box::new(move |r: &Record| {
            if let Some(tx) = &tx {
                let _ = tx.send(r.clone());
            }
        })
    }

    /// The file being written.
    pub fn path(&self) -> &Path {
        &self.path
    }

    /// Close the queue, let the writer write what is left and the summary, and say what it
    /// recorded. Every sink must be gone (the journal drops its own when the run ends).
    pub fn finish(mut self) -> Result<Stats, RecorderError> {
        self.tx = None;
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
        self.tx = None;
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

fn event_name(entry: &Entry) -> String {
    match serde_json::to_value(entry) {
        Ok(serde_json::Value::Object(m)) => m
            .get("event")
            .and_then(|v| v.as_str())
            .unwrap_or("unknown")
            .to_string(),
        _ => "unknown".into(),
    }
}

fn write_loop(
    mut w: McapWriter,
    ids: &[u16],
    rx: &Receiver<Record>,
    path: &Path,
    options: RecorderOptions,
) -> Result<Stats, RecorderError> {
    let err = mcap_err(path);
    let message = |why: String| RecorderError::Message {
        path: path.display().to_string(),
        why,
    };
    let mut stats = Stats::default();
    let flush_ns = FLUSH_EVERY.as_nanos() as u64;
    let (mut flushed_ns, mut dirty) = (0u64, false);
    let mut wall = Instant::now();
    let mut sequence = [0u32; 2];
    loop {
        let next = if options.wall_flush {
            match rx.recv_timeout(FLUSH_EVERY.saturating_sub(wall.elapsed())) {
                Ok(r) => Some(r),
                Err(RecvTimeoutError::Timeout) => None,
                Err(RecvTimeoutError::Disconnected) => break,
            }
        } else {
            match rx.recv() {
                Ok(r) => Some(r),
                Err(_) => break,
            }
        };
        let Some(r) = next else {
            if dirty {
                w.flush().map_err(&err)?;
                stats.chunks += 1;
                dirty = false;
            }
            wall = Instant::now();
            continue;
        };
        let t = nanos(r.t_s);
        let json =
            serde_json::to_string(&r).map_err(|e| message(format!("record {}: {e}", r.seq)))?;
        let event = Event {
            stamp: stamp(r.t_s),
            seq: r.seq,
            event: event_name(&r.entry),
            record_json: json,
        };
        let bytes = stitch_dvrk::encode(&event, "stitch_msgs/msg/Event")
            .map_err(|e| message(e.to_string()))?;
        w.write_to_known_channel(
            &MessageHeader {
                channel_id: ids[0],
                sequence: sequence[0],
                log_time: t,
                publish_time: t,
            },
            &bytes,
        )
        .map_err(&err)?;
        sequence[0] += 1;
        stats.events += 1;
        dirty = true;
        let transition = if let Entry::Transition { from, to } = &r.entry {
            let bytes = stitch_dvrk::encode(
                &Transition {
                    stamp: stamp(r.t_s),
                    seq: r.seq,
                    from_state: from.clone(),
                    to_state: to.clone(),
                },
                "stitch_msgs/msg/Transition",
            )
            .map_err(|e| message(e.to_string()))?;
            w.write_to_known_channel(
                &MessageHeader {
                    channel_id: ids[1],
                    sequence: sequence[1],
                    log_time: t,
                    publish_time: t,
                },
                &bytes,
            )
            .map_err(&err)?;
            sequence[1] += 1;
            true
        } else {
            false
        };
        let wall_due = options.wall_flush && wall.elapsed() >= FLUSH_EVERY;
        let end = matches!(r.entry, Entry::Finished { .. });
        if transition || end || wall_due || t >= flushed_ns + flush_ns {
            w.flush().map_err(&err)?;
            stats.chunks += 1;
            flushed_ns = t;
            dirty = false;
            wall = Instant::now();
        }
    }
    w.finish().map_err(&err)?;
    Ok(stats)
}
