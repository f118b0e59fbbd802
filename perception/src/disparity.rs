//! Stage 2, disparity over a region of interest of a rectified pair: two matchers behind
//! [`StereoMatcher`].
//!
//! - [`SemiGlobalMatcher`]: census transform (5×5), semi-global aggregation along four
//!   paths (Hirschmüller 2008), winner-takes-all with a parabola for sub-pixel disparity, a
//!   uniqueness test and a left-right consistency check. A general matcher, for any texture.
//! - [`MaskRowMatcher`]: matches the needle mask's runs along each epipolar line (image row),
//!   with sub-pixel run edges from the segmenter's needleness, and keeps a pair only if each
//!   run is the other's best match (the left-right check). A 0.7 mm wire is a few pixels wide
//!   and shows view-dependent highlights; its silhouette does not move with them. The
//!   fastest (tens of microseconds), but rows along which the wire lies give no depth.
//!
//! The pipeline's default is semi-global matching restricted to a few pixels around the
//! needle mask, over the disparity range the mask rows' matches give: more accurate than the
//! mask rows (it sees the whole arc) at a few milliseconds. `stitch bench perception`
//! measures both.
//!
//! Both written by hand: no maintained Rust crate does stereo matching (checked: see
//! ../shared/PERCEPTION-NOTES.md).

use crate::PerceptionError;
use crate::segment::{Masks, Rect, Segmenter};
use serde::{Deserialize, Serialize};
use stitch_robot::RgbImage;

/// Disparities over a region of the left image: left x − right x of the same point, pixels;
/// `f32::INFINITY` where there is none.
#[derive(Clone, Debug, PartialEq)]
pub struct DisparityMap {
    /// The region, left-image pixels.
    pub roi: Rect,
    /// Row-major over `roi`.
    pub data: Vec<f32>,
}

impl DisparityMap {
    /// The disparity at left-image pixel `(x, y)`, if valid.
    pub fn at(&self, x: u32, y: u32) -> Option<f32> {
        let r = &self.roi;
        if x < r.x0 || x >= r.x1 || y < r.y0 || y >= r.y1 {
            return None;
        }
        let d = self.data[((y - r.y0) * r.width() + (x - r.x0)) as usize];
        d.is_finite().then_some(d)
    }
    /// Valid disparities.
    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|d| d.is_finite()).count()
    }
}

/// What a matcher gets.
#[derive(Clone, Copy, Debug)]
pub struct StereoInput<'a> {
    /// Left image.
    pub left: &'a RgbImage,
    /// Right image.
    pub right: &'a RgbImage,
    /// Needle masks of the left image (over the region to match).
    pub left_masks: &'a Masks,
    /// Needle masks of the right image (over the right image's search region).
    pub right_masks: &'a Masks,
    /// Least disparity to consider, pixels.
    pub min_disparity: u32,
    /// Greatest disparity to consider, pixels.
    pub max_disparity: u32,
    /// The segmenter, for sub-pixel edges.
    pub segmenter: &'a dyn Segmenter,
    /// Whether the matcher may use a second thread.
    pub parallel: bool,
}

/// Computes a disparity map over `input.left_masks.roi`.
pub trait StereoMatcher: Send + Sync + std::fmt::Debug {
    /// The map.
    fn disparity(&self, input: &StereoInput<'_>) -> Result<DisparityMap, PerceptionError>;
    /// Short name for tables.
    fn name(&self) -> &'static str;
}

/// Row-run matching of the needle masks.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MaskRowMatcher {
    /// Runs longer than this are the wire lying along the row, where a row gives no depth;
    /// skipped, pixels.
    pub max_run_px: f32,
    /// Least run length, pixels.
    pub min_run_px: f32,
    /// Most difference of the two runs' lengths, as a share of the longer.
    pub max_width_ratio: f32,
}

impl Default for MaskRowMatcher {
    fn default() -> Self {
        Self {
            max_run_px: 22.0,
            min_run_px: 1.5,
            max_width_ratio: 0.45,
        }
    }
}

