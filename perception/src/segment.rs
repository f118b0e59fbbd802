//! Stage 1, segmentation: needle and thread masks.
//!
//! The classical default ([`ColorSegmenter`]) classifies pixels by colour: the needle is
//! bright and unsaturated (polished steel, white highlights), the thread strongly violet
//! (blue well above red and green), tissue and drape saturated red or green, instruments
//! dark. A learned segmenter plugs in behind [`Segmenter`].
//!
//! Finding the needle in a full frame costs little: a coarse grid (every `stride` pixels)
//! finds candidate pixels, the largest connected group and its neighbours give the region
//! of interest, and only that region is classified at full resolution.

use crate::PerceptionError;
use serde::{Deserialize, Serialize};
use stitch_robot::RgbImage;

/// A pixel rectangle, `[x0, x1) × [y0, y1)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Rect {
    /// Left edge (inclusive).
    pub x0: u32,
    /// Top edge (inclusive).
    pub y0: u32,
    /// Right edge (exclusive).
    pub x1: u32,
    /// Bottom edge (exclusive).
    pub y1: u32,
}

impl Rect {
    /// Width, pixels.
    pub fn width(&self) -> u32 {
        self.x1.saturating_sub(self.x0)
    }
    /// Height, pixels.
    pub fn height(&self) -> u32 {
        self.y1.saturating_sub(self.y0)
    }
    /// Whether it holds no pixel.
    pub fn is_empty(&self) -> bool {
        self.width() == 0 || self.height() == 0
    }
    /// Grown by `m` pixels on every side, clipped to a `w × h` image.
    pub fn grown(&self, m: u32, w: u32, h: u32) -> Rect {
        Rect {
            x0: self.x0.saturating_sub(m),
            y0: self.y0.saturating_sub(m),
            x1: (self.x1 + m).min(w),
            y1: (self.y1 + m).min(h),
        }
    }
    /// The part inside a `w × h` image.
    pub fn clipped(&self, w: u32, h: u32) -> Rect {
        Rect {
            x0: self.x0.min(w),
            y0: self.y0.min(h),
            x1: self.x1.min(w),
            y1: self.y1.min(h),
        }
    }
    /// The whole of a `w × h` image.
    pub fn full(w: u32, h: u32) -> Rect {
        Rect {
            x0: 0,
            y0: 0,
            x1: w,
            y1: h,
        }
    }
}

/// Needle and thread masks over a region of one image.
#[derive(Clone, Debug, PartialEq)]
pub struct Masks {
    /// The region they cover, image pixels.
    pub roi: Rect,
    /// 1 where the needle is, row-major over `roi`.
    pub needle: Vec<u8>,
    /// 1 where the thread is, row-major over `roi`.
    pub thread: Vec<u8>,
}

impl Masks {
    /// Whether image pixel `(x, y)` is needle (false outside the region).
    pub fn is_needle(&self, x: u32, y: u32) -> bool {
        self.at(&self.needle, x, y)
    }
    /// Whether image pixel `(x, y)` is thread (false outside the region).
    pub fn is_thread(&self, x: u32, y: u32) -> bool {
        self.at(&self.thread, x, y)
    }
    fn at(&self, m: &[u8], x: u32, y: u32) -> bool {
        let r = &self.roi;
        x >= r.x0
            && x < r.x1
            && y >= r.y0
            && y < r.y1
            && m[((y - r.y0) * r.width() + (x - r.x0)) as usize] != 0
    }
    /// Needle pixels.
    pub fn needle_count(&self) -> usize {
        self.needle.iter().filter(|&&v| v != 0).count()
    }
}

