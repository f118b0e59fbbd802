//! The learned segmenter through ONNX Runtime (feature `onnx`; ORT_DYLIB_PATH names
//! libonnxruntime.so 1.31: `.ci/run` sets it from the tests' Python venv).
#![cfg(feature = "onnx")]

use std::path::PathBuf;
use stitch_perception::onnx::OnnxSegmenter;
use stitch_perception::{PerceptionError, Rect, Segmenter};
use stitch_robot::RgbImage;

fn models() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("models")
}

fn committed() -> OnnxSegmenter {
    OnnxSegmenter::from_file(&models().join("needle_thread_unet.onnx"), 1)
        .unwrap_or_else(|e| panic!("the committed model: {e}"))
}

fn reference_input() -> RgbImage {
    let img = image::open(models().join("reference/input.png"))
        .expect("reference input")
        .to_rgb8();
    RgbImage {
        width: img.width(),
        height: img.height(),
        data: img.into_raw(),
    }
}

/// Logits written outside the project (`reference/NAME-logits.bin`: PyTorch's for the reference
/// input, by train.py; `reference/shrunk_logits.bin`: by shrunk_reference.py): three
/// little-endian u32 (channels, height, width), then the floats.
fn reference_logits(file: &str) -> (Vec<usize>, Vec<f32>) {
    let bytes = std::fs::read(models().join("reference").join(file)).expect("logits");
    let dims: Vec<usize> = bytes[..12]
        .chunks_exact(4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as usize)
        .collect();
    let data = bytes[12..]
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    (dims, data)
}

#[test]
fn the_committed_models_give_pytorchs_logits_on_the_reference_input() {
    for name in ["needle_thread_unet", "needle_thread_unet_fast"] {
        gives_pytorchs_logits(name);
    }
}

/// The committed model `NAME.onnx` gives `reference/NAME-logits.bin` (train.py's PyTorch
/// logits) on the reference input, and the masks those logits make.
fn gives_pytorchs_logits(name: &str) {
    let mut s = OnnxSegmenter::from_file(&models().join(format!("{name}.onnx")), 1).expect(name);
    // PyTorch's logits are at the crop's own size: the model's enlarging left out here (the
    // enlarged reference below checks it).
    s.max_upscale = 1.0;
    let img = reference_input();
    let (dims, want) = reference_logits(&format!("{name}-logits.bin"));
    assert_eq!(dims, vec![2, img.height as usize, img.width as usize]);
    let [needle, thread] = s
        .logits(&img, Rect::full(img.width, img.height))
        .expect("logits");
    let n = needle.len();
    assert_eq!(n, (img.width * img.height) as usize);
    let got: Vec<f32> = needle.into_iter().chain(thread).collect();
    let worst = got
        .iter()
        .zip(&want)
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert!(
        worst < 1e-3,
        "{name}: largest difference from PyTorch's logits: {worst}"
    );
    // The masks are the logits above zero (then needle specks dropped).
    let m = s
        .segment(&img, Rect::full(img.width, img.height))
        .expect("masks");
    let thread_want: Vec<u8> = want[n..].iter().map(|&v| u8::from(v > 0.0)).collect();
    assert_eq!(m.thread, thread_want);
    let needle_want = want[..n].iter().filter(|&&v| v > 0.0).count();
    assert!(m.needle_count() <= needle_want);
}

/// The image `shrunk_reference.py` draws (its `pattern`).
fn shrunk_pattern(w: u32, h: u32) -> RgbImage {
    let mut data = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..u64::from(h) {
        for x in 0..u64::from(w) {
            data.extend([
                ((37 * x + 11 * y) % 251) as u8,
                ((17 * x + 29 * y) % 241) as u8,
                ((x * y + 3 * x) % 239) as u8,
            ]);
        }
    }
    RgbImage {
        width: w,
        height: h,
        data,
    }
}

/// A region wider than the model's side: shrunk as train.py shrinks its crops (PIL's box
/// filter) and the logits brought back as PyTorch's bilinear interpolation does, checked
/// against ONNX Runtime run from Python on the same image (every third row and column).
#[test]
fn a_shrunk_region_gives_the_logits_onnx_runtime_gives_from_python() {
    let s = committed();
    assert_eq!(s.max_side, 256, "the reference was made at a side of 256");
    matches_python(&s, 300, 41, "shrunk_logits.bin");
}

/// A region below the model's side, enlarged by its `stitch.max_upscale` (1.5, from the
/// committed model's metadata) bilinearly and the logits brought back, checked against
/// ONNX Runtime run from Python on the same image.
#[test]
fn an_enlarged_region_gives_the_logits_onnx_runtime_gives_from_python() {
    let s = committed();
    assert_eq!(
        (s.max_side, s.max_upscale),
        (256, 1.5),
        "the committed model's metadata"
    );
    matches_python(&s, 100, 40, "enlarged_logits.bin");
    let fast = OnnxSegmenter::from_file(&models().join("needle_thread_unet_fast.onnx"), 1)
        .expect("the fast model");
    assert_eq!((fast.max_side, fast.max_upscale), (240, 1.5));
}

