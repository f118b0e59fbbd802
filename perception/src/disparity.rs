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

/// Which paths semi-global matching aggregates along.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum SgmPaths {
    /// → ← ↓ ↑: the needle pipeline's (half the time of eight; a thin wire's neighbourhood
    /// gains nothing measurable from the diagonals).
    #[default]
    Four,
    /// → ← ↓ ↘ ↙, in one pass over the rows holding only a few of them (no cost volume):
    /// the fastest over a whole image, in the least memory.
    Five,
    /// The four and the four diagonals (Hirschmüller's eight): smoother surfaces.
    Eight,
}

/// The left-right check: a pixel's disparity must agree, within `lr_max_diff`, with the
/// disparity the right view picks where it lands.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "kebab-case")]
pub enum LeftRight {
    /// The right pixel picks the least sum over every left pixel that could match it
    /// (Hirschmüller 2008), read at the nearest right pixel: the needle pipeline's rule.
    #[default]
    Nearest,
    /// The same right view, read at both right pixels the sub-pixel disparity lands
    /// between; either may agree.
    Between,
    /// The right pixel takes the disparity of the left pixel whose winning (unique) sum is
    /// least among those landing on it, and a right pixel no winner lands on refuses
    /// nothing; both right pixels the disparity lands between must disagree to refuse it
    /// (OpenCV's StereoSGBM's check): dense matching's default.
    Winners,
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
    /// How the left-right check reads the right view.
    pub left_right: LeftRight,
    /// Refuse to match more cost cells than this (matched pixels × disparities; each takes
    /// 3 bytes, 5 when matching on two threads; five paths hold no volume and ignore it).
    pub max_cells: usize,
    /// Match only pixels within this many of the needle mask (`None`: the whole region).
    pub around_mask_px: Option<u32>,
    /// The aggregation paths.
    pub paths: SgmPaths,
    /// After the checks, replace every disparity by the median of its 3×3 neighbourhood, a
    /// pixel with no answer (or past the region) counting as larger than any
    /// ([`median_3x3`]): dense matching's default, off in the needle pipeline (whose
    /// accuracy tables were measured without it).
    pub median: bool,
}

impl Default for SemiGlobalMatcher {
    fn default() -> Self {
        Self {
            p1: 3,
            p2: 20,
            uniqueness: 0.05,
            lr_max_diff: 1.0,
            left_right: LeftRight::Nearest,
            max_cells: 64 << 20,
            around_mask_px: Some(4),
            paths: SgmPaths::Four,
            median: false,
        }
    }
}

/// The 3×3 median of a `w × h` disparity map (`data`, row by row: `w · h` values), a pixel
/// with no answer (+inf) counting as larger than any answer, the map's edge repeated past
/// it: Hirschmüller's refinement (2008, §3.4), which removes isolated wrong answers and fills
/// an isolated refusal from the answers around it (a pixel with five or more of its nine
/// refused stays refused). On four photographed pairs it cut bad-2.0 on every one
/// (docs/perception.md).
///
/// Written here because no image crate filters `f32` maps with that rule (imageproc's median
/// takes 8-bit images): Paeth's 19-exchange network for the fifth of nine, over whole rows of
/// a padded copy, so that the compiler vectorises it.
#[multiversion::multiversion(targets("x86_64+avx2", "x86_64+sse4.2"))]
pub fn median_3x3(data: &[f32], w: usize, h: usize) -> Vec<f32> {
    if w == 0 || h == 0 {
        return data.to_vec();
    }
    let pw = w + 2;
    let mut padded = vec![f32::INFINITY; pw * (h + 2)];
    for (y, dst) in padded.chunks_exact_mut(pw).enumerate() {
        let src = &data[y.clamp(1, h) * w - w..][..w];
        dst[1..=w].copy_from_slice(src);
        dst[0] = src[0];
        dst[w + 1] = src[w - 1];
    }
    let mut out = vec![f32::INFINITY; w * h];
    let sort = |a: &mut f32, b: &mut f32| {
        let (lo, hi) = (a.min(*b), a.max(*b));
        *a = lo;
        *b = hi;
    };
    for (y, row) in out.chunks_exact_mut(w).enumerate() {
        let [r0, r1, r2] = [y, y + 1, y + 2].map(|r| &padded[r * pw..(r + 1) * pw]);
        for (x, o) in row.iter_mut().enumerate() {
            let [mut p0, mut p1, mut p2] = [r0[x], r0[x + 1], r0[x + 2]];
            let [mut p3, mut p4, mut p5] = [r1[x], r1[x + 1], r1[x + 2]];
            let [mut p6, mut p7, mut p8] = [r2[x], r2[x + 1], r2[x + 2]];
            sort(&mut p1, &mut p2);
            sort(&mut p4, &mut p5);
            sort(&mut p7, &mut p8);
            sort(&mut p0, &mut p1);
            sort(&mut p3, &mut p4);
            sort(&mut p6, &mut p7);
            sort(&mut p1, &mut p2);
            sort(&mut p4, &mut p5);
            sort(&mut p7, &mut p8);
            sort(&mut p0, &mut p3);
            sort(&mut p5, &mut p8);
            sort(&mut p4, &mut p7);
            sort(&mut p3, &mut p6);
            sort(&mut p1, &mut p4);
            sort(&mut p2, &mut p5);
            sort(&mut p4, &mut p7);
            sort(&mut p4, &mut p2);
            sort(&mut p6, &mut p4);
            sort(&mut p4, &mut p2);
            *o = p4;
        }
    }
    out
}