/// Makes needle and thread masks from one image.
pub trait Segmenter: Send + Sync + std::fmt::Debug {
    /// Where the needle appears in `image`, searched over `within`: a region of interest
    /// around it (including margin for the thread near it), or `None` if no needle is seen.
    fn locate(&self, image: &RgbImage, within: Rect) -> Option<Rect>;
    /// The places the needle may be in `image`, searched over `within`, likeliest first
    /// (`locate`'s answer first): what a pipeline tries in turn when the first holds no
    /// needle it can fit (a patch of wet glare ranked above it). A segmenter that ranks only
    /// one place gives that one.
    fn candidates(&self, image: &RgbImage, within: Rect) -> Vec<Rect> {
        self.locate(image, within).into_iter().collect()
    }
    /// Needle and thread masks over `roi`; an error only when the segmenter itself fails
    /// (a learned model that cannot run), never for an image without a needle.
    fn segment(&self, image: &RgbImage, roi: Rect) -> Result<Masks, PerceptionError>;
    /// How needle-like a pixel is: positive inside the needle mask, negative outside, with
    /// a zero crossing at its edge (for sub-pixel edges). Needs no neighbours.
    fn needleness(&self, rgb: [u8; 3]) -> f32;
    /// The thread mask alone over `roi` (1 where the thread is, row-major): what the thread
    /// tracer asks for; a segmenter with a cheaper way than `segment` overrides it.
    fn thread_mask(&self, image: &RgbImage, roi: Rect) -> Result<Vec<u8>, PerceptionError> {
        self.segment(image, roi).map(|m| m.thread)
    }
    /// `Some(b)` if `thread_mask` is local on a grid of `b`-pixel blocks laid from the
    /// region's corner: a pixel's value depends only on its own block and the eight round
    /// it, so a region cut on that grid, with a block to spare round the pixels asked
    /// about, gives them the values the larger region gives. The tracer then computes the
    /// right view's mask only where it reads it. `None` (the default: a learned model sees
    /// the whole region): the mask over the whole band.
    fn thread_mask_block_px(&self) -> Option<u32> {
        None
    }
}

/// A segmenter several pipelines share (a model loaded once), equal only to itself.
#[derive(Clone, Debug)]
pub struct SharedSegmenter(pub std::sync::Arc<dyn Segmenter>);

impl PartialEq for SharedSegmenter {
    fn eq(&self, other: &Self) -> bool {
        std::sync::Arc::ptr_eq(&self.0, &other.0)
    }
}

impl Segmenter for SharedSegmenter {
    fn locate(&self, image: &RgbImage, within: Rect) -> Option<Rect> {
        self.0.locate(image, within)
    }
    fn candidates(&self, image: &RgbImage, within: Rect) -> Vec<Rect> {
        self.0.candidates(image, within)
    }
    fn segment(&self, image: &RgbImage, roi: Rect) -> Result<Masks, PerceptionError> {
        self.0.segment(image, roi)
    }
    fn needleness(&self, rgb: [u8; 3]) -> f32 {
        self.0.needleness(rgb)
    }
    fn thread_mask(&self, image: &RgbImage, roi: Rect) -> Result<Vec<u8>, PerceptionError> {
        self.0.thread_mask(image, roi)
    }
    fn thread_mask_block_px(&self) -> Option<u32> {
        self.0.thread_mask_block_px()
    }
}

/// How much more violet than its surroundings a pixel must be for the tracer's mask, levels
/// (see [`ColorSegmenter`]'s `thread_mask`).
const THREAD_CONTRAST: i32 = 30;

/// The side of the blocks whose sums give [`ColorSegmenter`]'s `thread_mask` a pixel's
/// surroundings, pixels.
const THREAD_BLOCK_PX: u32 = 4;

/// The classical colour segmenter's thresholds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ColorSegmenter {
    /// Least brightness (largest channel) of a needle pixel, 0–255.
    pub needle_min_value: u8,
    /// Most saturation ((max − min) / max) of a needle pixel.
    pub needle_max_saturation: f32,
    /// Least amount blue exceeds red by in a thread pixel, levels.
    pub thread_blue_over_red: u8,
    /// Least amount blue exceeds green by in a thread pixel, levels.
    pub thread_blue_over_green: u8,
    /// Grid step of the full-frame search, pixels (at most the needle's width in pixels).
    pub stride: u32,
    /// Least coarse-grid hits for a needle.
    pub min_hits: usize,
    /// Margin added around the needle's region, pixels.
    pub margin_px: u32,
    /// Groups of hits at most this far from the largest join it (parts of one needle split
    /// by an occluder), pixels.
    pub join_px: u32,
    /// Grid cells this near each other belong to one group (1: touching, 8-neighbours;
    /// 2: one empty cell bridged).
    pub bridge_cells: u32,
    /// Most cells a group may fill of its extent squared and still be taken for the
    /// needle: a half circle of wire d and radius R fills about 1.6·d/(2R) whatever its
    /// distance (0.05 for the default needle); glare on wet tissue makes fuller blobs.
    pub max_fill: f32,
    /// Least spread across a group's main axis over the spread along it for the needle
    /// (standard deviations): a half circle gives 0.44 face on and about 0.13 within 18° of
    /// edge on; a highlight along a straight shaft, a few hundredths.
    pub min_bend: f32,
    /// Needle-mask components smaller than this are specks (glints, noise) and dropped,
    /// pixels.
    pub min_component_px: u32,
}

