//! A learned segmenter: any ONNX model that keeps the contract below, run by ONNX Runtime
//! through `ort` (feature `onnx`). ONNX Runtime is a native library loaded when the first
//! model is: the path in `ORT_DYLIB_PATH` (`libonnxruntime.so` 1.31 from the PyPI
//! `onnxruntime==1.31.1` wheel, `onnxruntime/capi/`). Nothing native is needed to build.
//!
//! # The model contract
//! - One input, float32 `[1, 3, H, W]`: the region's RGB, `value / 255` (as stored, not
//!   linearised), rows top to bottom. H and W are multiples of 8 (the runner pads the region
//!   by repeating its last row and column).
//! - The first output, float32 `[1, 2, H, W]`: logits, channel 0 the needle, channel 1 the
//!   thread. A pixel is in a mask where its logit is above 0.
//! - H and W may be anything the model accepts (dynamic axes); a region whose longer side
//!   is above [`OnnxSegmenter::max_side`] is shrunk to it first (box filter), one whose
//!   longer side is below it is enlarged towards it by at most
//!   [`OnnxSegmenter::max_upscale`] (bilinear; 1 by default: not enlarged), and the logits
//!   are brought back to the region's pixels by bilinear interpolation.
//! - Optional metadata (the ONNX file's `metadata_props`) sets those two for the model:
//!   `stitch.max_side` (pixels, an integer from 8 to 4096; 256 when absent) and
//!   `stitch.max_upscale` (a number from 1 to 4; 1 when absent). A value out of range or
//!   not a number is an error when the model is loaded.
//!
//! Finding the region (`locate`) and the sub-pixel edge measure (`needleness`) stay with the
//! colour segmenter's rules: the model decides which pixels of the region are needle and
//! thread. Needle specks smaller than the colour segmenter's `min_component_px` are dropped,
//! as its own are.

use crate::PerceptionError;
use crate::segment::{ColorSegmenter, Masks, Rect, Segmenter};
use ort::session::Session;
use ort::session::builder::GraphOptimizationLevel;
use ort::value::{TensorRef, ValueType};
use std::path::Path;
use std::sync::{Mutex, OnceLock};
use stitch_robot::RgbImage;

/// Input and output sides are padded to a multiple of this.
pub const SIDE_MULTIPLE: u32 = 8;

/// The environment variable naming ONNX Runtime's library.
pub const DYLIB_VAR: &str = "ORT_DYLIB_PATH";

/// ONNX Runtime's environment, made once per process (the library is loaded once).
static ENVIRONMENT: OnceLock<Result<ort::environment::Environment, String>> = OnceLock::new();

fn environment() -> Result<&'static ort::environment::Environment, PerceptionError> {
    let made = ENVIRONMENT.get_or_init(|| {
        let path = std::env::var_os(DYLIB_VAR)
            .map(std::path::PathBuf::from)
            .ok_or_else(|| {
                format!(
                    "ONNX Runtime is not found: set {DYLIB_VAR} to its library, \
                 libonnxruntime.so 1.31 (in the PyPI wheel onnxruntime==1.31.1, \
                 onnxruntime/capi/; docs/perception.md)"
                )
            })?;
        ort::init_from(&path)
            .map_err(|e| format!("cannot load ONNX Runtime from {}: {e}", path.display()))?
            .with_name("stitch")
            .build()
            .map_err(|e| format!("cannot start ONNX Runtime: {e}"))
    });
    made.as_ref()
        .map_err(|m| PerceptionError::Config { message: m.clone() })
}

/// Needle and thread masks from an ONNX model (see the module's contract).
#[derive(Debug)]
pub struct OnnxSegmenter {
    /// `ort` runs one inference at a time per session.
    session: Mutex<Session>,
    input: String,
    /// Where the model came from, for messages.
    source: String,
    /// A region whose longer side is above this is shrunk to it before the model sees it,
    /// pixels (the committed models were trained on regions of at most 256). From the
    /// model's `stitch.max_side` metadata, 256 when it has none.
    pub max_side: u32,
    /// A region whose longer side is below `max_side` is enlarged towards it by at most
    /// this factor (1: never enlarged). From the model's `stitch.max_upscale` metadata, 1
    /// when it has none.
    pub max_upscale: f64,
    /// Finds the region and measures edges.
    pub locator: ColorSegmenter,
}