/// The compact index of pixel `i`, if it is matched.
#[inline(always)]
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

/// The value either side of a path's costs: a disparity outside the range never wins.
const PAD: u16 = u16::MAX / 4;

/// One step of a path (Hirschmüller 2008, eq. 13): `cur = C + min(prev, prev±1 + P1,
/// min(prev) + P2) − min(prev)`, and added to the pixel's sum. `prev` and `cur` hold `nd`
/// values between two [`PAD`]s, then their least value (`[nd + 2]`, kept by the step that
/// wrote them: no second pass to find it); written over slices of equal length so that it
/// vectorises.
#[inline(always)]
fn step(prev: &[u16], costs: &[u8], cur: &mut [u16], sum: &mut [u16], p1: u16, p2: u16) {
    let nd = costs.len();
    let (below, here, above) = (&prev[..nd], &prev[1..=nd], &prev[2..nd + 2]);
    let best = prev[nd + 2];
    let jump = best.saturating_add(p2);
    let out = &mut cur[1..=nd];
    let sum = &mut sum[..nd];
    let mut least = u16::MAX;
    for k in 0..nd {
        let m = here[k]
            .min(below[k].saturating_add(p1))
            .min(above[k].saturating_add(p1))
            .min(jump);
        let v = (m - best).saturating_add(u16::from(costs[k]));
        out[k] = v;
        sum[k] = sum[k].saturating_add(v);
        least = least.min(v);
    }
    cur[nd + 2] = least;
}

/// The first pixel of a path: its own costs.
#[inline(always)]
fn start(costs: &[u8], cur: &mut [u16], sum: &mut [u16]) {
    let nd = costs.len();
    let mut least = u16::MAX;
    for ((o, s), &c) in cur[1..=nd].iter_mut().zip(&mut sum[..nd]).zip(costs) {
        *o = u16::from(c);
        *s = s.saturating_add(*o);
        least = least.min(*o);
    }
    cur[nd + 2] = least;
}

/// Two views' censuses over the same rows: the left region's (`w` wide, from image column
/// `x0`) and the right strip's (`rw` wide, columns `rx0..rx1`).
struct Census<'a> {
    left: &'a [u32],
    right: &'a [u32],
    w: usize,
    rw: usize,
    x0: usize,
    rx0: usize,
    rx1: usize,
    dmin: usize,
}

/// Row `y`'s costs: `cost[c·nd + k]` = Hamming distance between the census of the pixel
/// `index_row` gives slot `c` and that of the right pixel `dmin + k` to its left (left as it
/// is, 24, where that pixel is outside the strip).
#[inline(always)]
fn hamming_row(c: &Census<'_>, y: usize, index_row: &[u32], nd: usize, cost: &mut [u8]) {
    let row = &c.right[y * c.rw..(y + 1) * c.rw];
    for x in 0..c.w {
        let Some(slot) = slot(index_row, x) else {
            continue;
        };
        let lx = c.x0 + x;
        // d = dmin + k is inside the strip for rx0 + d ≤ lx and lx − d < rx1.
        let Some(k1) = (lx - c.rx0).checked_sub(c.dmin).map(|k| k.min(nd - 1)) else {
            continue;
        };
        let k0 = (lx + 1).saturating_sub(c.rx1 + c.dmin);
        if k0 > k1 {
            continue;
        }
        let lv = c.left[y * c.w + x];
        // The right pixels for k0..=k1, nearest the left pixel first.
        let right = &row[lx - c.dmin - k1 - c.rx0..=lx - c.dmin - k0 - c.rx0];
        for (o, r) in cost[slot * nd + k0..=slot * nd + k1]
            .iter_mut()
            .zip(right.iter().rev())
        {
            *o = (lv ^ r).count_ones() as u8;
        }
    }
}

