//! `--segmenter classical|onnx|onnx-fast|onnx:FILE`: which segmenter the needle pipeline uses.

use anyhow::Context;
use std::path::PathBuf;
use std::str::FromStr;
use std::sync::Arc;
use stitch_perception::{ColorSegmenter, SharedSegmenter};

/// The committed model (`perception/models/needle_thread_unet.onnx`), built into the binary.
#[cfg(feature = "onnx")]
const BUILT_IN: &[u8] = include_bytes!("../../perception/models/needle_thread_unet.onnx");
/// The committed fast model (`perception/models/needle_thread_unet_fast.onnx`: from half
/// resolution, about half the time), built into the binary.
#[cfg(feature = "onnx")]
const BUILT_IN_FAST: &[u8] = include_bytes!("../../perception/models/needle_thread_unet_fast.onnx");

/// What `--segmenter` names.
#[derive(Clone, Debug, PartialEq, Eq, Default)]
pub(crate) enum SegmenterChoice {
    /// The colour segmenter.
    #[default]
    Classical,
    /// A U-Net through ONNX Runtime: the built-in model, or one from a file.
    Onnx(Option<PathBuf>),
    /// The built-in fast U-Net (from half resolution).
    OnnxFast,
}

impl FromStr for SegmenterChoice {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "classical" => Ok(Self::Classical),
            "onnx" => Ok(Self::Onnx(None)),
            "onnx-fast" => Ok(Self::OnnxFast),
            _ => match s.strip_prefix("onnx:") {
                Some(file) if !file.is_empty() => Ok(Self::Onnx(Some(PathBuf::from(file)))),
                _ => Err(format!(
                    "{s:?}: expected classical, onnx (the built-in model), onnx-fast (the built-in \
                     fast model) or onnx:FILE"
                )),
            },
        }
    }
}

impl std::fmt::Display for SegmenterChoice {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Classical => write!(f, "classical"),
            Self::Onnx(None) => write!(f, "onnx"),
            Self::OnnxFast => write!(f, "onnx-fast"),
            Self::Onnx(Some(p)) => write!(f, "onnx:{}", p.display()),
        }
    }
}

impl SegmenterChoice {
    /// The segmenter, loaded (a model is checked against the contract once, here).
    pub(crate) fn load(&self) -> anyhow::Result<SharedSegmenter> {
        match self {
            Self::Classical => Ok(SharedSegmenter(Arc::new(ColorSegmenter::default()))),
            Self::Onnx(file) => onnx(file.as_ref(), false),
            Self::OnnxFast => onnx(None, true),
        }
    }

    /// The segmenter, or `None` for the classical one (the pipeline's default).
    pub(crate) fn load_learned(&self) -> anyhow::Result<Option<SharedSegmenter>> {
        match self {
            Self::Classical => Ok(None),
            _ => self.load().map(Some),
        }
    }
}

#[cfg(feature = "onnx")]
fn onnx(file: Option<&PathBuf>, fast: bool) -> anyhow::Result<SharedSegmenter> {
    use stitch_perception::onnx::OnnxSegmenter;
    let s = match file {
        Some(path) => OnnxSegmenter::from_file(path, 1),
        None if fast => OnnxSegmenter::from_bytes(
            BUILT_IN_FAST,
            "the built-in needle_thread_unet_fast.onnx",
            1,
        ),
        None => OnnxSegmenter::from_bytes(BUILT_IN, "the built-in needle_thread_unet.onnx", 1),
    }
    .context("--segmenter")?;
    Ok(SharedSegmenter(Arc::new(s)))
}

#[cfg(not(feature = "onnx"))]
fn onnx(_: Option<&PathBuf>, _: bool) -> anyhow::Result<SharedSegmenter> {
    Err(anyhow::anyhow!(
        "--segmenter onnx: this stitch was built without ONNX Runtime; build it with \
         `cargo build --release --features onnx` and set ORT_DYLIB_PATH (docs/perception.md)"
    ))
    .context("--segmenter")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn choices_parse_and_print_back() {
        for s in ["classical", "onnx", "onnx-fast", "onnx:models/mine.onnx"] {
            let c: SegmenterChoice = s.parse().expect(s);
            assert_eq!(c.to_string(), s);
        }
        for bad in ["", "onnx:", "unet", "ONNX", "onnx-slow"] {
            assert!(bad.parse::<SegmenterChoice>().is_err(), "{bad}");
        }
    }
}