fn model_error(source: &str, why: impl std::fmt::Display) -> PerceptionError {
    PerceptionError::Config {
        message: format!("segmentation model {source}: {why}"),
    }
}

impl OnnxSegmenter {
    /// The model in the file at `path`, run on `threads` threads.
    pub fn from_file(path: &Path, threads: usize) -> Result<Self, PerceptionError> {
        let bytes = std::fs::read(path).map_err(|e| PerceptionError::Config {
            message: format!("cannot read the segmentation model {}: {e}", path.display()),
        })?;
        Self::from_bytes(&bytes, &path.display().to_string(), threads)
    }

    /// The model in `bytes` (an ONNX file's contents), named `source` in messages, run on
    /// `threads` threads. Checks the contract: the input's and output's types and shapes,
    /// and one inference on a 16×16 region.
    pub fn from_bytes(bytes: &[u8], source: &str, threads: usize) -> Result<Self, PerceptionError> {
        let env = environment()?;
        let err = |e: &dyn std::fmt::Display| model_error(source, e);
        let session = Session::builder(env)
            .and_then(|b| Ok(b.with_optimization_level(GraphOptimizationLevel::Level3)?))
            .and_then(|b| Ok(b.with_intra_threads(threads.max(1))?))
            .and_then(|b| Ok(b.with_inter_threads(1)?))
            // Every region has its own size: a memory plan per shape does not pay.
            .and_then(|b| Ok(b.with_memory_pattern(false)?))
            .map_err(|e| err(&e))?
            .commit_from_memory(bytes)
            .map_err(|e| err(&format!("not a model ONNX Runtime can load ({e})")))?;
        let [input] = session.inputs() else {
            return Err(err(&format!(
                "has {} inputs; the contract wants one, float32 [1, 3, H, W]",
                session.inputs().len()
            )));
        };
        check_outlet(input.dtype(), 3)
            .map_err(|why| err(&format!("input {}: {why}", input.name())))?;
        let Some(output) = session.outputs().first() else {
            return Err(err(
                &"has no output; the contract wants float32 [1, 2, H, W]",
            ));
        };
        check_outlet(output.dtype(), 2)
            .map_err(|why| err(&format!("output {}: {why}", output.name())))?;
        let (max_side, max_upscale) = {
            let meta = session.metadata().map_err(|e| err(&e))?;
            let read = |key: &str| meta.custom(key);
            region_scale(read).map_err(|why| err(&why))?
        };
        let me = Self {
            input: input.name().to_string(),
            session: Mutex::new(session),
            source: source.to_string(),
            max_side,
            max_upscale,
            locator: ColorSegmenter::default(),
        };
        // One inference, so that a model that loads but cannot run says so now, not mid-run.
        let side = 2 * SIDE_MULTIPLE as usize;
        me.infer(&vec![0.0; 3 * side * side], side, side)?;
        Ok(me)
    }

    /// The logits `[2, h, w]` the model gives for an input `[3, h, w]` (h, w multiples of
    /// [`SIDE_MULTIPLE`]).
    fn infer(&self, input: &[f32], h: usize, w: usize) -> Result<Vec<f32>, PerceptionError> {
        let err = |why: String| PerceptionError::Model {
            message: format!("{}: {why}", self.source),
        };
        let tensor = TensorRef::from_array_view(([1usize, 3, h, w], input))
            .map_err(|e| err(e.to_string()))?;
        let mut session = self
            .session
            .lock()
            .map_err(|_| err("a previous inference panicked".into()))?;
        let outputs = session
            .run(ort::inputs![self.input.as_str() => tensor])
            .map_err(|e| err(format!("inference failed: {e}")))?;
        let (shape, data) = outputs[0]
            .try_extract_tensor::<f32>()
            .map_err(|e| err(format!("output is not a float32 tensor: {e}")))?;
        let want = [1, 2, h as i64, w as i64];
        if **shape != want {
            return Err(err(format!(
                "gave an output of shape {:?} for an input of [1, 3, {h}, {w}]; the contract \
                 wants {want:?}",
                &**shape
            )));
        }
        Ok(data.to_vec())
    }