/// The whole cost volume (`index` maps each region pixel to its slot). Compiled also with
/// the processor's population count.
#[multiversion::multiversion(targets("x86_64+avx2+popcnt", "x86_64+sse4.2+popcnt"))]
fn hamming<'a>(c: &Census<'a>, index: &[u32], nd: usize, cost: &mut [u8]) {
    for (y, index_row) in index.chunks_exact(c.w).enumerate() {
        hamming_row(c, y, index_row, nd, cost);
    }
}

/// The paths that one visit of a row extends: the one along the row, and `verticals` from
/// the row visited before (0; 1, straight; or 3, with the diagonals from columns x − 1 and
/// x + 1), whose values are kept per column. A path restarts where the matched pixels stop.
struct Paths {
    stride: usize,
    line_prev: Vec<u16>,
    line_cur: Vec<u16>,
    prev_rows: Vec<Vec<u16>>,
    cur_rows: Vec<Vec<u16>>,
    prev_live: Vec<bool>,
    cur_live: Vec<bool>,
}

impl Paths {
    fn new(w: usize, nd: usize, verticals: usize) -> Self {
        // A path's values at a pixel: a pad, nd values, a pad, their least.
        let stride = nd + 3;
        Self {
            stride,
            line_prev: vec![PAD; stride],
            line_cur: vec![PAD; stride],
            prev_rows: vec![vec![PAD; w * stride]; verticals],
            cur_rows: vec![vec![PAD; w * stride]; verticals],
            prev_live: vec![false; w],
            cur_live: vec![false; w],
        }
    }

    /// One row, visited left to right (`forward`) or right to left; its costs and sums at
    /// the slots `index_row` gives.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn row(
        &mut self,
        cost: &[u8],
        index_row: &[u32],
        sum: &mut [u16],
        nd: usize,
        forward: bool,
        p1: u16,
        p2: u16,
    ) {
        let (w, stride) = (index_row.len(), self.stride);
        let mut live = false;
        for i in 0..w {
            let x = if forward { i } else { w - 1 - i };
            let Some(c) = slot(index_row, x) else {
                live = false;
                self.cur_live[x] = false;
                continue;
            };
            let costs = &cost[c * nd..(c + 1) * nd];
            let out = &mut sum[c * nd..(c + 1) * nd];
            if live {
                step(&self.line_prev, costs, &mut self.line_cur, out, p1, p2);
            } else {
                start(costs, &mut self.line_cur, out);
            }
            std::mem::swap(&mut self.line_prev, &mut self.line_cur);
            live = true;
            for (p, from) in [Some(x), x.checked_sub(1), Some(x + 1)]
                .into_iter()
                .take(self.prev_rows.len())
                .enumerate()
            {
                let cur = &mut self.cur_rows[p][x * stride..(x + 1) * stride];
                match from.filter(|&f| f < w && self.prev_live[f]) {
                    Some(f) => step(
                        &self.prev_rows[p][f * stride..(f + 1) * stride],
                        costs,
                        cur,
                        out,
                        p1,
                        p2,
                    ),
                    None => start(costs, cur, out),
                }
            }
            self.cur_live[x] = true;
        }
        if !self.prev_rows.is_empty() {
            std::mem::swap(&mut self.prev_rows, &mut self.cur_rows);
            std::mem::swap(&mut self.prev_live, &mut self.cur_live);
        }
    }
}

/// [`SemiGlobalMatcher::sweep`], compiled also for AVX2 and chosen when the processor has it
/// (the paths' minima over 16 disparities at once).
#[multiversion::multiversion(targets("x86_64+avx2+popcnt", "x86_64+sse4.2+popcnt"))]
fn sweep<'a>(v: &Volume<'a>, down: bool, diagonals: bool, p1: u16, p2: u16, sum: &mut [u16]) {
    let mut paths = Paths::new(v.w, v.nd, if diagonals { 3 } else { 1 });
    for j in 0..v.h {
        let y = if down { j } else { v.h - 1 - j };
        let index_row = &v.index[y * v.w..(y + 1) * v.w];
        paths.row(v.cost, index_row, sum, v.nd, down, p1, p2);
    }
}

