#![doc = include_str!("../README.md")]

mod msgs;
mod read;
mod tap;
mod write;

pub use msgs::{
    CHANNELS, COMPRESSED_IMAGE, Channel, Color, CompressedImage, Event, IMAGE_ANNOTATIONS,
    ImageAnnotations, Log, MsgType, NeedleEstimate, PATH, Path, Qos, StepEnd, THREAD_TRACE,
    ThreadTrace, Transition, schema_text,
};
pub use read::{Recorded, read, read_bytes, recover, rewrite, to_jsonl};
pub use tap::{FRAME, Tap, Truth};
pub use write::{FRAME_TOPICS, MAX_FRAME_QUEUE_BYTES, Recorder, RecorderOptions, RunInfo, Stats};

/// What can go wrong recording or reading a run.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecorderError {
    /// The file could not be created, written or read.
    #[error("{path}: {error}")]
    Io {
        /// The file.
        path: String,
        /// Why (in the message, not a separate cause: printed once).
        error: std::io::Error,
    },
    /// The MCAP layer refused (a bug, or a file that is not MCAP).
    #[error("{path}: MCAP: {why}")]
    Mcap {
        /// The file.
        path: String,
        /// Why.
        why: String,
    },
    /// A message could not be encoded or decoded.
    #[error("{path}: {why}")]
    Message {
        /// The file.
        path: String,
        /// What and where.
        why: String,
    },
    /// The writer thread is gone (it failed earlier: its error is in `Recorder::finish`).
    #[error("the recorder's writer stopped: {0}")]
    Stopped(String),
}