impl Default for ColorSegmenter {
    /// Thresholds set on rendered frames (see docs/perception.md); a lab re-tunes them on its
    /// own images with `stitch perceive needle`.
    fn default() -> Self {
        Self {
            needle_min_value: 72,
            needle_max_saturation: 0.22,
            thread_blue_over_red: 12,
            thread_blue_over_green: 45,
            stride: 3,
            min_hits: 6,
            margin_px: 24,
            join_px: 90,
            bridge_cells: 2,
            max_fill: 0.10,
            min_bend: 0.09,
            min_component_px: 10,
        }
    }
}

impl ColorSegmenter {
    #[inline]
    fn is_needle(&self, p: &[u8]) -> bool {
        let max = p[0].max(p[1]).max(p[2]);
        let min = p[0].min(p[1]).min(p[2]);
        max >= self.needle_min_value
            && f32::from(max - min) < self.needle_max_saturation * f32::from(max)
    }
    #[inline]
    fn is_thread(&self, p: &[u8]) -> bool {
        let (r, g, b) = (i16::from(p[0]), i16::from(p[1]), i16::from(p[2]));
        b >= r + i16::from(self.thread_blue_over_red)
            && b >= g + i16::from(self.thread_blue_over_green)
    }
}

impl ColorSegmenter {
    /// Up to `max` places the needle may be, likeliest first: around each group of hits
    /// that is thin and bent, largest first (or the largest group if none is), with the
    /// pieces that join it.
    fn ranked(&self, image: &RgbImage, within: Rect, max: usize) -> Vec<Rect> {
        let within = within.clipped(image.width, image.height);
        let s = self.stride.max(1);
        let w = image.width as usize;
        let gw = within.width().div_ceil(s) as usize;
        let gh = within.height().div_ceil(s) as usize;
        if gw == 0 || gh == 0 {
            return Vec::new();
        }
        let mut grid = vec![0u32; gw * gh]; // 0: nothing, u32::MAX: hit, else a label
        let mut hits = 0usize;
        for gy in 0..gh {
            let y = within.y0 as usize + gy * s as usize;
            let row = &image.data[y * w * 3..(y + 1) * w * 3];
            for gx in 0..gw {
                let x = within.x0 as usize + gx * s as usize;
                if self.is_needle(&row[x * 3..x * 3 + 3]) {
                    grid[gy * gw + gx] = u32::MAX;
                    hits += 1;
                }
            }
        }
        if hits < self.min_hits {
            return Vec::new();
        }
        let groups = label_groups(&mut grid, gw, gh, self.bridge_cells as i64);
        // The needle is the largest group that is thin for its extent and bent: a half
        // circle of wire covers a small share of its extent squared, whatever its distance,
        // while the glare on wet tissue makes blobs, and the highlight along an instrument's
        // shaft is straight. Groups too small to have a shape count as both.
        let thin = |g: &Group| g.extent() < MIN_SHAPED_CELLS || g.fill() <= self.max_fill;
        let bent = |g: &Group| g.extent() < MIN_SHAPED_CELLS || g.bend() >= self.min_bend;
        let mut order: Vec<&Group> = groups
            .iter()
            .filter(|g| g.count >= self.min_hits && thin(g) && bent(g))
            .collect();
        order.sort_by_key(|g| std::cmp::Reverse(g.count));
        if order.is_empty() {
            order.extend(groups.iter().max_by_key(|g| g.count));
        }
        let mut out: Vec<Rect> = Vec::new();
        for best in order.into_iter().take(max) {
            if best.count < self.min_hits {
                break;
            }
            let rect = self.around(best, &groups, &thin, &bent, within, image);
            let inside =
                |o: &Rect| rect.x0 >= o.x0 && rect.y0 >= o.y0 && rect.x1 <= o.x1 && rect.y1 <= o.y1;
            if !out.iter().any(inside) {
                out.push(rect);
            }
        }
        out
    }