    /// The needle's and the thread's logits over `roi` (clipped to the image), row-major,
    /// at the region's pixels.
    pub fn logits(&self, image: &RgbImage, roi: Rect) -> Result<[Vec<f32>; 2], PerceptionError> {
        let roi = roi.clipped(image.width, image.height);
        let (rw, rh) = (roi.width() as usize, roi.height() as usize);
        if rw == 0 || rh == 0 {
            return Ok([Vec::new(), Vec::new()]);
        }
        // The model's grid: the region shrunk so its longer side fits (or enlarged towards
        // it, by at most `max_upscale`), then padded.
        let scale = (f64::from(self.max_side.max(SIDE_MULTIPLE)) / rw.max(rh) as f64)
            .min(self.max_upscale.max(1.0));
        let mw = ((rw as f64 * scale).round() as usize).max(1);
        let mh = ((rh as f64 * scale).round() as usize).max(1);
        let m = SIDE_MULTIPLE as usize;
        let (pw, ph) = (mw.div_ceil(m) * m, mh.div_ceil(m) * m);
        let input = model_input(image, roi, mw, mh, pw, ph);
        let out = self.infer(&input, ph, pw)?;
        let (needle, thread) = out.split_at(pw * ph);
        if mw == rw && mh == rh {
            let crop = |c: &[f32]| -> Vec<f32> {
                (0..rh)
                    .flat_map(|y| c[y * pw..y * pw + rw].iter().copied())
                    .collect()
            };
            return Ok([crop(needle), crop(thread)]);
        }
        // Bilinear, pixel centres aligned (PyTorch's align_corners=False).
        let (xs, ys) = (taps(rw, mw), taps(rh, mh));
        let up = |c: &[f32]| -> Vec<f32> {
            let mut v = Vec::with_capacity(rw * rh);
            for &(y0, y1, ty) in &ys {
                let (r0, r1) = (&c[y0 * pw..y0 * pw + mw], &c[y1 * pw..y1 * pw + mw]);
                v.extend(xs.iter().map(|&(x0, x1, tx)| {
                    let a = r0[x0] + (r0[x1] - r0[x0]) * tx;
                    let b = r1[x0] + (r1[x1] - r1[x0]) * tx;
                    a + (b - a) * ty
                }));
            }
            v
        };
        Ok([up(needle), up(thread)])
    }
}

/// Bilinear taps, pixel centres aligned (PyTorch's `align_corners=False`), for each of `n`
/// samples over `len` source pixels: the two source indices and the second's weight.
fn taps(n: usize, len: usize) -> Vec<(usize, usize, f32)> {
    let s = len as f64 / n as f64;
    (0..n)
        .map(|i| {
            let f = ((i as f64 + 0.5) * s - 0.5).clamp(0.0, (len - 1) as f64);
            let a = f.floor() as usize;
            (a, (a + 1).min(len - 1), (f - f.floor()) as f32)
        })
        .collect()
}