/// A run of needle pixels on one row, with sub-pixel edges.
#[derive(Clone, Copy, Debug)]
struct Run {
    /// First pixel inside.
    first: u32,
    /// Last pixel inside.
    last: u32,
    /// Sub-pixel left edge, pixels (pixel centres at +0.5).
    start: f32,
    /// Sub-pixel right edge.
    end: f32,
}

impl Run {
    fn center(&self) -> f32 {
        (self.start + self.end) / 2.0
    }
    fn width(&self) -> f32 {
        self.end - self.start
    }
}

/// The needle runs of row `y` in `masks`, with sub-pixel edges where the needleness crosses
/// zero between the last pixel outside and the first inside.
fn runs(image: &RgbImage, masks: &Masks, y: u32, seg: &dyn Segmenter) -> Vec<Run> {
    let r = &masks.roi;
    let w = r.width() as usize;
    let row = &masks.needle[(y - r.y0) as usize * w..(y - r.y0 + 1) as usize * w];
    let px = |x: u32| -> f32 {
        if x >= image.width {
            return -1.0;
        }
        let i = ((y * image.width + x) * 3) as usize;
        seg.needleness([image.data[i], image.data[i + 1], image.data[i + 2]])
    };
    // The zero crossing between pixel centres a (outside) and b (inside), as an x.
    let edge = |outside: u32, inside: u32| -> f32 {
        let (fo, fi) = (px(outside), px(inside));
        let t = if fi - fo > 1e-6 {
            (fi / (fi - fo)).clamp(0.0, 1.0)
        } else {
            0.5
        };
        let (co, ci) = (outside as f32 + 0.5, inside as f32 + 0.5);
        ci + (co - ci) * t
    };
    let mut out = Vec::new();
    let mut x = 0usize;
    while x < w {
        if row[x] == 0 {
            x += 1;
            continue;
        }
        let s = x;
        while x < w && row[x] != 0 {
            x += 1;
        }
        let (first, last) = (r.x0 + s as u32, r.x0 + x as u32 - 1);
        let start = if first > 0 {
            edge(first - 1, first)
        } else {
            first as f32
        };
        let end = edge(last + 1, last);
        out.push(Run {
            first,
            last,
            start,
            end,
        });
    }
    out
}

impl StereoMatcher for MaskRowMatcher {
    fn name(&self) -> &'static str {
        "mask-row"
    }

    fn disparity(&self, input: &StereoInput<'_>) -> Result<DisparityMap, PerceptionError> {
        let lroi = input.left_masks.roi;
        let rroi = input.right_masks.roi;
        let mut data = vec![f32::INFINITY; (lroi.width() * lroi.height()) as usize];
        let (dmin, dmax) = (input.min_disparity as f32, input.max_disparity as f32);
        let usable = |r: &Run| {
            let wd = r.width();
            wd >= self.min_run_px && wd <= self.max_run_px
        };
        let similar = |a: &Run, b: &Run| {
            let (wa, wb) = (a.width(), b.width());
            (wa - wb).abs() <= self.max_width_ratio * wa.max(wb) + 0.75
        };
        // The typical offset between the two views' needles, to prefer among candidates.
        let prior = ((lroi.x0 + lroi.x1) as f32 - (rroi.x0 + rroi.x1) as f32) / 2.0;
        let cost = |l: &Run, r: &Run| {
            (l.width() - r.width()).abs() + 0.02 * ((l.center() - r.center()) - prior).abs()
        };
        for y in lroi.y0.max(rroi.y0)..lroi.y1.min(rroi.y1) {
            let ls: Vec<Run> = runs(input.left, input.left_masks, y, input.segmenter)
                .into_iter()
                .filter(usable)
                .collect();
            if ls.is_empty() {
                continue;
            }
            let rs: Vec<Run> = runs(input.right, input.right_masks, y, input.segmenter)
                .into_iter()
                .filter(usable)
                .collect();
            let ok = |l: &Run, r: &Run| {
                let d = l.center() - r.center();
                d >= dmin && d <= dmax && similar(l, r)
            };
            let best_right = |l: &Run| {
                rs.iter()
                    .enumerate()
                    .filter(|(_, r)| ok(l, r))
                    .min_by(|a, b| cost(l, a.1).total_cmp(&cost(l, b.1)))
                    .map(|(i, _)| i)
            };
            let best_left = |r: &Run| {
                ls.iter()
                    .enumerate()
                    .filter(|(_, l)| ok(l, r))
                    .min_by(|a, b| cost(a.1, r).total_cmp(&cost(b.1, r)))
                    .map(|(i, _)| i)
            };
            for (li, l) in ls.iter().enumerate() {
                let Some(ri) = best_right(l) else { continue };
                if best_left(&rs[ri]) != Some(li) {
                    continue; // fails the left-right check
                }
                let d = l.center() - rs[ri].center();
                let base = ((y - lroi.y0) * lroi.width()) as usize;
                for x in l.first.max(lroi.x0)..=l.last.min(lroi.x1 - 1) {
                    data[base + (x - lroi.x0) as usize] = d;
                }
            }
        }
        Ok(DisparityMap { roi: lroi, data })
    }
}

