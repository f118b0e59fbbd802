//! Segmentation against truth: labelled crops around the needle from either set, the
//! training frames a learned segmenter is made from, and intersection over union of any
//! [`Segmenter`]'s masks.
//!
//! A crop is what a segmenter's `segment` is given in the pipeline: the needle's region
//! grown by a margin. Here the region comes from the truth labels (the needle's bounding box
//! in the view, grown by [`MARGIN_PX`]), so every segmenter is scored on the same pixels
//! whatever its `locate` would have found.

use crate::independent;
use crate::own;
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use std::time::{Duration, Instant};
use stitch_perception::PerceptionError;
use stitch_perception::segment::{Rect, Segmenter};
use stitch_robot::{Needle, Pose, RgbImage, Vector};
use stitch_sim::{CameraConfig, Label, PhantomView, StereoRenderer};

/// Margin around the needle's bounding box a crop adds, pixels (the classical segmenter's
/// default `margin_px`).
pub const MARGIN_PX: u32 = 24;

/// One view with its truth: the image and what each pixel shows ([`Label`] as `u8`).
#[derive(Clone, Debug, PartialEq)]
pub struct LabelledView {
    /// The whole image.
    pub image: RgbImage,
    /// Row-major labels over the whole image.
    pub labels: Vec<u8>,
    /// The needle's bounding box grown by [`MARGIN_PX`] (the region segmenters are scored
    /// over); `None` when no needle pixel is in view.
    pub roi: Option<Rect>,
}

impl LabelledView {
    /// A view and its labels; the region found from the labels.
    pub fn new(image: RgbImage, labels: Vec<u8>) -> Self {
        let roi =
            needle_box(&labels, image.width).map(|b| b.grown(MARGIN_PX, image.width, image.height));
        Self { image, labels, roi }
    }

    /// The image and labels cut to `r` (inside the image).
    pub fn crop(&self, r: Rect) -> (RgbImage, Vec<u8>) {
        let w = self.image.width as usize;
        let (cw, ch) = (r.width() as usize, r.height() as usize);
        let mut data = Vec::with_capacity(cw * ch * 3);
        let mut labels = Vec::with_capacity(cw * ch);
        for y in r.y0 as usize..r.y1 as usize {
            let row = y * w + r.x0 as usize;
            data.extend_from_slice(&self.image.data[row * 3..(row + cw) * 3]);
            labels.extend_from_slice(&self.labels[row..row + cw]);
        }
        (
            RgbImage {
                width: r.width(),
                height: r.height(),
                data,
            },
            labels,
        )
    }
}

/// The bounding box of the needle's pixels in a row-major label image `width` wide.
fn needle_box(labels: &[u8], width: u32) -> Option<Rect> {
    let w = width as usize;
    let mut b: Option<Rect> = None;
    for (i, _) in labels
        .iter()
        .enumerate()
        .filter(|&(_, &l)| l == Label::Needle as u8)
    {
        let (x, y) = ((i % w) as u32, (i / w) as u32);
        let r = b.get_or_insert(Rect {
            x0: x,
            y0: y,
            x1: x + 1,
            y1: y + 1,
        });
        r.x0 = r.x0.min(x);
        r.y0 = r.y0.min(y);
        r.x1 = r.x1.max(x + 1);
        r.y1 = r.y1.max(y + 1);
    }
    b
}

/// The left views of the own set's `n` samples from `seed` (the mock's renderer and
/// camera, as in [`own::run`]).
pub fn own_views(
    renderer: &StereoRenderer,
    phantom: &PhantomView,
    n: usize,
    seed: u64,
) -> Vec<LabelledView> {
    let needle = Needle::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed);
    own::dataset(n, seed, needle, phantom)
        .iter()
        .map(|s| {
            let pair = renderer.render(&s.scene, &Pose::identity(), &mut rng);
            LabelledView::new(pair.left, pair.truth.left_labels)
        })
        .collect()
}

