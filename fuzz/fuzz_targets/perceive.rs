//! The needle pipeline (`stitch perceive needle`) and the thread tracer (`stitch perceive
//! thread`) on any pair of images: PNG bytes decoded as `perceive` decodes a file, or raw
//! pixels of a window of the mock's camera at full resolution, with or without a hint. An
//! estimate (a trace) or a typed failure, never a panic, and never one that is not finite.
#![no_main]

use libfuzzer_sys::fuzz_target;
use stitch_perception::ColorSegmenter;
use stitch_perception::pipeline::{JawHint, NeedleEnd, NeedleHint, NeedlePipeline, TissueHint};
use stitch_perception::thread::{ThreadHint, ThreadParams, trace};
use stitch_robot::{Needle, Point, RgbImage};
use stitch_sim::CameraConfig;

/// Where the window starts in the mock's frame, pixels.
const WINDOW: (u32, u32) = (400, 150);

fuzz_target!(|data: &[u8]| {
    if data.starts_with(b"\x89PNG") {
        let _ = stitch_cli::inputs::image(data);
        return;
    }
    let [a, b, mode, seed, pixels @ ..] = data else {
        return;
    };
    if pixels.is_empty() {
        return;
    }
    // A window of the mock's camera at full resolution, 32×24 to 400×160 pixels from
    // (400, 150) of its 1280×960 frame: where a needle held at the start is seen, in both
    // views, at the size the pipeline was made for (a scaled-down frame loses the wire).
    let (w, h) = (
        32 + u32::from(*a) * 368 / 255,
        24 + u32::from(*b) * 136 / 255,
    );
    let base = CameraConfig::default();
    let mut calibration = CameraConfig {
        width: w,
        height: h,
        ..base.clone()
    }
    .calibration();
    calibration.cx = f64::from(base.width) / 2.0 - f64::from(WINDOW.0);
    calibration.cy = f64::from(base.height) / 2.0 - f64::from(WINDOW.1);
    let Ok(pipeline) = NeedlePipeline::classical(calibration.clone(), Needle::default()) else {
        return;
    };
    let n = (w * h * 3) as usize;
    let mut bytes = pixels.iter().copied().cycle();
    let mut image = || RgbImage {
        width: w,
        height: h,
        data: bytes.by_ref().take(n).collect(),
    };
    let (left, right) = (image(), image());
    let jaw = Point::new(0.02, 0.01, -0.1);
    let hint = match mode % 4 {
        0 => None,
        1 => Some(NeedleHint::Held(JawHint {
            jaw,
            end: NeedleEnd::Swage,
        })),
        2 => Some(NeedleHint::Held(JawHint {
            jaw,
            end: NeedleEnd::Tip,
        })),
        _ => Some(NeedleHint::InTissue(TissueHint {
            entry: Point::new(0.015, 0.01, -0.115),
            exit: Point::new(0.025, 0.01, -0.115),
        })),
    };
    let seed = u64::from(*seed);
    let out = match &hint {
        Some(NeedleHint::InTissue(holes)) => {
            pipeline.estimate_in_tissue(&left, &right, holes, seed)
        }
        Some(NeedleHint::Held(jaw)) => pipeline.estimate(&left, &right, Some(jaw), seed),
        None => pipeline.estimate(&left, &right, None, seed),
    };
    if let Ok(out) = out {
        let t = out.pose.translation.vector;
        assert!(t.iter().all(|v| v.is_finite()), "{:?}", out.pose);
        assert!(out.confidence.is_finite(), "{}", out.confidence);
    }
    // The thread from the holes' exit (or its tail) to a swage by the jaw.
    let thread = ThreadHint {
        start: (mode % 2 == 0).then(|| Point::new(0.025, 0.01, -0.115)),
        swage: jaw,
        length_m: (mode % 3 == 0).then_some(0.05),
    };
    let seg = ColorSegmenter::default();
    if let Ok(t) = trace(&ThreadParams::default(), &seg, &calibration, &left, &right, &thread) {
        assert!(t.length_m.is_finite() && t.points.len() == t.sigma_m.len());
        for (p, s) in t.points.iter().zip(&t.sigma_m) {
            assert!(p.coords.iter().all(|v| v.is_finite()) && s.is_finite(), "{p:?} {s}");
        }
    }
});