/// Census semi-global matching.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SemiGlobalMatcher {
    /// Penalty for a disparity change of one pixel between neighbours (census bits).
    pub p1: u16,
    /// Penalty for larger changes.
    pub p2: u16,
    /// The best cost must beat the second best (more than one pixel away) by this share.
    pub uniqueness: f32,
    /// Most left-right disagreement, pixels.
    pub lr_max_diff: f32,
    /// Refuse to match more cost cells than this (matched pixels × disparities).
    pub max_cells: usize,
    /// Match only pixels within this many of the needle mask (`None`: the whole region).
    pub around_mask_px: Option<u32>,
}

impl Default for SemiGlobalMatcher {
    fn default() -> Self {
        Self {
            p1: 3,
            p2: 20,
            uniqueness: 0.05,
            lr_max_diff: 1.0,
            max_cells: 64 << 20,
            around_mask_px: Some(4),
        }
    }
}

/// The compact index of pixel `i`, if it is matched.
fn slot(index: &[u32], i: usize) -> Option<usize> {
    let c = index[i];
    (c != u32::MAX).then_some(c as usize)
}

/// `mask` (row-major `w × h`, non-zero = set) grown by `r` pixels (a square).
fn dilate(mask: &[u8], w: usize, h: usize, r: usize) -> Vec<bool> {
    let mut rows = vec![false; w * h];
    for y in 0..h {
        let row = &mask[y * w..(y + 1) * w];
        let mut last: Option<usize> = None;
        // Distance to the nearest set pixel along the row, both ways.
        for x in 0..w {
            if row[x] != 0 {
                last = Some(x);
            }
            if last.is_some_and(|l| x - l <= r) {
                rows[y * w + x] = true;
            }
        }
        last = None;
        for x in (0..w).rev() {
            if row[x] != 0 {
                last = Some(x);
            }
            if last.is_some_and(|l| l - x <= r) {
                rows[y * w + x] = true;
            }
        }
    }
    let mut out = vec![false; w * h];
    for x in 0..w {
        let mut last: Option<usize> = None;
        for y in 0..h {
            if rows[y * w + x] {
                last = Some(y);
            }
            if last.is_some_and(|l| y - l <= r) {
                out[y * w + x] = true;
            }
        }
        last = None;
        for y in (0..h).rev() {
            if rows[y * w + x] {
                last = Some(y);
            }
            if last.is_some_and(|l| l - y <= r) {
                out[y * w + x] = true;
            }
        }
    }
    out
}

/// 5×5 census of a grey image (24 bits: each neighbour darker than the centre).
fn census(grey: &[u8], w: usize, h: usize) -> Vec<u32> {
    let mut out = vec![0u32; w * h];
    for y in 2..h.saturating_sub(2) {
        for x in 2..w.saturating_sub(2) {
            let c = grey[y * w + x];
            let mut bits = 0u32;
            for dy in 0..5 {
                for dx in 0..5 {
                    if dy == 2 && dx == 2 {
                        continue;
                    }
                    bits = (bits << 1) | u32::from(grey[(y + dy - 2) * w + x + dx - 2] < c);
                }
            }
            out[y * w + x] = bits;
        }
    }
    out
}