    /// The region around the group `best` and the groups that join it, grown by the margin.
    fn around(
        &self,
        best: &Group,
        groups: &[Group],
        thin: &dyn Fn(&Group) -> bool,
        bent: &dyn Fn(&Group) -> bool,
        within: Rect,
        image: &RgbImage,
    ) -> Rect {
        let s = self.stride.max(1);
        // Pieces of the same needle split by an occluder (the thread, a jaw) join it: groups
        // that are thin (and bent, or half its size or less), within `join_px` or half the
        // needle's extent; and small groups (a short piece of wire has no shape to judge).
        let far = ((self.join_px / s) as usize).max(best.extent() / 2);
        let near = 2 * self.bridge_cells.max(1) as usize;
        let gap = |g: &Group, b: &[usize; 4]| {
            let gap_x = g.bbox[0]
                .saturating_sub(b[2])
                .max(b[0].saturating_sub(g.bbox[2]));
            let gap_y = g.bbox[1]
                .saturating_sub(b[3])
                .max(b[1].saturating_sub(g.bbox[3]));
            gap_x.max(gap_y)
        };
        // A short piece of arc is nearly straight: thin groups half the needle's size or
        // less join whether bent or not (a shaft's highlight is longer than that).
        let shaped = |g: &Group| {
            thin(g) && (bent(g) || g.count * 2 <= best.count) && g.extent() >= MIN_SHAPED_CELLS
        };
        // Small groups within reach: a few are the needle's pieces past a jaw or the
        // thread; many are a field of glare specks, of which only those touching it join.
        let small = |g: &Group| {
            g.count >= 2
                && !shaped(g)
                && g.count * 2 <= best.count
                && !std::ptr::eq(g, best)
                && gap(g, &best.bbox) <= far
        };
        // A group touching it, bent and nearly as thin as wire: a piece of the needle
        // thickened by what lies on it (a jaw's steel fingers closed on the wire), fuller
        // than wire alone, not a blob of glare.
        let thickened = |g: &Group| {
            !std::ptr::eq(g, best)
                && gap(g, &best.bbox) == 0
                && g.extent() >= MIN_SHAPED_CELLS
                && g.fill() <= TOUCHING_FILL_SCALE * self.max_fill
                && bent(g)
        };
        let small_reach = if groups.iter().filter(|g| small(g)).count() <= MAX_PIECES {
            far
        } else {
            near
        };
        let mut b = best.bbox;
        for g in groups {
            let joins = if shaped(g) {
                gap(g, &b) <= far
            } else {
                (small(g) && gap(g, &best.bbox) <= small_reach) || thickened(g)
            };
            if g.count >= 2 && joins {
                b = [
                    b[0].min(g.bbox[0]),
                    b[1].min(g.bbox[1]),
                    b[2].max(g.bbox[2]),
                    b[3].max(g.bbox[3]),
                ];
            }
        }
        let rect = Rect {
            x0: within.x0 + b[0] as u32 * s,
            y0: within.y0 + b[1] as u32 * s,
            x1: within.x0 + (b[2] as u32 + 1) * s,
            y1: within.y0 + (b[3] as u32 + 1) * s,
        };
        rect.grown(self.margin_px, image.width, image.height)
    }
}

impl Segmenter for ColorSegmenter {
    fn locate(&self, image: &RgbImage, within: Rect) -> Option<Rect> {
        self.ranked(image, within, 1).pop()
    }

    fn candidates(&self, image: &RgbImage, within: Rect) -> Vec<Rect> {
        self.ranked(image, within, 3)
    }

    fn segment(&self, image: &RgbImage, roi: Rect) -> Result<Masks, PerceptionError> {
        let roi = roi.clipped(image.width, image.height);
        let w = image.width as usize;
        let (rw, rh) = (roi.width() as usize, roi.height() as usize);
        let mut needle = vec![0u8; rw * rh];
        let mut thread = vec![0u8; rw * rh];
        for y in 0..rh {
            let iy = roi.y0 as usize + y;
            let row = &image.data[(iy * w + roi.x0 as usize) * 3..(iy * w + roi.x1 as usize) * 3];
            for (x, p) in row.chunks_exact(3).enumerate() {
                needle[y * rw + x] = u8::from(self.is_needle(p));
                thread[y * rw + x] = u8::from(self.is_thread(p));
            }
        }
        if self.min_component_px > 1 {
            drop_specks(&mut needle, rw, rh, self.min_component_px as usize);
        }
        Ok(Masks {
            roi,
            needle,
            thread,
        })
    }