/// The left views of the independent set's `n` samples from `seed` (another renderer, other
/// rigs: see [`independent`]). Slow: one to two seconds a view.
pub fn independent_views(n: usize, seed: u64) -> Vec<LabelledView> {
    independent::dataset(n, seed, Needle::default())
        .iter()
        .map(|s| {
            let image = independent::render_left(s);
            let (labels, _) = independent::render_labels(s);
            LabelledView::new(image, labels)
        })
        .collect()
}

/// Training views for a learned segmenter: the own set's scenes from `seed`, each seen by a
/// camera drawn afresh (focal length 700–2,200 px, 10–26 cm from the wound at 30–70° of
/// elevation, 20–90 % of the view's default noise to three times it, defocus 0.4–2.6 px,
/// lighting ± 35 %), both views. The renderer is the mock's: the independent set is what the
/// result is scored on.
pub fn training_views(
    phantom: &PhantomView,
    n: usize,
    seed: u64,
) -> Result<Vec<LabelledView>, String> {
    let needle = Needle::default();
    let mut rng = ChaCha8Rng::seed_from_u64(seed ^ 0x5e67_7a11);
    let samples = own::dataset(n, seed, needle, phantom);
    let mut out = Vec::with_capacity(2 * n);
    for s in &samples {
        let target = s.truth.translation.vector;
        let elevation = rng.random_range(30f64..70.0).to_radians();
        let azimuth = rng.random_range(60f64..120.0).to_radians();
        let distance = rng.random_range(0.10..0.26);
        let dir = Vector::new(
            elevation.cos() * azimuth.cos(),
            elevation.cos() * azimuth.sin(),
            elevation.sin(),
        );
        let eye = target + dir * distance;
        let config = CameraConfig {
            focal_px: rng.random_range(700.0..2200.0),
            eye: [eye.x, eye.y, eye.z],
            target: [target.x, target.y, target.z],
            noise_sigma: rng.random_range(0.6..9.0),
            blur_px: rng.random_range(0.4..2.6),
            lighting_variation: 0.35,
            ..CameraConfig::default()
        };
        let renderer = StereoRenderer::new(config, *phantom).map_err(|e| e.to_string())?;
        let pair = renderer.render(&s.scene, &Pose::identity(), &mut rng);
        for (image, labels) in [
            (pair.left, pair.truth.left_labels),
            (pair.right, pair.truth.right_labels),
        ] {
            let v = LabelledView::new(image, labels);
            if v.roi.is_some() {
                out.push(v);
            }
        }
    }
    Ok(out)
}

/// Intersection over union of one class, pooled over views.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct Overlap {
    /// Pixels both in the mask and in the truth.
    pub intersection: u64,
    /// Pixels in either.
    pub union: u64,
}

impl Overlap {
    /// Intersection over union (1 when both are empty).
    pub fn iou(&self) -> f64 {
        if self.union == 0 {
            1.0
        } else {
            self.intersection as f64 / self.union as f64
        }
    }
    fn add(&mut self, mask: &[u8], truth: &[u8], label: Label) {
        for (&m, &t) in mask.iter().zip(truth) {
            let (m, t) = (m != 0, t == label as u8);
            self.intersection += u64::from(m && t);
            self.union += u64::from(m || t);
        }
    }
}

/// A segmenter's score over a set of views.
#[derive(Clone, Debug, PartialEq)]
pub struct SegmentationScore {
    /// Views scored (those with a needle in view).
    pub views: usize,
    /// The needle's masks against the truth.
    pub needle: Overlap,
    /// The thread's masks against the truth.
    pub thread: Overlap,
    /// Time of each view's `segment` call, in view order.
    pub times: Vec<Duration>,
    /// Pixels in each view's region, in view order.
    pub pixels: Vec<u64>,
}