/// What deciding a row needs besides its sums: per right pixel, counted from the right at
/// u = w − x + k for left pixel x at k (so that both run forwards), the least sum a left
/// pixel gives it (any sum, or only winners: [`LeftRight`]) and which left pixel x (the
/// first of a tie, the least k; k = u + x − w), as one key `sum << 16 | x`; the row's
/// winning disparities.
struct Decider {
    right: Vec<u32>,
    left_d: Vec<f32>,
}

impl Decider {
    fn new(w: usize, nd: usize) -> Self {
        Self {
            right: vec![u32::MAX; w + nd],
            left_d: vec![f32::INFINITY; w],
        }
    }

    /// Winner takes all, sub-pixel by a parabola, uniqueness; and the left-right check: the
    /// right pixel a left pixel lands on must itself pick a disparity within `lr_max_diff`,
    /// read as [`LeftRight`] says. One row, into `out`.
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn row(
        &mut self,
        m: &SemiGlobalMatcher,
        sum: &[u16],
        index_row: &[u32],
        x0: usize,
        dmin: usize,
        nd: usize,
        out: &mut [f32],
    ) {
        let w = index_row.len();
        self.right.fill(u32::MAX);
        for (x, d_out) in self.left_d.iter_mut().enumerate() {
            *d_out = f32::INFINITY;
            let Some(c) = slot(index_row, x) else {
                continue;
            };
            let s = &sum[c * nd..(c + 1) * nd];
            // One minimum over (sum << 16 | x): the least sum, and the first x of a tie.
            let x16 = x as u32;
            if m.left_right != LeftRight::Winners {
                for (key, &v) in self.right[w - x..w - x + nd].iter_mut().zip(s) {
                    *key = (*key).min((u32::from(v) << 16) | x16);
                }
            }
            // The least sum and its first k at once: one minimum over (sum << 16 | k).
            let key = s
                .iter()
                .enumerate()
                .map(|(k, &v)| (u32::from(v) << 16) | k as u32)
                .min()
                .unwrap_or(u32::MAX);
            let (bv, bk) = ((key >> 16) as u16, (key & 0xFFFF) as usize);
            let below = s[..bk.saturating_sub(1)].iter().copied().min();
            let above = s.get(bk + 2..).and_then(|a| a.iter().copied().min());
            let second = below.into_iter().chain(above).min().unwrap_or(u16::MAX);
            if f32::from(second) * (1.0 - m.uniqueness) < f32::from(bv) {
                continue;
            }
            if m.left_right == LeftRight::Winners {
                let key = &mut self.right[w - x + bk];
                *key = (*key).min((u32::from(bv) << 16) | x16);
            }
            let mut d = (dmin + bk) as f32;
            if bk > 0 && bk + 1 < nd {
                let (a, b, c) = (f32::from(s[bk - 1]), f32::from(bv), f32::from(s[bk + 1]));
                let den = a - 2.0 * b + c;
                if den > 0.0 {
                    d += 0.5 * (a - c) / den;
                }
            }
            *d_out = d;
        }
        let lowest = x0 as i64 - (dmin + nd - 1) as i64;
        for (x, (&d, o)) in self.left_d.iter().zip(out.iter_mut()).enumerate() {
            *o = f32::INFINITY;
            if !d.is_finite() {
                continue;
            }
            // The right pixel it lands on, or the two it lands between.
            let landing: &[f32] = if m.left_right == LeftRight::Nearest {
                &[d.round()]
            } else {
                &[d.floor(), d.ceil()]
            };
            // Per right pixel: no pick there, or the pick agrees.
            let check = |dr: &f32| -> (bool, bool) {
                let q = (x0 + x) as i64 - *dr as i64 - lowest;
                let Some(u) = usize::try_from(q)
                    .ok()
                    .and_then(|q| (w + nd - 1).checked_sub(q))
                else {
                    return (true, false);
                };
                let key = self.right[u];
                if key >> 16 == 0xFFFF {
                    return (true, false);
                }
                let k = u + (key & 0xFFFF) as usize - w;
                (false, ((dmin + k) as f32 - d).abs() <= m.lr_max_diff)
            };
            let agrees = if m.left_right == LeftRight::Winners {
                landing.iter().map(check).any(|(none, ok)| none || ok)
            } else {
                landing.iter().map(check).any(|(_, ok)| ok)
            };
            if agrees {
                *o = d;
            }
        }
    }
}