    /// The tracer's mask: the colour rule, or a pixel more violet than its surroundings (blue
    /// over green by `THREAD_CONTRAST` levels, blue over red by a third of that, more than
    /// the 12 × 12 pixels round it on average, and bluer than green). A thread a pixel or two
    /// wide against a backdrop other than tissue blends into it, and the fixed rule misses it.
    /// The surroundings are 4 × 4 blocks' sums, three blocks by three round the pixel's.
    fn thread_mask(&self, image: &RgbImage, roi: Rect) -> Result<Vec<u8>, PerceptionError> {
        const B: usize = THREAD_BLOCK_PX as usize;
        let roi = roi.clipped(image.width, image.height);
        let w = image.width as usize;
        let (rw, rh) = (roi.width() as usize, roi.height() as usize);
        let (bw, bh) = (rw.div_ceil(B), rh.div_ceil(B));
        // Each pixel's blue − green and blue − red, once (the rule below reads nothing else),
        // and per block Σ(blue − green), Σ(blue − red), pixels. The loops are plain slices
        // without branches, so the compiler vectorises the decision (the tracer's mask is half
        // its time).
        let mut bg = vec![0i16; rw * rh];
        let mut br = vec![0i16; rw * rh];
        let mut blocks = vec![[0i32; 3]; bw * bh];
        // Column sums over the block row so far: one add a pixel, folded into blocks every
        // B rows.
        let (mut col_bg, mut col_br) = (vec![0i32; rw], vec![0i32; rw]);
        for y in 0..rh {
            let row = &image.data[((roi.y0 as usize + y) * w + roi.x0 as usize) * 3..][..rw * 3];
            let (bgr, brr) = (&mut bg[y * rw..][..rw], &mut br[y * rw..][..rw]);
            for ((p, g), r) in row.chunks_exact(3).zip(bgr.iter_mut()).zip(brr.iter_mut()) {
                let b = i16::from(p[2]);
                *g = b - i16::from(p[1]);
                *r = b - i16::from(p[0]);
            }
            for (c, &v) in col_bg.iter_mut().zip(bgr.iter()) {
                *c += i32::from(v);
            }
            for (c, &v) in col_br.iter_mut().zip(brr.iter()) {
                *c += i32::from(v);
            }
            if y % B == B - 1 || y + 1 == rh {
                let rows = (y % B + 1) as i32;
                let brow = &mut blocks[(y / B) * bw..][..bw];
                for ((s, g), r) in brow.iter_mut().zip(col_bg.chunks(B)).zip(col_br.chunks(B)) {
                    *s = [g.iter().sum(), r.iter().sum(), g.len() as i32 * rows];
                }
                col_bg.fill(0);
                col_br.fill(0);
            }
        }
        // Each block's surroundings' means (inside the region a full 12 × 12: a division the
        // compiler makes a multiplication).
        let mut means = vec![[0i32; 2]; bw * bh];
        let div = |a: i32, n: i32| if n == 144 { a / 144 } else { a / n.max(1) };
        for by in 0..bh {
            for bx in 0..bw {
                let mut t = [0i32; 3];
                for yy in by.saturating_sub(1)..(by + 2).min(bh) {
                    for xx in bx.saturating_sub(1)..(bx + 2).min(bw) {
                        let s = blocks[yy * bw + xx];
                        t = [t[0] + s[0], t[1] + s[1], t[2] + s[2]];
                    }
                }
                means[by * bw + bx] = [div(t[0], t[2]), div(t[1], t[2])];
            }
        }
        // A pixel is thread where (blue − green) − mean ≥ THREAD_CONTRAST, (blue − red) −
        // mean ≥ a third of it and blue > green; or where the colour rule says so. Levels
        // stay within ±510 and the means within ±255, so i16 holds every difference.
        let (min_bg, min_br) = (
            i16::from(self.thread_blue_over_green),
            i16::from(self.thread_blue_over_red),
        );
        let contrast = THREAD_CONTRAST as i16;
        let mut thread = vec![0u8; rw * rh];
        let (mut need_bg, mut need_br) = (vec![0i16; rw], vec![0i16; rw]);
        for y in 0..rh {
            if y % B == 0 {
                // The thresholds of this row of blocks, per pixel.
                let mrow = &means[(y / B) * bw..][..bw];
                for (x, (a, b)) in need_bg.iter_mut().zip(need_br.iter_mut()).enumerate() {
                    let m = mrow[x / B];
                    *a = m[0] as i16 + contrast;
                    *b = m[1] as i16 + contrast / 3;
                }
            }
            let (g, r) = (&bg[y * rw..][..rw], &br[y * rw..][..rw]);
            for ((((o, &g), &r), &ng), &nr) in thread[y * rw..][..rw]
                .iter_mut()
                .zip(g)
                .zip(r)
                .zip(&need_bg)
                .zip(&need_br)
            {
                let contrasty = (g > 0) & (g >= ng) & (r >= nr);
                let coloured = (r >= min_br) & (g >= min_bg);
                *o = u8::from(contrasty | coloured);
            }
        }
        Ok(thread)
    }

    fn thread_mask_block_px(&self) -> Option<u32> {
        Some(THREAD_BLOCK_PX)
    }