/// The model's region scale, `(max_side, max_upscale)`, from its metadata (`read` looks a
/// key up): 256 and 1 where a key is absent.
fn region_scale(read: impl Fn(&str) -> Option<String>) -> Result<(u32, f64), String> {
    let max_side = match read(MAX_SIDE_KEY) {
        None => 256,
        Some(v) => v
            .trim()
            .parse::<u32>()
            .ok()
            .filter(|s| (SIDE_MULTIPLE..=4096).contains(s))
            .ok_or_else(|| {
                format!("metadata {MAX_SIDE_KEY} = {v:?}: want an integer from 8 to 4096 (pixels)")
            })?,
    };
    let max_upscale = match read(MAX_UPSCALE_KEY) {
        None => 1.0,
        Some(v) => v
            .trim()
            .parse::<f64>()
            .ok()
            .filter(|u| (1.0..=4.0).contains(u))
            .ok_or_else(|| {
                format!("metadata {MAX_UPSCALE_KEY} = {v:?}: want a number from 1 to 4")
            })?,
    };
    Ok((max_side, max_upscale))
}

/// The metadata key that sets [`OnnxSegmenter::max_side`].
pub const MAX_SIDE_KEY: &str = "stitch.max_side";
/// The metadata key that sets [`OnnxSegmenter::max_upscale`].
pub const MAX_UPSCALE_KEY: &str = "stitch.max_upscale";

/// Whether an input or output is float32, rank 4, one image, `channels` channels (a
/// dynamic size is accepted).
fn check_outlet(t: &ValueType, channels: i64) -> Result<(), String> {
    let want = format!("the contract wants float32 [1, {channels}, H, W]");
    let ValueType::Tensor { ty, shape, .. } = t else {
        return Err(format!("is not a tensor; {want}"));
    };
    if *ty != ort::value::TensorElementType::Float32 {
        return Err(format!("is {ty:?}; {want}"));
    }
    let ok = shape.len() == 4
        && (shape[0] == 1 || shape[0] < 0)
        && (shape[1] == channels || shape[1] < 0);
    if !ok {
        return Err(format!("has shape {:?}; {want}", &**shape));
    }
    Ok(())
}

/// The model's input `[3, ph, pw]`: the region box-filtered down to `mw × mh` (or, where
/// that is larger than the region, interpolated up to it bilinearly), values `/ 255`,
/// padded right and below by repeating the last column and row.
fn model_input(
    image: &RgbImage,
    roi: Rect,
    mw: usize,
    mh: usize,
    pw: usize,
    ph: usize,
) -> Vec<f32> {
    let (rw, rh) = (roi.width() as usize, roi.height() as usize);
    let w = image.width as usize;
    let mut out = vec![0.0f32; 3 * pw * ph];
    let plane = pw * ph;
    // Source span of model cell `i` of `n` over `len` pixels: the pixels whose centres lie
    // in the cell, as PIL's box filter takes them (the training script's `fit_side`), so
    // that the cells' centres are where the bilinear upsampling below puts them. (Cutting at
    // `⌊i·len/n⌋` instead shifted the model's view by up to half a pixel: on the independent
    // set's regions above 256 px, thread IoU 0.75 against PyTorch's 0.84 on the same crops.)
    let span = |i: usize, n: usize, len: usize| -> (usize, usize) {
        let edge = |k: usize| (2 * k * len + n) / (2 * n);
        let a = edge(i).min(len - 1);
        let b = edge(i + 1).max(a + 1).min(len);
        (a, b)
    };
    let enlarged = mw > rw || mh > rh;
    if enlarged {
        // Enlarged (the scale is the same both ways, so neither side shrinks): bilinear,
        // pixel centres aligned, as PyTorch's `interpolate(..., align_corners=False)` that
        // train.py's `fit_side` enlarges with.
        let (xs, ys) = (taps(mw, rw), taps(mh, rh));
        let row = |y: usize| {
            let start = ((roi.y0 as usize + y) * w + roi.x0 as usize) * 3;
            &image.data[start..start + rw * 3]
        };
        for (my, &(y0, y1, ty)) in ys.iter().enumerate() {
            let (r0, r1) = (row(y0), row(y1));
            for (mx, &(x0, x1, tx)) in xs.iter().enumerate() {
                for c in 0..3 {
                    let at = |r: &[u8], x: usize| f32::from(r[x * 3 + c]);
                    let a = at(r0, x0) + (at(r0, x1) - at(r0, x0)) * tx;
                    let b = at(r1, x0) + (at(r1, x1) - at(r1, x0)) * tx;
                    out[c * plane + my * pw + mx] = (a + (b - a) * ty) / 255.0;
                }
            }
        }
    } else {
        for my in 0..mh {
            let (y0, y1) = span(my, mh, rh);
            for mx in 0..mw {
                let (x0, x1) = span(mx, mw, rw);
                let mut acc = [0u32; 3];
                for y in y0..y1 {
                    let row = (roi.y0 as usize + y) * w + roi.x0 as usize;
                    for x in x0..x1 {
                        let p = &image.data[(row + x) * 3..(row + x) * 3 + 3];
                        for c in 0..3 {
                            acc[c] += u32::from(p[c]);
                        }
                    }
                }
                let n = ((y1 - y0) * (x1 - x0)) as f32 * 255.0;
                for c in 0..3 {
                    out[c * plane + my * pw + mx] = acc[c] as f32 / n;
                }
            }
        }
    }
    for c in 0..3 {
        let p = &mut out[c * plane..(c + 1) * plane];
        for y in 0..ph {
            let sy = y.min(mh - 1);
            for x in 0..pw {
                if y < mh && x < mw {
                    continue;
                }
                p[y * pw + x] = p[sy * pw + x.min(mw - 1)];
            }
        }
    }
    out
}