/// Every row of a region decided from the whole volume's sums.
#[allow(clippy::too_many_arguments)]
#[multiversion::multiversion(targets("x86_64+avx2+popcnt", "x86_64+sse4.2+popcnt"))]
fn decide(
    m: &SemiGlobalMatcher,
    sum: &[u16],
    index: &[u32],
    w: usize,
    x0: usize,
    dmin: usize,
    nd: usize,
    data: &mut [f32],
) {
    let mut decider = Decider::new(w, nd);
    for (index_row, out) in index.chunks_exact(w).zip(data.chunks_exact_mut(w)) {
        decider.row(m, sum, index_row, x0, dmin, nd, out);
    }
}

/// [`SgmPaths::Five`]: rows top to bottom, each row's costs, its five paths (→ ←, and ↓ ↘ ↙
/// from the row before) and its decision made before the next row, so that only a few rows
/// are ever held (OpenCV's StereoSGBM does the same in its default mode).
#[allow(clippy::too_many_arguments)]
#[multiversion::multiversion(targets("x86_64+avx2+popcnt", "x86_64+sse4.2+popcnt"))]
fn one_pass<'a>(
    m: &SemiGlobalMatcher,
    c: &Census<'a>,
    active: Option<&[bool]>,
    nd: usize,
    data: &mut [f32],
) {
    let w = c.w;
    let mut cost = vec![24u8; w * nd];
    let mut sum = vec![0u16; w * nd];
    let mut index_row = vec![0u32; w];
    let mut down = Paths::new(w, nd, 3);
    let mut back = Paths::new(w, nd, 0);
    let mut decider = Decider::new(w, nd);
    for (y, out) in data.chunks_exact_mut(w).enumerate() {
        for (x, i) in index_row.iter_mut().enumerate() {
            *i = if active.is_none_or(|a| a[y * w + x]) {
                x as u32
            } else {
                u32::MAX
            };
        }
        cost.fill(24);
        hamming_row(c, y, &index_row, nd, &mut cost);
        sum.fill(0);
        down.row(&cost, &index_row, &mut sum, nd, true, m.p1, m.p2);
        back.row(&cost, &index_row, &mut sum, nd, false, m.p1, m.p2);
        decider.row(m, &sum, &index_row, c.x0, c.dmin, nd, out);
    }
}

/// A matched region: the cost volume over its matched pixels (`index` maps a region pixel
/// to its row of `cost`), `nd` disparities each.
struct Volume<'a> {
    cost: &'a [u8],
    index: &'a [u32],
    w: usize,
    h: usize,
    nd: usize,
}

impl SemiGlobalMatcher {
    /// Dense disparity over `roi` of a rectified pair, no needle mask needed: every pixel of
    /// the region is matched over `min_disparity..=max_disparity` (left x − right x, pixels;
    /// the right image is searched wherever that range reaches). Invalid (occluded, not
    /// unique, failing the left-right check, or a window past the image's edge) = +inf.
    pub fn dense(
        &self,
        left: &RgbImage,
        right: &RgbImage,
        roi: Rect,
        min_disparity: u32,
        max_disparity: u32,
        parallel: bool,
    ) -> Result<DisparityMap, PerceptionError> {
        let config = |message: String| Err(PerceptionError::Config { message });
        if (left.width, left.height) != (right.width, right.height) {
            return config(format!(
                "the left image is {}×{} and the right {}×{}; a rectified pair has one size",
                left.width, left.height, right.width, right.height
            ));
        }
        if roi.is_empty() || roi.x1 > left.width || roi.y1 > left.height {
            return config(format!(
                "region {}..{} × {}..{} is not inside the {}×{} image",
                roi.x0, roi.x1, roi.y0, roi.y1, left.width, left.height
            ));
        }
        if min_disparity > max_disparity {
            return config(format!(
                "the disparity range {min_disparity}..{max_disparity} is empty"
            ));
        }
        if min_disparity >= roi.x1 {
            return config(format!(
                "every disparity from {min_disparity} puts the region's pixels (x < {}) outside the right image",
                roi.x1
            ));
        }
        self.matched(
            left,
            right,
            roi,
            min_disparity,
            max_disparity,
            None,
            parallel,
        )
    }

    /// The costs aggregated along the paths one sweep of the rows takes: top to bottom
    /// (`down`) → and ↓ (and ↘ ↙), or bottom to top ← and ↑ (and ↖ ↗), added into `sum`.
    /// Every path of a sweep comes from the row just swept or from the pixel just visited, so
    /// one sweep reads the cost volume and writes the sums once, row by row; a path restarts
    /// where the matched pixels stop.
    fn sweep(&self, v: &Volume<'_>, down: bool, sum: &mut [u16]) {
        sweep(v, down, self.paths != SgmPaths::Four, self.p1, self.p2, sum);
    }