    fn needleness(&self, p: [u8; 3]) -> f32 {
        let max = f32::from(p[0].max(p[1]).max(p[2]));
        let min = f32::from(p[0].min(p[1]).min(p[2]));
        let by_saturation = self.needle_max_saturation * max - (max - min);
        let by_value = max - f32::from(self.needle_min_value);
        by_saturation.min(by_value)
    }
}

/// Small groups near the needle that can be its pieces (past a jaw, the thread); more are
/// a field of glare specks.
const MAX_PIECES: usize = 3;

/// Groups smaller than this many cells across have no shape to judge.
const MIN_SHAPED_CELLS: usize = 8;
/// A group touching the needle's likeliest group joins it when it is bent and fills at most
/// this many times [`ColorSegmenter::max_fill`] (a piece of wire under a jaw's fingers).
const TOUCHING_FILL_SCALE: f32 = 1.5;

/// A connected group of grid cells.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Group {
    count: usize,
    /// `[x0, y0, x1, y1]`, cells, inclusive.
    bbox: [usize; 4],
    /// Sums of x, y, x², y², xy over its cells (for its principal axes).
    moments: [f64; 5],
}

impl Group {
    /// The larger side of its box, cells.
    fn extent(&self) -> usize {
        (self.bbox[2] - self.bbox[0]).max(self.bbox[3] - self.bbox[1]) + 1
    }
    /// Its cells over its extent squared.
    fn fill(&self) -> f32 {
        self.count as f32 / (self.extent() * self.extent()) as f32
    }
    /// The spread across its main axis over the spread along it (standard deviations):
    /// near 0 for a straight streak, about 0.44 for a half circle seen face on.
    fn bend(&self) -> f32 {
        let n = self.count as f64;
        let [sx, sy, sxx, syy, sxy] = self.moments;
        let (mx, my) = (sx / n, sy / n);
        let (a, b, c) = (sxx / n - mx * mx, sxy / n - mx * my, syy / n - my * my);
        // Eigenvalues of [[a, b], [b, c]].
        let mid = (a + c) / 2.0;
        let half = (((a - c) / 2.0).powi(2) + b * b).sqrt();
        let (major, minor) = (mid + half, (mid - half).max(0.0));
        if major <= 0.0 {
            return 0.0;
        }
        (minor / major).sqrt() as f32
    }
}

/// Label the connected groups of hits (`u32::MAX`) in a `gw × gh` grid, cells within
/// `reach` of each other joined (1: 8-neighbours). Labels the grid in place.
fn label_groups(grid: &mut [u32], gw: usize, gh: usize, reach: i64) -> Vec<Group> {
    let mut groups: Vec<Group> = Vec::new();
    let mut stack = Vec::new();
    for start in 0..grid.len() {
        if grid[start] != u32::MAX {
            continue;
        }
        let label = groups.len() as u32 + 1;
        grid[start] = label;
        stack.push(start);
        let mut g = Group {
            count: 0,
            bbox: [usize::MAX, usize::MAX, 0, 0],
            moments: [0.0; 5],
        };
        while let Some(i) = stack.pop() {
            let (x, y) = (i % gw, i / gw);
            g.count += 1;
            let (fx, fy) = (x as f64, y as f64);
            g.moments[0] += fx;
            g.moments[1] += fy;
            g.moments[2] += fx * fx;
            g.moments[3] += fy * fy;
            g.moments[4] += fx * fy;
            g.bbox = [
                g.bbox[0].min(x),
                g.bbox[1].min(y),
                g.bbox[2].max(x),
                g.bbox[3].max(y),
            ];
            for dy in -reach..=reach {
                for dx in -reach..=reach {
                    let (nx, ny) = (x as i64 + dx, y as i64 + dy);
                    if nx < 0 || ny < 0 || nx >= gw as i64 || ny >= gh as i64 {
                        continue;
                    }
                    let j = ny as usize * gw + nx as usize;
                    if grid[j] == u32::MAX {
                        grid[j] = label;
                        stack.push(j);
                    }
                }
            }
        }
        groups.push(g);
    }
    groups
}

/// Clear the 8-connected components of a `w × h` mask smaller than `min` pixels.
pub(crate) fn drop_specks(mask: &mut [u8], w: usize, h: usize, min: usize) {
    retain_components(mask, w, h, |g, _| g.count >= min);
}

