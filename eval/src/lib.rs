#![doc = include_str!("../README.md")]

pub mod independent;
pub mod own;
mod report;
pub mod segmentation;
pub mod thread;

pub use report::{Accuracy, FrameResult, accuracy, failure_kind, percentile};