    /// Semi-global matching over `lroi`, of the pixels `active` says (row-major over the
    /// region; `None`: all).
    #[allow(clippy::too_many_arguments)]
    fn matched(
        &self,
        left: &RgbImage,
        right: &RgbImage,
        lroi: Rect,
        min_disparity: u32,
        max_disparity: u32,
        active: Option<&[bool]>,
        parallel: bool,
    ) -> Result<DisparityMap, PerceptionError> {
        let (w, h) = (lroi.width() as usize, lroi.height() as usize);
        let dmin = min_disparity as usize;
        let nd = max_disparity.saturating_sub(min_disparity) as usize + 1;
        // Columns and disparities are counted in 16 bits where it speeds the matching.
        let most = usize::from(u16::MAX);
        if w > most || nd > most {
            return Err(PerceptionError::Config {
                message: format!(
                    "a region {w} pixels wide over {nd} disparities; semi-global matching takes at most {most} of each"
                ),
            });
        }
        // The right image's strip the region can match: x − d for every d.
        let rx0 = (lroi.x0 as usize).saturating_sub(dmin + nd - 1);
        let rx1 = (lroi.x1 as usize).saturating_sub(dmin).max(rx0 + 1);
        let rroi = Rect {
            x0: rx0 as u32,
            x1: rx1 as u32,
            ..lroi
        };
        let rw = rroi.width() as usize;
        let lc = census(&grey(left, lroi), w, h);
        let rc = census(&grey(right, rroi), rw, h);
        let census = Census {
            left: &lc,
            right: &rc,
            w,
            rw,
            x0: lroi.x0 as usize,
            rx0,
            rx1,
            dmin,
        };
        let mut data = vec![f32::INFINITY; w * h];
        if self.paths == SgmPaths::Five {
            // One pass indexes each row itself and holds no cost volume.
            one_pass(self, &census, active, nd, &mut data);
            return Ok(self.refined(lroi, data));
        }
        let mut index = vec![u32::MAX; w * h];
        let mut n = 0usize;
        for (i, slot) in index.iter_mut().enumerate() {
            if active.is_none_or(|a| a[i]) {
                *slot = n as u32;
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
        // Matching cost C(p, d): Hamming distance of the censuses (24 = no match: the
        // right pixel x − d is outside the strip).
        let mut cost = vec![24u8; n * nd];
        hamming(&census, &index, nd, &mut cost);
        let volume = Volume {
            cost: &cost,
            index: &index,
            w,
            h,
            nd,
        };
        // The two sweeps run on two threads if asked.
        let sum = if parallel {
            let (mut a, b) = rayon::join(
                || {
                    let mut s = vec![0u16; cost.len()];
                    self.sweep(&volume, true, &mut s);
                    s
                },
                || {
                    let mut s = vec![0u16; cost.len()];
                    self.sweep(&volume, false, &mut s);
                    s
                },
            );
            for (x, y) in a.iter_mut().zip(&b) {
                *x = x.saturating_add(*y);
            }
            a
        } else {
            let mut s = vec![0u16; cost.len()];
            self.sweep(&volume, true, &mut s);
            self.sweep(&volume, false, &mut s);
            s
        };
        drop(cost);
        decide(self, &sum, &index, w, lroi.x0 as usize, dmin, nd, &mut data);
        Ok(self.refined(lroi, data))
    }

    /// The decided map, median-filtered if [`SemiGlobalMatcher::median`] says so.
    fn refined(&self, roi: Rect, data: Vec<f32>) -> DisparityMap {
        let data = if self.median {
            median_3x3(&data, roi.width() as usize, roi.height() as usize)
        } else {
            data
        };
        DisparityMap { roi, data }
    }
}

impl StereoMatcher for SemiGlobalMatcher {
    fn name(&self) -> &'static str {
        "sgm"
    }

    fn disparity(&self, input: &StereoInput<'_>) -> Result<DisparityMap, PerceptionError> {
        let lroi = input.left_masks.roi;
        let (w, h) = (lroi.width() as usize, lroi.height() as usize);
        // Which pixels to match: all of the region, or only those within `around_mask_px`
        // of the needle mask (a thin wire's neighbourhood is a tenth of its box).
        let active = self
            .around_mask_px
            .map(|r| dilate(&input.left_masks.needle, w, h, r as usize));
        self.matched(
            input.left,
            input.right,
            lroi,
            input.min_disparity,
            input.max_disparity,
            active.as_deref(),
            input.parallel,
        )
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

    /// The matcher as first written (paths walked pixel by pixel, columns for the vertical
    /// ones, bounds checked per disparity): the oracle the row-swept, vectorised one must
    /// equal value for value.
    fn reference(sgm: &SemiGlobalMatcher, input: &StereoInput<'_>) -> DisparityMap {
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
        let active: Vec<bool> = match sgm.around_mask_px {
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
                                    m = m.min(prev[k - 1] + sgm.p1);
                                }
                                if k + 1 < nd {
                                    m = m.min(prev[k + 1] + sgm.p1);
                                }
                                m = m.min(best_prev + sgm.p2);
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
            if f32::from(second) * (1.0 - sgm.uniqueness) < f32::from(bv) {
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
                if best.0 != u16::MAX && ((dmin + best.1) as f32 - d).abs() <= sgm.lr_max_diff {
                    data[y * w + x] = d;
                }
            }
        }
        DisparityMap { roi: lroi, data }
    }

    /// A pseudo-random textured pair, the right view shifted by a disparity that varies
    /// with the row and the column (a slanted surface with a step), and a random mask.
    fn slanted_pair(w: u32, h: u32, seed: u64) -> (RgbImage, RgbImage, Vec<u8>) {
        let mut state = seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1;
        let mut next = move || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        let tex: Vec<u8> = (0..(w as usize + 200) * h as usize)
            .map(|_| (next() % 200) as u8 + 20)
            .collect();
        let tw = w as usize + 200;
        let mut l = RgbImage::new(w, h);
        let mut r = RgbImage::new(w, h);
        for y in 0..h as usize {
            for x in 0..w as usize {
                let d = 20 + (x / 7 + y / 5) % 13 + if x > w as usize / 2 { 9 } else { 0 };
                let i = (y * w as usize + x) * 3;
                let v = tex[y * tw + x + 100];
                l.data[i..i + 3].copy_from_slice(&[v, v / 2, v / 3]);
                let u = tex[y * tw + x + 100 + d];
                r.data[i..i + 3].copy_from_slice(&[u, u / 2, u / 3]);
            }
        }
        let mask = (0..(w * h) as usize)
            .map(|_| u8::from(next() % 5 == 0))
            .collect();
        (l, r, mask)
    }

    #[test]
    fn the_row_swept_matcher_equals_the_first_one_value_for_value() {
        let seg = ColorSegmenter::default();
        for seed in 1..=6u64 {
            let (l, r, needle) = slanted_pair(150, 60, seed);
            let roi = Rect {
                x0: 30 + seed as u32,
                y0: 3,
                x1: 140,
                y1: 57,
            };
            let mut lm = seg.segment(&l, roi).expect("masks");
            // A sparse random mask, so that paths stop and restart.
            lm.needle = (0..roi.width() * roi.height())
                .map(|i| needle[i as usize])
                .collect();
            let rm = seg.segment(&r, Rect::full(150, 60)).expect("masks");
            for around in [None, Some(1), Some(3)] {
                let m = SemiGlobalMatcher {
                    around_mask_px: around,
                    ..SemiGlobalMatcher::default()
                };
                for parallel in [false, true] {
                    let mut i = input(&l, &r, &lm, &rm, &seg);
                    i.min_disparity = 5 * seed as u32;
                    i.parallel = parallel;
                    let fast = m.disparity(&i).expect("map");
                    let slow = reference(&m, &i);
                    assert!(fast.valid_count() > 0, "seed {seed}: nothing matched");
                    let same = fast
                        .data
                        .iter()
                        .zip(&slow.data)
                        .all(|(a, b)| a.to_bits() == b.to_bits());
                    assert!(same, "seed {seed}, around {around:?}: the maps differ");
                }
            }
        }
    }

    /// The median as plainly as it can be said: sort the nine (past the map: the nearest
    /// pixel of its edge), take the fifth.
    fn median_by_sorting(data: &[f32], w: usize, h: usize) -> Vec<f32> {
        let mut out = Vec::with_capacity(data.len());
        for y in 0..h as i64 {
            for x in 0..w as i64 {
                let mut nine: Vec<f32> = (-1..=1)
                    .flat_map(|dy| (-1..=1).map(move |dx| (x + dx, y + dy)))
                    .map(|(xx, yy)| {
                        let (xx, yy) = (xx.clamp(0, w as i64 - 1), yy.clamp(0, h as i64 - 1));
                        data[yy as usize * w + xx as usize]
                    })
                    .collect();
                nine.sort_by(f32::total_cmp);
                out.push(nine[4]);
            }
        }
        out
    }

    #[test]
    fn the_median_network_equals_sorting_the_nine() {
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut next = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            state
        };
        for (w, h) in [
            (0, 0),
            (0, 3),
            (1, 1),
            (2, 1),
            (1, 3),
            (3, 3),
            (17, 9),
            (64, 31),
        ] {
            for refused_in_8 in 0..8u64 {
                let data: Vec<f32> = (0..w * h)
                    .map(|_| {
                        let r = next();
                        if r % 8 < refused_in_8 {
                            f32::INFINITY
                        } else {
                            // Few distinct values, so that ties are common.
                            ((r >> 8) % 40) as f32 * 0.25
                        }
                    })
                    .collect();
                assert_eq!(
                    median_3x3(&data, w, h),
                    median_by_sorting(&data, w, h),
                    "{w}×{h}"
                );
            }
        }
    }