/// Clear the 8-connected components of a `w × h` mask that `keep` (each component, and how
/// many there are) says no to.
fn retain_components(mask: &mut [u8], w: usize, h: usize, keep: impl Fn(&Group, usize) -> bool) {
    let mut grid: Vec<u32> = mask
        .iter()
        .map(|&v| if v != 0 { u32::MAX } else { 0 })
        .collect();
    let groups = label_groups(&mut grid, w, h, 1);
    let kept: Vec<bool> = groups.iter().map(|g| keep(g, groups.len())).collect();
    if kept.iter().all(|&k| k) {
        return;
    }
    for (m, &label) in mask.iter_mut().zip(&grid) {
        if label != 0 && !kept[label as usize - 1] {
            *m = 0;
        }
    }
}

/// In a cluttered needle mask (more than `max_components` 8-connected components: wet
/// glare's specks), keep only the components shaped like wire: at least `min_extent` pixels
/// across and covering no more than `max_fill` of their extent squared. A mask of fewer
/// components is left as it is: a needle cut by a jaw or the thread keeps its short pieces.
pub(crate) fn declutter(
    mask: &mut [u8],
    w: usize,
    h: usize,
    max_components: usize,
    min_extent: usize,
    max_fill: f32,
) {
    retain_components(mask, w, h, |g, n| {
        n <= max_components || (g.extent() >= min_extent && g.fill() <= max_fill)
    });
}