/// Rec. 601 luma of a region.
fn grey(image: &RgbImage, r: Rect) -> Vec<u8> {
    let w = image.width as usize;
    let mut out = Vec::with_capacity((r.width() * r.height()) as usize);
    for y in r.y0 as usize..r.y1 as usize {
        for x in r.x0 as usize..r.x1 as usize {
            let i = (y * w + x) * 3;
            let v = (77 * u32::from(image.data[i])
                + 150 * u32::from(image.data[i + 1])
                + 29 * u32::from(image.data[i + 2]))
                >> 8;
            out.push(v as u8);
        }
    }
    out
}

impl StereoMatcher for SemiGlobalMatcher {
    fn name(&self) -> &'static str {
        "sgm"
    }

    fn disparity(&self, input: &StereoInput<'_>) -> Result<DisparityMap, PerceptionError> {
        let lroi = input.left_masks.roi;
        let (w, h) = (lroi.width() as usize, lroi.height() as usize);
        let dmin = input.min_disparity as usize;
        let nd = input.max_disparity.saturating_sub(input.min_disparity) as usize + 1;
        // The right image's strip the region can match: x − d for every d.
        let rx0 = (lroi.x0 as usize).saturating_sub(dmin + nd - 1);
        let rx1 = (lroi.x1 as usize).saturating_sub(dmin).max(rx0 + 1);
        let rroi = Rect {
            x0: rx0 as u32,
            x1: rx1 as u32,
            ..lroi
        };
        let rw = rroi.width() as usize;
        let lc = census(&grey(input.left, lroi), w, h);
        let rc = census(&grey(input.right, rroi), rw, h);
        // Which pixels to match: all of the region, or only those within `around_mask_px`
        // of the needle mask (a thin wire's neighbourhood is a tenth of its box).
        let active: Vec<bool> = match self.around_mask_px {
            None => vec![true; w * h],
            Some(r) => dilate(&input.left_masks.needle, w, h, r as usize),
        };
        let mut index = vec![u32::MAX; w * h];
        let mut n = 0usize;
        for (i, &a) in active.iter().enumerate() {
            if a {
                index[i] = n as u32;
                n += 1;
            }
        }
        // The cost volume holds the matched pixels only.
        if n * nd > self.max_cells {
            return Err(PerceptionError::Config {
                message: format!(
                    "semi-global matching of {n} pixels (of a {w}×{h} region) over {nd} disparities needs {} cost cells, more than the limit {}; give a smaller region or disparity range",
                    n * nd,
                    self.max_cells
                ),
            });
        }
        // Matching cost C(p, d): Hamming distance of the censuses (24 = no match).
        let mut cost = vec![24u8; n * nd];
        for y in 0..h {
            for x in 0..w {
                let Some(c) = slot(&index, y * w + x) else {
                    continue;
                };
                let lx = lroi.x0 as usize + x;
                for k in 0..nd {
                    let d = dmin + k;
                    if lx < d + rx0 || lx - d >= rx1 {
                        continue;
                    }
                    let r = rc[y * rw + (lx - d - rx0)];
                    cost[c * nd + k] = (lc[y * w + x] ^ r).count_ones() as u8;
                }
            }
        }
        // Aggregate along four paths: → ← ↓ ↑; a path restarts where the active pixels
        // stop. The horizontal and the vertical pair run on two threads if asked.
        let along = |paths: &[(i64, i64)]| {
            let mut sum = vec![0u16; n * nd];
            let mut prev = vec![0u16; nd];
            let mut cur = vec![0u16; nd];
            for &(dx, dy) in paths {
                let starts: Vec<(i64, i64)> = if dx != 0 {
                    (0..h as i64)
                        .map(|y| (if dx > 0 { 0 } else { w as i64 - 1 }, y))
                        .collect()
                } else {
                    (0..w as i64)
                        .map(|x| (x, if dy > 0 { 0 } else { h as i64 - 1 }))
                        .collect()
                };
                for (sx, sy) in starts {
                    let (mut x, mut y) = (sx, sy);
                    let mut first = true;
                    while x >= 0 && y >= 0 && x < w as i64 && y < h as i64 {
                        let here = slot(&index, y as usize * w + x as usize);
                        x += dx;
                        y += dy;
                        let Some(c) = here else {
                            first = true;
                            continue;
                        };
                        let c = c * nd;
                        let costs = &cost[c..c + nd];
                        if first {
                            for k in 0..nd {
                                cur[k] = u16::from(costs[k]);
                            }
                            first = false;
                        } else {
                            let best_prev = prev.iter().copied().min().unwrap_or(0);
                            for k in 0..nd {
                                let mut m = prev[k];
                                if k > 0 {
                                    m = m.min(prev[k - 1] + self.p1);
                                }
                                if k + 1 < nd {
                                    m = m.min(prev[k + 1] + self.p1);
                                }
                                m = m.min(best_prev + self.p2);
                                cur[k] = u16::from(costs[k]) + m - best_prev;
                            }
                        }
                        for k in 0..nd {
                            sum[c + k] = sum[c + k].saturating_add(cur[k]);
                        }
                        std::mem::swap(&mut prev, &mut cur);
                    }
                }
            }
            sum
        };
        let sum = if input.parallel {
            let (mut a, b) =
                rayon::join(|| along(&[(1, 0), (-1, 0)]), || along(&[(0, 1), (0, -1)]));
            for (x, y) in a.iter_mut().zip(&b) {
                *x = x.saturating_add(*y);
            }
            a
        } else {
            along(&[(1, 0), (-1, 0), (0, 1), (0, -1)])
        };
        // Winner takes all, sub-pixel by a parabola, uniqueness; then the right view's
        // disparities from the same sums for the left-right check.
        let mut left_d = vec![f32::INFINITY; w * h];
        for (p, out) in left_d.iter_mut().enumerate() {
            let Some(c) = slot(&index, p) else { continue };
            let s = &sum[c * nd..(c + 1) * nd];
            let (mut bk, mut bv) = (0usize, u16::MAX);
            for (k, &v) in s.iter().enumerate() {
                if v < bv {
                    bv = v;
                    bk = k;
                }
            }
            let second = s
                .iter()
                .enumerate()
                .filter(|(k, _)| k.abs_diff(bk) > 1)
                .map(|(_, &v)| v)
                .min()
                .unwrap_or(u16::MAX);
            if f32::from(second) * (1.0 - self.uniqueness) < f32::from(bv) {
                continue;
            }
            let mut d = (dmin + bk) as f32;
            if bk > 0 && bk + 1 < nd {
                let (a, b, c) = (f32::from(s[bk - 1]), f32::from(bv), f32::from(s[bk + 1]));
                let den = a - 2.0 * b + c;
                if den > 0.0 {
                    d += 0.5 * (a - c) / den;
                }
            }
            *out = d;
        }
        let mut data = vec![f32::INFINITY; w * h];
        for y in 0..h {
            for x in 0..w {
                let d = left_d[y * w + x];
                if !d.is_finite() {
                    continue;
                }
                // The right pixel this matches, and its own best disparity over the left
                // pixels that could match it.
                let xr = (lroi.x0 as usize + x) as i64 - d.round() as i64;
                let mut best = (u16::MAX, 0usize);
                for k in 0..nd {
                    let xl = xr + (dmin + k) as i64 - lroi.x0 as i64;
                    if xl < 0 || xl >= w as i64 {
                        continue;
                    }
                    let Some(c) = slot(&index, y * w + xl as usize) else {
                        continue;
                    };
                    let v = sum[c * nd + k];
                    if v < best.0 {
                        best = (v, k);
                    }
                }
                if best.0 != u16::MAX && ((dmin + best.1) as f32 - d).abs() <= self.lr_max_diff {
                    data[y * w + x] = d;
                }
            }
        }
        Ok(DisparityMap { roi: lroi, data })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::segment::ColorSegmenter;

    /// A textured pair whose right view is the left shifted by `d` pixels, with a grey bar.
    fn shifted_pair(w: u32, h: u32, d: u32) -> (RgbImage, RgbImage) {
        let tex = |x: i64, y: i64| -> [u8; 3] {
            let v = ((x * 7919 + y * 104_729) ^ (x * y * 31)).rem_euclid(97) as u8;
            let bar = (100..108).contains(&x) && (20..60).contains(&y);
            if bar {
                [170, 170, 172]
            } else {
                [150 + v, 60 + v / 2, 60 + v / 3]
            }
        };
        let mut l = RgbImage::new(w, h);
        let mut r = RgbImage::new(w, h);
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let i = ((y * w as i64 + x) * 3) as usize;
                l.data[i..i + 3].copy_from_slice(&tex(x, y));
                r.data[i..i + 3].copy_from_slice(&tex(x + i64::from(d), y));
            }
        }
        (l, r)
    }

    fn input<'a>(
        l: &'a RgbImage,
        r: &'a RgbImage,
        lm: &'a Masks,
        rm: &'a Masks,
        seg: &'a ColorSegmenter,
    ) -> StereoInput<'a> {
        StereoInput {
            left: l,
            right: r,
            left_masks: lm,
            right_masks: rm,
            min_disparity: 20,
            max_disparity: 60,
            segmenter: seg,
            parallel: false,
        }
    }

    #[test]
    fn sgm_recovers_a_uniform_shift() {
        let (l, r) = shifted_pair(200, 80, 37);
        let seg = ColorSegmenter::default();
        let roi = Rect {
            x0: 70,
            y0: 5,
            x1: 190,
            y1: 75,
        };
        let lm = seg.segment(&l, roi);
        let rm = seg.segment(&r, Rect::full(200, 80));
        let whole = SemiGlobalMatcher {
            around_mask_px: None,
            ..SemiGlobalMatcher::default()
        };
        let map = whole
            .disparity(&input(&l, &r, &lm, &rm, &seg))
            .expect("map");
        // Around the mask only: the bar and a few pixels each side, nothing far from it.
        let near = SemiGlobalMatcher::default()
            .disparity(&input(&l, &r, &lm, &rm, &seg))
            .expect("map");
        assert!((near.at(104, 40).expect("on the bar") - 37.0).abs() < 0.5);
        assert_eq!(near.at(80, 40), None);
        let valid: Vec<f32> = map.data.iter().copied().filter(|d| d.is_finite()).collect();
        assert!(valid.len() > map.data.len() / 2, "{} valid", valid.len());
        let good = valid.iter().filter(|d| (*d - 37.0).abs() < 0.5).count();
        assert!(good * 100 > valid.len() * 95, "{good} of {}", valid.len());
    }

    #[test]
    fn mask_rows_match_the_bar_at_its_shift() {
        let (l, r) = shifted_pair(200, 80, 37);
        let seg = ColorSegmenter::default();
        let lm = seg.segment(&l, Rect::full(200, 80));
        let rm = seg.segment(&r, Rect::full(200, 80));
        let map = MaskRowMatcher::default()
            .disparity(&input(&l, &r, &lm, &rm, &seg))
            .expect("map");
        assert_eq!(map.valid_count(), 8 * 40);
        assert!((map.at(103, 30).expect("valid") - 37.0).abs() < 0.05);
        assert_eq!(map.at(50, 30), None);
    }

    #[test]
    fn sgm_refuses_a_volume_too_large() {
        let (l, r) = shifted_pair(200, 80, 37);
        let seg = ColorSegmenter::default();
        let m = seg.segment(&l, Rect::full(200, 80));
        let sgm = SemiGlobalMatcher {
            max_cells: 1000,
            ..SemiGlobalMatcher::default()
        };
        let e = sgm
            .disparity(&input(&l, &r, &m, &m, &seg))
            .expect_err("too big");
        assert!(e.to_string().contains("cost cells"), "{e}");
    }
}