    #[test]
    #[allow(clippy::float_cmp)] // a median picks one of the values: exactly equal
    fn the_median_fills_a_lone_refusal_and_removes_a_lone_outlier() {
        let (w, h) = (7, 5);
        let mut data = vec![10.0f32; w * h];
        data[2 * w + 2] = f32::INFINITY;
        data[2 * w + 4] = 40.0;
        // A column of refusals at the left edge stays refused (its pixels see six refused, the
        // edge repeated), and the column beside it keeps its answers (three).
        for y in 0..h {
            data[y * w] = f32::INFINITY;
        }
        let out = median_3x3(&data, w, h);
        assert_eq!(out[2 * w + 2], 10.0);
        assert_eq!(out[2 * w + 4], 10.0);
        assert!((0..h).all(|y| out[y * w] == f32::INFINITY));
        assert!(
            (0..h).all(|y| (1..w).all(|x| out[y * w + x] == 10.0)),
            "{out:?}"
        );
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
        let lm = seg.segment(&l, roi).expect("masks");
        let rm = seg.segment(&r, Rect::full(200, 80)).expect("masks");
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
    fn dense_matching_recovers_a_uniform_shift_along_any_paths_and_check() {
        let (l, r) = shifted_pair(200, 80, 37);
        for paths in [SgmPaths::Four, SgmPaths::Five, SgmPaths::Eight] {
            for left_right in [LeftRight::Nearest, LeftRight::Between, LeftRight::Winners] {
                let m = SemiGlobalMatcher {
                    around_mask_px: None,
                    paths,
                    left_right,
                    ..SemiGlobalMatcher::default()
                };
                for (parallel, median) in [(false, false), (true, false), (false, true)] {
                    let m = SemiGlobalMatcher { median, ..m };
                    let map = m
                        .dense(&l, &r, Rect::full(200, 80), 20, 60, parallel)
                        .expect("map");
                    // Scored where a match exists (x ≥ 37 + the census border) and away
                    // from the rows the census cannot see.
                    let (mut seen, mut right) = (0, 0);
                    for y in 2..78 {
                        for x in 42..198 {
                            seen += 1;
                            right +=
                                usize::from(map.at(x, y).is_some_and(|d| (d - 37.0).abs() < 0.5));
                        }
                    }
                    let what = format!(
                        "{paths:?} {left_right:?} parallel {parallel} median {median}: {right} of {seen}"
                    );
                    assert!(right * 100 >= seen * 95, "{what}");
                }
            }
        }
        // What it refuses, with the reason.
        let m = SemiGlobalMatcher::default();
        let e = m
            .dense(&l, &r, Rect::full(200, 80), 60, 20, false)
            .expect_err("empty");
        assert!(e.to_string().contains("is empty"), "{e}");
        let e = m.dense(
            &l,
            &r,
            Rect {
                x0: 0,
                y0: 0,
                x1: 300,
                y1: 80,
            },
            0,
            20,
            false,
        );
        assert!(e.expect_err("outside").to_string().contains("not inside"));
        let e = m.dense(&l, &r, Rect::full(200, 80), 200, 220, false);
        assert!(
            e.expect_err("past")
                .to_string()
                .contains("outside the right image")
        );
    }

    #[test]
    fn mask_rows_match_the_bar_at_its_shift() {
        let (l, r) = shifted_pair(200, 80, 37);
        let seg = ColorSegmenter::default();
        let lm = seg.segment(&l, Rect::full(200, 80)).expect("masks");
        let rm = seg.segment(&r, Rect::full(200, 80)).expect("masks");
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
        let m = seg.segment(&l, Rect::full(200, 80)).expect("masks");
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