/// Check an image has the size its calibration says and a whole number of pixels.
pub fn check_image(
    image: &RgbImage,
    width: u32,
    height: u32,
    which: &str,
) -> Result<(), PerceptionError> {
    if image.width != width || image.height != height {
        return Err(PerceptionError::Camera {
            message: format!(
                "{which} image is {}×{}; the calibration says {width}×{height}",
                image.width, image.height
            ),
        });
    }
    if image.data.len() != width as usize * height as usize * 3 {
        return Err(PerceptionError::Camera {
            message: format!(
                "{which} image has {} bytes; {width}×{height} RGB needs {}",
                image.data.len(),
                width as usize * height as usize * 3
            ),
        });
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn image_with(w: u32, h: u32, bg: [u8; 3], draw: &[(u32, u32, [u8; 3])]) -> RgbImage {
        let mut img = RgbImage::new(w, h);
        for p in img.data.chunks_exact_mut(3) {
            p.copy_from_slice(&bg);
        }
        for &(x, y, c) in draw {
            let i = ((y * w + x) * 3) as usize;
            img.data[i..i + 3].copy_from_slice(&c);
        }
        img
    }

    #[test]
    fn grey_is_needle_violet_is_thread_pink_is_neither() {
        let s = ColorSegmenter::default();
        assert!(s.is_needle(&[150, 150, 155]));
        assert!(s.is_needle(&[255, 255, 255]));
        assert!(!s.is_needle(&[206, 122, 118]), "tissue");
        assert!(!s.is_needle(&[40, 40, 44]), "tool");
        assert!(s.is_thread(&[118, 58, 172]));
        assert!(!s.is_thread(&[52, 112, 78]), "drape");
        assert!(s.needleness([150, 150, 150]) > 0.0);
        assert!(s.needleness([206, 122, 118]) < 0.0);
    }

    #[test]
    fn the_needle_is_located_and_specks_are_ignored() {
        let mut draw: Vec<_> = (100..160)
            .flat_map(|x| (50..56).map(move |y| (x, y, [160, 160, 160])))
            .collect();
        draw.push((10, 10, [200, 200, 200])); // a speck far away
        let img = image_with(320, 240, [206, 122, 118], &draw);
        let s = ColorSegmenter::default();
        let r = s.locate(&img, Rect::full(320, 240)).expect("found");
        assert!(
            r.x0 <= 100 && r.x1 >= 160 && r.y0 <= 50 && r.y1 >= 56,
            "{r:?}"
        );
        assert!(r.x0 > 10 && r.y0 > 10, "speck joined: {r:?}");
        let m = s.segment(&img, r).expect("masks");
        assert_eq!(m.needle_count(), 60 * 6);
        assert!(m.is_needle(120, 52) && !m.is_needle(120, 60));
        let blank = image_with(320, 240, [206, 122, 118], &[]);
        assert_eq!(s.locate(&blank, Rect::full(320, 240)), None);
    }

    #[test]
    fn glare_blobs_and_a_shaft_highlight_are_not_the_needle() {
        let grey = [170, 170, 172];
        let mut draw = Vec::new();
        // The needle: a half circle of radius 60 px, 3 px wire, around (400, 300).
        for k in 0..2000 {
            let a = std::f64::consts::PI * f64::from(k) / 1999.0;
            for dr in [-1.0, 0.0, 1.0] {
                let (x, y) = (400.0 + (60.0 + dr) * a.cos(), 300.0 - (60.0 + dr) * a.sin());
                draw.push((x as u32, y as u32, grey));
            }
        }
        // Glare: a dense blob of 70 px across, more pixels than the needle.
        for y in 60..130u32 {
            for x in 60..130u32 {
                if (x + y) % 5 != 0 {
                    draw.push((x, y, [235, 228, 226]));
                }
            }
        }
        // A shaft's highlight: a straight bar 300 px long, 6 px wide.
        for x in 150..450u32 {
            for y in 420..426u32 {
                draw.push((x, y, [200, 200, 200]));
            }
        }
        let img = image_with(640, 480, [150, 40, 40], &draw);
        let s = ColorSegmenter::default();
        let r = s.locate(&img, Rect::full(640, 480)).expect("found");
        assert!(
            r.x0 <= 340 && r.x1 >= 460 && r.y0 <= 240 && r.y1 >= 300,
            "{r:?}"
        );
        assert!(
            r.x0 > 130 && r.y1 < 420,
            "glare or the highlight taken: {r:?}"
        );
        // Without the shape tests (the largest group, as before), the glare is taken.
        let largest = ColorSegmenter {
            max_fill: 1.0,
            min_bend: 0.0,
            ..ColorSegmenter::default()
        };
        let r = largest.locate(&img, Rect::full(640, 480)).expect("found");
        assert!(r.x0 < 130 && r.y0 < 130, "{r:?}");
    }

    #[test]
    fn regions_past_the_image_are_clipped_not_a_panic() {
        let img = image_with(64, 48, [160, 160, 160], &[]);
        let s = ColorSegmenter::default();
        let far = Rect {
            x0: 60,
            y0: 40,
            x1: 5000,
            y1: 5000,
        };
        assert!(s.locate(&img, far).is_some());
        assert_eq!(
            s.segment(&img, far).expect("masks").roi,
            Rect {
                x0: 60,
                y0: 40,
                x1: 64,
                y1: 48
            }
        );
        let outside = Rect {
            x0: 100,
            y0: 100,
            x1: 200,
            y1: 200,
        };
        assert_eq!(s.locate(&img, outside), None);
        assert_eq!(s.segment(&img, outside).expect("masks").needle_count(), 0);
    }

    #[test]
    fn images_of_the_wrong_size_are_refused() {
        let img = RgbImage::new(10, 10);
        assert!(check_image(&img, 10, 10, "left").is_ok());
        let e = check_image(&img, 20, 10, "left").expect_err("size");
        assert!(e.to_string().contains("10×10"), "{e}");
    }

    /// A 120 × 120 mask: a half-ring of wire 3 px wide (radius 50 px about (60, 60)), a short
    /// straight piece of it past a gap, and `specks` 4 × 4 blobs along the bottom.
    fn wire_and_specks(specks: usize) -> Vec<u8> {
        let (w, h) = (120usize, 120usize);
        let mut m = vec![0u8; w * h];
        for y in 0..60 {
            for x in 0..w {
                let r = ((x as f64 - 60.0).powi(2) + (y as f64 - 60.0).powi(2)).sqrt();
                if (48.5..51.5).contains(&r) {
                    m[y * w + x] = 1;
                }
            }
        }
        for k in 0..specks {
            let (x0, y0) = (2 + (k % 19) * 6, 80 + (k / 19) * 6);
            for y in y0..y0 + 4 {
                for x in x0..x0 + 4 {
                    m[y * w + x] = 1;
                }
            }
        }
        m
    }

    #[test]
    fn a_cluttered_mask_keeps_only_its_wire_and_a_clean_one_everything() {
        let (w, h) = (120, 120);
        let wire = wire_and_specks(0);
        // 40 specks and the wire: 41 components, cluttered; the specks go, the wire stays.
        let mut m = wire_and_specks(40);
        declutter(&mut m, w, h, 30, 16, 0.10);
        assert_eq!(m, wire);
        // 20 specks: not cluttered (a needle cut by a jaw keeps its pieces): untouched.
        let mut m = wire_and_specks(20);
        let before = m.clone();
        declutter(&mut m, w, h, 30, 16, 0.10);
        assert_eq!(m, before);
        // A thick blob as large as the wire is not wire either.
        let mut m = wire_and_specks(40);
        for y in 100..118 {
            for x in 20..100 {
                m[y * w + x] = 1;
            }
        }
        declutter(&mut m, w, h, 30, 16, 0.10);
        assert_eq!(m, wire);
    }
}