/// Score `segmenter` on every view with a needle in view: its masks over the view's region
/// against the truth's needle and thread labels, and its time per region. Fails only if the
/// segmenter does (a model that cannot run).
pub fn score(
    segmenter: &dyn Segmenter,
    views: &[LabelledView],
) -> Result<SegmentationScore, PerceptionError> {
    let mut s = SegmentationScore {
        views: 0,
        needle: Overlap::default(),
        thread: Overlap::default(),
        times: Vec::new(),
        pixels: Vec::new(),
    };
    for v in views {
        let Some(roi) = v.roi else { continue };
        let t0 = Instant::now();
        let masks = segmenter.segment(&v.image, roi)?;
        s.times.push(t0.elapsed());
        let (_, truth) = v.crop(roi);
        s.needle.add(&masks.needle, &truth, Label::Needle);
        s.thread.add(&masks.thread, &truth, Label::Thread);
        s.pixels
            .push(u64::from(roi.width()) * u64::from(roi.height()));
        s.views += 1;
    }
    Ok(s)
}

/// The time of `segmenter`'s `segment` call on each view with a needle in view, in view
/// order (as [`score`] times them, the masks not scored): for timing again.
pub fn time(
    segmenter: &dyn Segmenter,
    views: &[LabelledView],
) -> Result<Vec<Duration>, PerceptionError> {
    let mut times = Vec::new();
    for v in views {
        let Some(roi) = v.roi else { continue };
        let t0 = Instant::now();
        let masks = segmenter.segment(&v.image, roi)?;
        times.push(t0.elapsed());
        std::hint::black_box(masks);
    }
    Ok(times)
}

#[cfg(test)]
mod tests {
    use super::*;
    use stitch_perception::segment::ColorSegmenter;

    #[test]
    fn a_crop_keeps_its_pixels_and_labels_in_place() {
        let (w, h) = (7u32, 5u32);
        let data: Vec<u8> = (0..w * h * 3).map(|i| i as u8).collect();
        let mut labels = vec![0u8; (w * h) as usize];
        labels[(2 * w + 3) as usize] = Label::Needle as u8;
        labels[(3 * w + 4) as usize] = Label::Needle as u8;
        let v = LabelledView::new(
            RgbImage {
                width: w,
                height: h,
                data,
            },
            labels,
        );
        assert_eq!(
            needle_box(&v.labels, w),
            Some(Rect {
                x0: 3,
                y0: 2,
                x1: 5,
                y1: 4
            })
        );
        let r = Rect {
            x0: 3,
            y0: 2,
            x1: 5,
            y1: 4,
        };
        let (img, lab) = v.crop(r);
        assert_eq!(lab, vec![1, 0, 0, 1]);
        assert_eq!(
            &img.data[0..3],
            &v.image.data[((2 * w + 3) * 3) as usize..][..3]
        );
    }

    #[test]
    fn iou_counts_the_overlap_of_a_mask_and_the_truth() {
        let mut o = Overlap::default();
        o.add(&[1, 1, 0, 0], &[1, 0, 1, 0], Label::Needle);
        assert_eq!((o.intersection, o.union), (1, 3));
        assert!((o.iou() - 1.0 / 3.0).abs() < 1e-12);
    }

    #[test]
    fn the_classical_segmenter_scores_well_on_its_own_renderer() {
        let views = {
            let world = stitch_sim::MockDvrk::new(
                &stitch_sim::SceneConfig::default(),
                stitch_sim::Streams::new(1),
                stitch_robot::SimClock::new(),
            )
            .expect("mock");
            let phantom = world.phantom_view();
            let r = StereoRenderer::new(CameraConfig::default(), phantom).expect("renderer");
            own_views(&r, &phantom, 6, 3)
        };
        let s = score(&ColorSegmenter::default(), &views).expect("classical");
        assert_eq!(s.views, 6);
        assert!(s.needle.iou() > 0.6, "needle IoU {}", s.needle.iou());
        assert!(s.thread.iou() > 0.3, "thread IoU {}", s.thread.iou());
    }
}