/// `s` on `shrunk_pattern(w, h)` gives the logits in `file` (every third row and column,
/// made by shrunk_reference.py).
fn matches_python(s: &OnnxSegmenter, w: u32, h: u32, file: &str) {
    let img = shrunk_pattern(w, h);
    let (dims, want) = reference_logits(file);
    let (rows, cols) = (h.div_ceil(3) as usize, w.div_ceil(3) as usize);
    assert_eq!(dims, vec![2, rows, cols]);
    let [needle, thread] = s
        .logits(&img, Rect::full(img.width, img.height))
        .expect("logits");
    let mut worst = 0.0f32;
    for (c, plane) in [needle, thread].iter().enumerate() {
        let n = rows * cols;
        for (k, &v) in want[c * n..(c + 1) * n].iter().enumerate() {
            let (y, x) = (3 * (k / cols), 3 * (k % cols));
            worst = worst.max((plane[y * w as usize + x] - v).abs());
        }
    }
    assert!(
        worst < 1e-3,
        "{file}: largest difference from the reference's logits: {worst}"
    );
}

#[test]
fn a_region_larger_than_the_models_side_is_shrunk_and_brought_back() {
    let s = committed();
    let (w, h) = (700u32, 90u32);
    let img = RgbImage {
        width: w,
        height: h,
        data: (0..w * h * 3).map(|i| (i % 251) as u8).collect(),
    };
    let roi = Rect {
        x0: 10,
        y0: 5,
        x1: 690,
        y1: 85,
    };
    let [n, t] = s.logits(&img, roi).expect("logits");
    assert_eq!(n.len(), (roi.width() * roi.height()) as usize);
    assert_eq!(t.len(), n.len());
    assert!(n.iter().chain(&t).all(|v| v.is_finite()));
    let m = s.segment(&img, roi).expect("masks");
    assert_eq!(m.roi, roi);
    // An empty region gives empty masks, not an error.
    let empty = Rect {
        x0: 5,
        y0: 5,
        x1: 5,
        y1: 9,
    };
    assert_eq!(s.segment(&img, empty).expect("empty").needle.len(), 0);
}

fn config_message(e: PerceptionError) -> String {
    match e {
        PerceptionError::Config { message } => message,
        other => panic!("expected a configuration error, got {other:?}"),
    }
}

#[test]
fn a_file_that_is_not_a_model_is_a_clear_error() {
    let e = OnnxSegmenter::from_bytes(b"not an onnx model at all", "garbage.onnx", 1)
        .expect_err("garbage loads");
    let m = config_message(e);
    assert!(
        m.contains("garbage.onnx") && m.contains("not a model"),
        "{m}"
    );
    // Truncated: the committed model cut in half.
    let bytes = std::fs::read(models().join("needle_thread_unet.onnx")).expect("model");
    let e = OnnxSegmenter::from_bytes(&bytes[..bytes.len() / 2], "half.onnx", 1)
        .expect_err("half a model loads");
    assert!(config_message(e).contains("half.onnx"));
    let e = OnnxSegmenter::from_file(&models().join("no-such-model.onnx"), 1)
        .expect_err("a missing file loads");
    assert!(config_message(e).contains("cannot read"));
}

#[test]
fn a_model_with_the_wrong_input_shape_is_refused_with_the_contract() {
    let e = OnnxSegmenter::from_file(&models().join("wrong_input.onnx"), 1)
        .expect_err("a one-channel model loads");
    let m = config_message(e);
    assert!(m.contains("wrong_input.onnx"), "{m}");
    assert!(m.contains("[1, 3, H, W]"), "{m}");
}

/// The committed model with one more `metadata_props` entry: a serialised protobuf message
/// followed by more of its fields is the message with them merged in (ModelProto's field 14,
/// a StringStringEntryProto of key 1 and value 2), so no ONNX library is needed here.
fn with_metadata(key: &str, value: &str) -> Vec<u8> {
    let mut bytes = std::fs::read(models().join("needle_thread_unet_fast.onnx")).expect("model");
    let mut entry = vec![0x0a, key.len() as u8];
    entry.extend(key.as_bytes());
    entry.extend([0x12, value.len() as u8]);
    entry.extend(value.as_bytes());
    bytes.extend([(14 << 3) | 2, entry.len() as u8]);
    bytes.extend(entry);
    bytes
}

#[test]
fn a_region_scale_out_of_range_in_the_metadata_is_a_clear_error() {
    // The appended entry is read (a value in range loads and is used) ...
    let s = OnnxSegmenter::from_bytes(&with_metadata("stitch.max_side", "128"), "ok.onnx", 1)
        .expect("a model with a side of 128");
    assert_eq!(s.max_side, 128);
    // ... and one out of range is refused, naming the model, the key and the value.
    for (key, value) in [("stitch.max_upscale", "0.5"), ("stitch.max_side", "big")] {
        let e = OnnxSegmenter::from_bytes(&with_metadata(key, value), "scaled.onnx", 1)
            .expect_err(value);
        let m = config_message(e);
        assert!(
            m.contains("scaled.onnx") && m.contains(key) && m.contains(value),
            "{m}"
        );
    }
}