impl Segmenter for OnnxSegmenter {
    fn locate(&self, image: &RgbImage, within: Rect) -> Option<Rect> {
        self.locator.locate(image, within)
    }

    fn candidates(&self, image: &RgbImage, within: Rect) -> Vec<Rect> {
        self.locator.candidates(image, within)
    }

    fn segment(&self, image: &RgbImage, roi: Rect) -> Result<Masks, PerceptionError> {
        let roi = roi.clipped(image.width, image.height);
        let [n, t] = self.logits(image, roi)?;
        let mut needle: Vec<u8> = n.iter().map(|&v| u8::from(v > 0.0)).collect();
        if self.locator.min_component_px > 1 {
            let (w, h) = (roi.width() as usize, roi.height() as usize);
            crate::segment::drop_specks(&mut needle, w, h, self.locator.min_component_px as usize);
        }
        Ok(Masks {
            roi,
            needle,
            thread: t.iter().map(|&v| u8::from(v > 0.0)).collect(),
        })
    }

    fn needleness(&self, rgb: [u8; 3]) -> f32 {
        self.locator.needleness(rgb)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_input_is_the_region_scaled_to_0_1_and_padded_by_its_edge() {
        let img = RgbImage {
            width: 4,
            height: 3,
            data: (0..36).map(|i| (i * 7) as u8).collect(),
        };
        let roi = Rect {
            x0: 1,
            y0: 1,
            x1: 4,
            y1: 3,
        };
        let v = model_input(&img, roi, 3, 2, 8, 8);
        let px = |x: usize, y: usize, c: usize| f32::from(img.data[(y * 4 + x) * 3 + c]) / 255.0;
        assert!((v[0] - px(1, 1, 0)).abs() < 1e-6);
        assert!((v[64 + 8 + 2] - px(3, 2, 1)).abs() < 1e-6);
        // Padding repeats the last column and row.
        assert!((v[7 * 8 + 7] - px(3, 2, 0)).abs() < 1e-6);
        assert!((v[5] - px(3, 1, 0)).abs() < 1e-6);
        // Shrunk by two: each cell is the mean of its 2×1 block.
        let roi = Rect {
            x0: 0,
            y0: 0,
            x1: 4,
            y1: 1,
        };
        let v = model_input(&img, roi, 2, 1, 8, 8);
        assert!((v[1] - (px(2, 0, 0) + px(3, 0, 0)) / 2.0).abs() < 1e-6);
    }

    /// Shrunk by a fraction, a cell is the mean of the pixels whose centres it covers, as
    /// PIL's box filter (which trained the committed model) takes them. The expected values
    /// are PIL 11's `Image.resize((3, 1), Image.BOX)` of these rows, rounded to 8 bits there.
    #[test]
    fn a_fractional_shrink_takes_the_pixels_pils_box_filter_takes() {
        let rows: [(Vec<u8>, [[u8; 3]; 3]); 2] = [
            (
                vec![
                    10, 200, 30, 50, 60, 70, 90, 0, 255, 130, 140, 150, 170, 180, 190,
                ],
                [[30, 130, 50], [90, 0, 255], [150, 160, 170]],
            ),
            (
                (0..21).map(|i| i * 11).collect(),
                [[17, 28, 39], [99, 110, 121], [182, 193, 204]],
            ),
        ];
        for (data, want) in rows {
            let w = (data.len() / 3) as u32;
            let img = RgbImage {
                width: w,
                height: 1,
                data,
            };
            let roi = Rect {
                x0: 0,
                y0: 0,
                x1: w,
                y1: 1,
            };
            let v = model_input(&img, roi, 3, 1, 8, 8);
            for (x, px) in want.iter().enumerate() {
                for (c, &p) in px.iter().enumerate() {
                    let got = v[c * 64 + x] * 255.0;
                    assert!(
                        (got - f32::from(p)).abs() <= 0.5,
                        "{w} px to 3, cell {x} channel {c}: {got} against PIL's {p}"
                    );
                }
            }
        }
    }

    /// Enlarged by 1.5, a cell is the bilinear blend of the pixels round its centre, pixel
    /// centres aligned: cell 0 of 6 sits at source x = -1/6 (clamped to pixel 0), cell 1 at
    /// 1/2 (halfway between pixels 0 and 1), cell 2 at 7/6. The values are PyTorch's
    /// `F.interpolate(size=(1, 6), mode="bilinear", align_corners=False)` of the row.
    #[test]
    fn an_enlarged_region_is_interpolated_with_pixel_centres_aligned() {
        let img = RgbImage {
            width: 4,
            height: 1,
            data: [0u8, 60, 120, 240]
                .iter()
                .flat_map(|&v| [v, v / 2, 255 - v])
                .collect(),
        };
        let roi = Rect {
            x0: 0,
            y0: 0,
            x1: 4,
            y1: 1,
        };
        let v = model_input(&img, roi, 6, 1, 8, 8);
        let want = [0.0, 30.0, 70.0, 110.0, 180.0, 240.0];
        for (x, w) in want.iter().enumerate() {
            assert!(
                (v[x] * 255.0 - w).abs() < 1e-3,
                "cell {x}: {} against {w}",
                v[x] * 255.0
            );
            let inv = v[2 * 64 + x] * 255.0;
            assert!((inv - (255.0 - w)).abs() < 1e-3, "cell {x}, blue: {inv}");
        }
        // The one row is repeated below it (padding).
        assert!((v[8 + 3] - v[3]).abs() < 1e-6);
    }

    #[test]
    fn the_region_scale_comes_from_the_models_metadata_and_bad_values_are_named() {
        let meta = |pairs: &'static [(&'static str, &'static str)]| {
            move |k: &str| {
                pairs
                    .iter()
                    .find(|(key, _)| *key == k)
                    .map(|(_, v)| v.to_string())
            }
        };
        assert_eq!(region_scale(meta(&[])), Ok((256, 1.0)));
        assert_eq!(
            region_scale(meta(&[(MAX_SIDE_KEY, "240"), (MAX_UPSCALE_KEY, "1.5")])),
            Ok((240, 1.5))
        );
        for (key, bad) in [
            (MAX_SIDE_KEY, "4"),
            (MAX_SIDE_KEY, "two hundred"),
            (MAX_UPSCALE_KEY, "0.5"),
            (MAX_UPSCALE_KEY, "NaN"),
        ] {
            let pairs: &'static [(&str, &str)] = Box::leak(Box::new([(key, bad)]));
            let e = region_scale(meta(pairs)).expect_err(bad);
            assert!(e.contains(key) && e.contains(bad), "{e}");
        }
    }
}
