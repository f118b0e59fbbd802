//! The stereo needle pipeline: segmentation → disparity → point cloud → RANSAC plane →
//! RANSAC circle (known radius) → endpoints, tip told from swage by the holding jaw, the
//! taper and the thread → a pose with a confidence, or a typed failure. Deterministic given
//! its seed.

use crate::disparity::{
    DisparityMap, MaskRowMatcher, SemiGlobalMatcher, StereoInput, StereoMatcher,
};
use crate::fit::{self, Circle, RansacParams, arc_extent, plane_basis};
use crate::refine::{Images, Refined};
use crate::segment::{ColorSegmenter, Masks, Rect, Segmenter, check_image, declutter};
use crate::{NeedleEstimate, NeedleEstimator, PerceptionError};
use nalgebra::{Matrix3, Rotation3, UnitQuaternion};
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use serde::{Deserialize, Serialize};
use std::f64::consts::PI;
use std::time::{Duration, Instant};
use stitch_robot::{Needle, Point, Pose, StereoCalibration, StereoCamera, StereoFrame, Vector};

/// Both views' masks, the cloud from them and the diagnostics so far.
type Found = (Masks, Masks, Vec<Point>, Diagnostics);

/// Mixed into the seed for the free circle's draws (any constant: they are its own).
const FREE_CIRCLE_SEED: u64 = 0x5EED_F8EE;

/// Places for the needle tried in turn, at most (the segmenter's ranking, then the likeliest
/// joined with its neighbours: [`joined`]).
const MAX_CANDIDATES: usize = 5;

/// The swage's radius as a multiple of the wire's (a crimped swage is thicker; modelling
/// choice shared with the renderer's needle).
const SWAGE_RADIUS_SCALE: f64 = 1.25;

/// The pipeline's thresholds.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct PipelineParams {
    /// Nearest and farthest needle depth the disparity search covers, m.
    pub depth_range_m: [f64; 2],
    /// Extra disparity allowed beyond the two views' regions' offsets, pixels.
    pub disparity_margin_px: u32,
    /// Margin around the disparities the mask rows match, for a general matcher's search;
    /// 0 searches the whole range, pixels.
    pub narrow_margin_px: u32,
    /// Most points kept for fitting (evenly subsampled).
    pub max_points: usize,
    /// Least points in the cloud, and least circle inliers.
    pub min_points: usize,
    /// RANSAC thresholds and iterations.
    pub ransac: RansacParams,
    /// The rig's disparity step at the needle (depth² / (focal length × baseline)) that the
    /// RANSAC thresholds and the share zone were made for, m: where a rig's step at a point
    /// is coarser, the point's offset along its own viewing ray is scaled by this over that
    /// step ([`fit::RayDiscount`]); 0 counts it in full on every rig.
    pub depth_step_ref_m: f64,
    /// Hypotheses of the circle through three points, for a cloud whose plane and circle do
    /// not hold (most draws miss: the needle's points may be a fifth of the cloud).
    pub free_circle_iterations: usize,
    /// Least share of the points within `share_zone_m` of the fitted circle that are on it.
    pub min_inlier_share: f64,
    /// Points this near the fitted circle count for `min_inlier_share` (clutter beside
    /// the needle counts against a fit; things farther off, a jaw's body, a patch of
    /// glare, do not), m.
    pub share_zone_m: f64,
    /// Least arc seen, rad (the needle is a half circle: π).
    pub min_arc_rad: f64,
    /// A half-circle needle covers π and its two rounded ends; points covering more than π
    /// plus this are not all needle, rad.
    pub max_overshoot_rad: f64,
    /// An arc within this of π counts as both ends seen, rad.
    pub full_arc_tolerance_rad: f64,
    /// Thread pixels searched for within this distance of each end, m.
    pub swage_search_m: f64,
    /// An end whose wire is narrower than this share of its width 3 mm along is the tip.
    pub tip_taper_ratio: f64,
    /// With both ends measured, the end whose width ratio is lower by this much is the tip.
    pub taper_difference: f64,
    /// An end whose wire is wider than this share of its width 3 mm along is the swage.
    pub swage_taper_ratio: f64,
    /// An end whose wire measures wider than this share of its width 3 mm in, with an
    /// instrument beside it (`min_instrument_share`), is a jaw's steel merged with the wire:
    /// its taper is not read (a swage is at most about 1.35 times the wire).
    pub max_end_width_ratio: f64,
    /// Least share of the left image's pixels within `swage_search_m` of an end that are
    /// dark grey (an instrument's shaft or fingers) for `max_end_width_ratio` to apply.
    pub min_instrument_share: f64,
    /// Least thread pixels near the swage end.
    pub min_thread_px: usize,
    /// The swage end must have at least this many times the other end's thread pixels.
    pub swage_ratio: f64,
    /// A jaw hint decides which end is which only if the jaw is this much nearer one end of
    /// the arc, rad.
    pub jaw_margin_rad: f64,
    /// Least points for a needle in tissue (most of it is hidden).
    pub min_points_in_tissue: usize,
    /// Least needle seen past a hole to place its end, in tissue, m.
    pub min_tip_seen_m: f64,
    /// A needle in tissue passes its holes: a circle fitted freely to what is seen is taken
    /// only if it passes within this of both (the plan's holes, which the needle misses by a
    /// few millimetres at most: on the mock, up to about 2 mm once pushed through), m.
    pub max_hole_miss_m: f64,
    /// Estimates less confident than this are refused.
    pub min_confidence: f64,
    /// Least share of the arc whose wire the refined circle runs down in both views for
    /// the images to decide the fit (otherwise the cloud's tests do).
    pub min_image_support: f64,
    /// The wire's middle within this of the projected circle counts as on it, pixels.
    pub image_tolerance_px: f64,
    /// Along the refined circle, gaps in the wire up to this are bridged when the arc the
    /// images show is followed past the cloud's, rad.
    pub image_gap_rad: f64,
    /// A refinement that moves the centre of a circle the cloud holds farther than this is
    /// not taken, m.
    pub image_max_shift_m: f64,
    /// Nor one that tilts it more than this, rad.
    pub image_max_tilt_rad: f64,
    /// The images decide a fit only if the camera sees the circle's plane at least this
    /// far from edge on, rad.
    pub image_min_view_rad: f64,
    /// Least arc seen when the images decide the circle (`min_arc_rad` otherwise), rad.
    pub image_min_arc_rad: f64,
    /// A needle mask of more than this many 8-connected components is cluttered (wet
    /// glare's specks, hundreds of them): only its components shaped like wire are kept
    /// (`clutter_min_extent_px` across or more, covering at most `clutter_max_fill` of their
    /// extent squared).
    pub clutter_components: usize,
    /// See `clutter_components`, pixels.
    pub clutter_min_extent_px: usize,
    /// See `clutter_components`.
    pub clutter_max_fill: f32,
}

impl Default for PipelineParams {
    fn default() -> Self {
        Self {
            depth_range_m: [0.05, 0.6],
            disparity_margin_px: 40,
            narrow_margin_px: 20,
            max_points: 1500,
            min_points: 40,
            ransac: RansacParams::default(),
            depth_step_ref_m: 0.0007,
            free_circle_iterations: 2000,
            min_inlier_share: 0.5,
            share_zone_m: 0.003,
            min_arc_rad: 140f64.to_radians(),
            max_overshoot_rad: 8f64.to_radians(),
            full_arc_tolerance_rad: 12f64.to_radians(),
            swage_search_m: 0.0025,
            tip_taper_ratio: 0.8,
            swage_taper_ratio: 1.08,
            taper_difference: 0.25,
            max_end_width_ratio: 1.6,
            min_instrument_share: 0.1,
            min_thread_px: 4,
            swage_ratio: 2.0,
            jaw_margin_rad: 30f64.to_radians(),
            min_points_in_tissue: 15,
            min_tip_seen_m: 0.002,
            max_hole_miss_m: 0.005,
            min_confidence: 0.5,
            min_image_support: 0.8,
            image_tolerance_px: 1.5,
            image_gap_rad: 12f64.to_radians(),
            image_max_shift_m: 0.0006,
            image_max_tilt_rad: 3f64.to_radians(),
            image_min_view_rad: 15f64.to_radians(),
            image_min_arc_rad: 110f64.to_radians(),
            clutter_components: 30,
            clutter_min_extent_px: 16,
            clutter_max_fill: 0.10,
        }
    }
}

/// Time spent in each stage of one estimate (measured; never affects the result).
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize)]
pub struct StageTimes {
    /// Locating and segmenting both views.
    pub segment: Duration,
    /// Disparity.
    pub disparity: Duration,
    /// Point cloud.
    pub cloud: Duration,
    /// Plane, circle, endpoints.
    pub fit: Duration,
}

/// What one estimate found besides the pose, for diagnosis and benchmarks.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Diagnostics {
    /// The left and right regions of interest.
    pub rois: [Rect; 2],
    /// Disparity search range, pixels.
    pub disparity_range: [u32; 2],
    /// Needle pixels, left view.
    pub needle_px: usize,
    /// Points in the cloud (after subsampling).
    pub cloud_points: usize,
    /// Plane inliers.
    pub plane_inliers: usize,
    /// Circle inliers.
    pub circle_inliers: usize,
    /// RMS distance of the circle inliers, m.
    pub rms_m: f64,
    /// Arc seen, rad.
    pub arc_rad: f64,
    /// Thread pixels near the arc's two observed ends (counter-clockwise first).
    pub thread_px: [usize; 2],
    /// The wire's width near each observed end against 3 mm along the arc.
    pub taper: [Option<f64>; 2],
    /// Share of the arc the images held on the circle refined against both views' masks
    /// (`None`: not refined, or not held; the cloud's tests decided).
    pub image_support: Option<f64>,
    /// The circle came from the left silhouette's ellipse, not from the cloud (which could
    /// not be fitted).
    pub from_silhouettes: bool,
    /// The circle came from the cloud with no plane first (its plane was clutter's).
    pub free_circle: bool,
    /// Stage times.
    pub times: StageTimes,
}

/// Which end of the needle a jaw holds it nearer to.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NeedleEnd {
    /// The sharp end (the left jaw after a handover).
    Tip,
    /// The thread end (the right jaw's grasp for insertion).
    Swage,
}

/// What the robot knows about where the needle is: the jaw holding it. The pipeline crops
/// both views around the jaw's projection and takes the needle end nearer the jaw to be
/// `end`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JawHint {
    /// The holding jaw's tool-tip position, robot frame, m.
    pub jaw: Point,
    /// The end it holds the needle nearer to.
    pub end: NeedleEnd,
}

/// A ball the needle must lie in, robot frame.
#[derive(Clone, Copy, Debug, PartialEq)]
struct Region {
    center: Point,
    reach_m: f64,
    /// Segment the whole projection rather than locate the needle in it: a needle lodged
    /// in tissue shows short pieces past its holes, which the segmenter's tests of a
    /// needle's shape are not made for.
    whole: bool,
}

/// What the robot knows about a needle lodged in tissue: the holes it went through.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TissueHint {
    /// Where it entered, robot frame, m.
    pub entry: Point,
    /// Where it came out, m.
    pub exit: Point,
}

/// What the robot knows about where the needle is.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum NeedleHint {
    /// A jaw holds it.
    Held(JawHint),
    /// It is lodged in the tissue through these holes.
    InTissue(TissueHint),
}

/// The stereo needle pipeline.
#[derive(Debug)]
pub struct NeedlePipeline {
    /// Thresholds.
    pub params: PipelineParams,
    /// Stage 1.
    pub segmenter: Box<dyn Segmenter>,
    /// Stage 2.
    pub matcher: Box<dyn StereoMatcher>,
    /// The needle's shape.
    pub needle: Needle,
    /// The camera.
    pub calibration: StereoCalibration,
    /// Run the two views' segmentation on two threads.
    pub parallel: bool,
}

/// A circle fitted to the needle, the arc of it seen, and how well: the share of the
/// points (or of the arc's samples in the images) on it, and how tightly they hug it (0 to 1).
struct Fitted {
    circle: Circle,
    arc: fit::ArcExtent,
    share: f64,
    tight: f64,
}

/// An estimate and how it was found.
#[derive(Clone, Debug, PartialEq)]
pub struct PipelineOutput {
    /// The needle frame in the robot frame, m.
    pub pose: Pose,
    /// 0 to 1.
    pub confidence: f64,
    /// Numbers along the way.
    pub diagnostics: Diagnostics,
}

impl NeedlePipeline {
    /// The classical pipeline (colour segmentation, semi-global matching around the needle
    /// mask, its disparity range narrowed by the mask rows' matches) for this camera.
    pub fn classical(
        calibration: StereoCalibration,
        needle: Needle,
    ) -> Result<Self, PerceptionError> {
        calibration
            .validate()
            .map_err(|e| PerceptionError::Config {
                message: e.to_string(),
            })?;
        Ok(Self {
            params: PipelineParams::default(),
            segmenter: Box::new(ColorSegmenter::default()),
            matcher: Box::new(SemiGlobalMatcher::default()),
            needle,
            calibration,
            parallel: false,
        })
    }

    /// Where the needle is in a stereo pair: searched over the whole frames, or only around
    /// the holding jaw's projection if `hint` gives the jaw. `seed` fixes RANSAC's draws.
    pub fn estimate(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        hint: Option<&JawHint>,
        seed: u64,
    ) -> Result<PipelineOutput, PerceptionError> {
        let region = hint.map(|h| self.region_near(&h.jaw));
        self.run(left, right, region, hint, seed)
    }

    /// Where the needle must be when it is near `point` (a jaw holding it, or the middle of
    /// the holes it is in): within two radii and a margin.
    fn region_near(&self, point: &Point) -> Region {
        Region {
            center: *point,
            reach_m: 2.0 * self.needle.radius_m + 0.004,
            whole: false,
        }
    }

    /// Disparity over the needle's region only (stages 1–2), for `stitch perceive disparity`.
    pub fn disparity(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        roi: Option<Rect>,
    ) -> Result<DisparityMap, PerceptionError> {
        let c = &self.calibration;
        check_image(left, c.width, c.height, "left")?;
        check_image(right, c.width, c.height, "right")?;
        if let Some(r) = roi {
            if r.is_empty() || r.x1 > c.width || r.y1 > c.height {
                return Err(PerceptionError::Config {
                    message: format!(
                        "region {}..{} × {}..{} is not inside the {}×{} image",
                        r.x0, r.x1, r.y0, r.y1, c.width, c.height
                    ),
                });
            }
        }
        let (lm, rm, range) = self.masks(left, right, roi, None, 0)?.ok_or(no_left())?;
        self.matcher.disparity(&StereoInput {
            left,
            right,
            left_masks: &lm,
            right_masks: &rm,
            min_disparity: range[0],
            max_disparity: range[1],
            segmenter: self.segmenter.as_ref(),
            parallel: self.parallel,
        })
    }

    /// The disparity range narrowed to what the needle masks' rows match (a fraction of a
    /// millisecond), with `narrow_margin_px` either side: a general matcher then searches
    /// tens of disparities, not hundreds. Unchanged if too few rows match.
    fn narrowed(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        lm: &Masks,
        rm: &Masks,
        range: [u32; 2],
    ) -> [u32; 2] {
        if self.params.narrow_margin_px == 0 || self.matcher.name() == "mask-row" {
            return range;
        }
        let Ok(map) = MaskRowMatcher::default().disparity(&StereoInput {
            left,
            right,
            left_masks: lm,
            right_masks: rm,
            min_disparity: range[0],
            max_disparity: range[1],
            segmenter: self.segmenter.as_ref(),
            parallel: self.parallel,
        }) else {
            return range;
        };
        let mut d: Vec<f32> = map.data.iter().copied().filter(|v| v.is_finite()).collect();
        if d.len() < 20 {
            return range;
        }
        d.sort_by(f32::total_cmp);
        let lo = d[0].floor() as i64 - i64::from(self.params.narrow_margin_px);
        let hi = d[d.len() - 1].ceil() as i64 + i64::from(self.params.narrow_margin_px);
        let lo = lo.max(i64::from(range[0])) as u32;
        let hi = hi.min(i64::from(range[1])) as u32;
        if lo < hi { [lo, hi] } else { range }
    }

    /// A region's projection in the left view and the disparities its depths give.
    fn project_region(&self, region: &Region) -> Option<(Rect, [u32; 2])> {
        let c = &self.calibration;
        let q = c.camera_to_robot.inverse() * region.center;
        let reach = region.reach_m;
        if q.z <= reach + 0.01 {
            return None;
        }
        let rad = c.fx * reach / (q.z - reach);
        let (u, v) = (c.fx * q.x / q.z + c.cx, c.fy * q.y / q.z + c.cy);
        let clip = |x: f64, hi: u32| x.clamp(0.0, f64::from(hi)) as u32;
        let rect = Rect {
            x0: clip(u - rad, c.width),
            y0: clip(v - rad, c.height),
            x1: clip(u + rad, c.width),
            y1: clip(v + rad, c.height),
        };
        let fb = c.fx * c.baseline_m;
        let range = [
            (fb / (q.z + reach)).floor() as u32,
            (fb / (q.z - reach)).ceil() as u32,
        ];
        (!rect.is_empty()).then_some((rect, range))
    }

    /// The disparity range the calibration allows: depths `depth_range_m`.
    fn calibrated_range(&self) -> [u32; 2] {
        let c = &self.calibration;
        let [near, far] = self.params.depth_range_m;
        let fb = c.fx * c.baseline_m;
        [
            (fb / far).floor().max(0.0) as u32,
            (fb / near).ceil() as u32,
        ]
    }

    /// A needle mask cluttered with wet glare's specks (`clutter_components`) keeps only
    /// its components shaped like wire: the specks next to the wire pull the cloud's circle
    /// and the silhouette's ellipse off it, and their matches outnumber the wire's.
    fn declutter(&self, m: &mut Masks) {
        let p = &self.params;
        let (w, h) = (m.roi.width() as usize, m.roi.height() as usize);
        declutter(
            &mut m.needle,
            w,
            h,
            p.clutter_components,
            p.clutter_min_extent_px,
            p.clutter_max_fill,
        );
    }

    fn masks(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        within: Option<Rect>,
        region: Option<Region>,
        candidate: usize,
    ) -> Result<Option<(Masks, Masks, [u32; 2])>, PerceptionError> {
        let c = &self.calibration;
        let full = Rect::full(c.width, c.height);
        let seg = self.segmenter.as_ref();
        if let Some(region) = region {
            // Where the needle must be is known: search the left view around its
            // projection, and the right view only where the same points can appear at the
            // depths the region allows — no independent search that could find another
            // part of the needle (or something else) in the right view.
            let (rect, range) = self
                .project_region(&region)
                .ok_or(PerceptionError::NoMask {
                    view: "left (the expected region is out of view)".into(),
                })?;
            let mut lm = if region.whole {
                Some(seg.segment(left, rect)?).filter(|m| m.needle_count() > 0)
            } else {
                let places = joined(seg.candidates(left, rect));
                if candidate > 0 && candidate >= places.len() {
                    return Ok(None);
                }
                places
                    .get(candidate)
                    .map(|&roi| seg.segment(left, roi))
                    .transpose()?
            }
            .ok_or(PerceptionError::NoMask {
                view: "left".into(),
            })?;
            let l = lm.roi;
            let rr = right_band(&l, range);
            let mut rm = seg.segment(right, rr)?;
            self.declutter(&mut lm);
            self.declutter(&mut rm);
            if rm.needle_count() == 0 {
                return Err(PerceptionError::NoMask {
                    view: "right".into(),
                });
            }
            return Ok(Some((lm, rm, range)));
        }
        let hl = within.unwrap_or(full);
        // The left view is searched where asked; the right view only where the same needle
        // can appear: the left region's rows (rectified views), shifted by the calibrated
        // disparities — another bright thing elsewhere in the right view is not a candidate.
        let [cmin, cmax] = self.calibrated_range();
        let places = joined(seg.candidates(left, hl));
        if candidate > 0 && candidate >= places.len() {
            return Ok(None);
        }
        let lroi = places
            .get(candidate)
            .copied()
            .ok_or(PerceptionError::NoMask {
                view: "left".into(),
            })?;
        let hr = right_band(&lroi, [cmin, cmax]).clipped(c.width, c.height);
        let rroi = seg.locate(right, hr).ok_or(PerceptionError::NoMask {
            view: "right".into(),
        })?;
        let (lm, rm) = if self.parallel {
            rayon::join(|| seg.segment(left, lroi), || seg.segment(right, rroi))
        } else {
            (seg.segment(left, lroi), seg.segment(right, rroi))
        };
        let (mut lm, mut rm) = (lm?, rm?);
        self.declutter(&mut lm);
        self.declutter(&mut rm);
        // The two regions frame the same needle: their left edges' offset and their right
        // edges' offset are disparities of its extreme points; the needle's own depth spread
        // is within the margin of them.
        let m = self.params.disparity_margin_px as i64;
        let a = i64::from(lm.roi.x0) - i64::from(rm.roi.x0);
        let b = i64::from(lm.roi.x1) - i64::from(rm.roi.x1);
        let lo = a.min(b) - m;
        let hi = a.max(b) + m;
        let lo = lo.max(i64::from(cmin)).max(0) as u32;
        let hi = hi.min(i64::from(cmax));
        if hi < i64::from(lo) {
            return Err(PerceptionError::NoMask {
                view: format!(
                    "both (the two views' needles are {}–{} pixels apart, outside the calibrated disparity range {cmin}–{cmax})",
                    a.min(b),
                    a.max(b)
                ),
            });
        }
        Ok(Some((lm, rm, [lo, hi as u32])))
    }

    /// The whole pipeline on a pair: searched in `region` if given, else over the frames.
    fn run(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        region: Option<Region>,
        jaw: Option<&JawHint>,
        seed: u64,
    ) -> Result<PipelineOutput, PerceptionError> {
        let c = &self.calibration;
        check_image(left, c.width, c.height, "left")?;
        check_image(right, c.width, c.height, "right")?;
        let first = self
            .run_candidate(left, right, region, jaw, seed, 0)
            .unwrap_or(Err(no_left()));
        // The segmenter's likeliest place may be a patch of wet glare: the places it ranks
        // lower are tried in turn while no needle can be fitted (a 12 mm circle both views
        // hold is not found in glare). The answer is the first estimate, or the failure
        // that got furthest.
        let refitable = |e: &PerceptionError| {
            matches!(
                e,
                PerceptionError::BadFit { .. }
                    | PerceptionError::TooFewPoints { .. }
                    | PerceptionError::NoMask { .. }
            )
        };
        if !first.as_ref().is_err_and(refitable) {
            return first;
        }
        let mut answer = first;
        for k in 1..MAX_CANDIDATES {
            let Some(next) = self.run_candidate(left, right, region, jaw, seed, k) else {
                break;
            };
            let further = |e: &PerceptionError| match e {
                PerceptionError::NoMask { .. } => 0,
                PerceptionError::TooFewPoints { .. } => 1,
                PerceptionError::BadFit { .. } => 2,
                _ => 3,
            };
            match (&answer, &next) {
                (_, Ok(_)) => return next,
                (Err(a), Err(b)) if further(b) > further(a) => answer = next,
                _ => {}
            }
        }
        answer
    }

    /// The pipeline on the segmenter's `candidate`-th place for the needle (full frame).
    fn run_candidate(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        region: Option<Region>,
        jaw: Option<&JawHint>,
        seed: u64,
        candidate: usize,
    ) -> Option<Result<PipelineOutput, PerceptionError>> {
        match self.cloud(left, right, region, candidate) {
            Ok(Some(found)) => Some(self.fit(found, jaw, seed, left)),
            Ok(None) => None,
            Err(e) => Some(Err(e)),
        }
    }

    /// Stages 4 and 5 on a cloud: the circle, the ends, the pose.
    fn fit(
        &self,
        (lm, rm, cloud, mut diag): Found,
        jaw: Option<&JawHint>,
        seed: u64,
        left: &stitch_robot::RgbImage,
    ) -> Result<PipelineOutput, PerceptionError> {
        let c = &self.calibration;
        let p = &self.params;
        let t3 = Instant::now();
        if cloud.len() < p.min_points {
            return Err(PerceptionError::TooFewPoints {
                found: cloud.len(),
                needed: p.min_points,
            });
        }
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let r = self.needle.radius_m;
        let images = Images::new(c, &lm, &rm, self.needle.wire_diameter_m);
        let rays = self.ray_discounts(&cloud);
        // From the cloud (its plane, then the circle in it); if that cannot be fitted, from
        // the silhouettes alone; then from the cloud with no plane first (its own draws).
        // The first whose arc a half-circle needle can be placed on is the answer, else the
        // cloud's failure.
        let mut first_error: Option<PerceptionError> = None;
        let mut fitted: Option<Fitted> = None;
        for attempt in 0..3 {
            diag.image_support = None;
            diag.from_silhouettes = false;
            diag.free_circle = attempt == 2;
            let f = match attempt {
                0 => self.fit_cloud(&cloud, &rays, &images, &mut rng, &mut diag),
                1 => self
                    .fit_silhouettes(&images, &mut rng, &mut diag)
                    .ok_or_else(|| PerceptionError::BadFit {
                        why: "the silhouettes hold no circle".into(),
                    }),
                _ => {
                    let mut own = ChaCha8Rng::seed_from_u64(seed ^ FREE_CIRCLE_SEED);
                    self.fit_cloud_free(&cloud, &rays, &images, &mut own, &mut diag)
                }
            };
            // A circle the cloud holds with too short an arc is the answer (a failure): the
            // other ways would place a half circle on that same short stretch of wire. A
            // circle found in clutter places the needle only when both its ends are seen
            // (an end hidden is placed from the ends' cues, which clutter confuses).
            let cloud_fitted = attempt == 0 && f.is_ok();
            let min_arc = match attempt {
                2 => PI - p.full_arc_tolerance_rad,
                _ if diag.image_support.is_some() => p.image_min_arc_rad,
                _ => p.min_arc_rad,
            };
            let f = f.and_then(|f| self.check_arc(f, min_arc));
            match f {
                Err(e) if cloud_fitted => return Err(e),
                Ok(f) => {
                    fitted = Some(f);
                    break;
                }
                Err(e @ PerceptionError::BadFit { .. }) => {
                    first_error.get_or_insert(e);
                }
                Err(e) => return Err(e),
            }
        }
        let Some(Fitted {
            circle,
            arc,
            share,
            tight,
        }) = fitted
        else {
            return Err(first_error.unwrap_or(PerceptionError::BadFit {
                why: "no circle".into(),
            }));
        };
        diag.arc_rad = arc.extent;
        // The ends: both seen → centre the half circle on the arc; one hidden → the thread
        // says which end is seen.
        let (e1, e2) = plane_basis(&circle.normal);
        let at = |a: f64| circle.center + (e1 * a.cos() + e2 * a.sin()) * r;
        let cap = self.needle.wire_diameter_m / 2.0 / r;
        let (lo_end, hi_end) = (arc.start + cap, arc.start + arc.extent - cap);
        let full = (arc.extent - PI).abs() <= p.full_arc_tolerance_rad;
        // Outward along the circle past each end.
        let tangent = |a: f64| e2 * a.cos() - e1 * a.sin();
        let thread_at = |strands| {
            [
                self.thread_near(&lm, &at(lo_end), &-tangent(lo_end), strands),
                self.thread_near(&lm, &at(hi_end), &tangent(hi_end), strands),
            ]
        };
        let mut threads = thread_at(Strands::All);
        // The tip tapers: the wire's width in the image near an end against its width 3 mm
        // along, for each observed end (the direction along the arc into the needle).
        // An end far wider than wire or swage with an instrument's steel round it is a jaw
        // merged with the wire: its width says nothing of a taper. `view`: a view's masks,
        // and whether they are the right view's.
        let step = 0.001 / r;
        let taper_in = |view: (&Masks, bool)| {
            [(lo_end, step), (hi_end, -step)].map(|(end, inward)| {
                self.width_ratio(view, &circle, end, inward).filter(|&t| {
                    t <= p.max_end_width_ratio
                        || self.instrument_share(left, &at(end)) < p.min_instrument_share
                })
            })
        };
        let taper = taper_in((&lm, false));
        diag.taper = taper;
        let tip_like = taper.map(|t| t.is_some_and(|t| t > 0.2 && t < p.tip_taper_ratio));
        // A known jaw decides: the end it holds the needle nearer to (if clearly nearer).
        let jaw_score = jaw.map_or(0, |h| {
            let d = h.jaw - circle.center;
            let a = d.dot(&e2).atan2(d.dot(&e1));
            let gap = |b: f64| (a - b + PI).rem_euclid(2.0 * PI) - PI;
            let (to_lo, to_hi) = (gap(arc.start).abs(), gap(arc.start + arc.extent).abs());
            if (to_lo - to_hi).abs() < p.jaw_margin_rad {
                0
            } else {
                let lo_nearer = to_lo < to_hi;
                let lo_is_tip = lo_nearer == (h.end == NeedleEnd::Tip);
                if lo_is_tip { 8 } else { -8 }
            }
        });
        let mut decided = tip_is_low_end(threads, taper, jaw_score, p);
        let by_taper = tip_is_low_end([0, 0], taper, 0, p);
        if decided.is_none() && by_taper.is_some() {
            // The thread contradicts the taper: a strand that only passes an end is not the
            // thread leaving the swage. Counted again without such strands, the taper decides
            // if the thread no longer says otherwise (never the thread alone: a strand
            // leaving the swage and bending back across the disc looks like one passing).
            let leaving = thread_at(Strands::Leaving);
            if tip_is_low_end(leaving, taper, jaw_score, p) == by_taper {
                threads = leaving;
                decided = by_taper;
            }
        }
        if decided.is_none() {
            // The left view's cues leave it open: an end is a few pixels wide, and one view's
            // mask may lose or add a pixel there. The right view's taper, read the same way,
            // decides if it tells the ends apart by itself, the left view's taper leans the
            // same way (the narrower end the tip) and the thread does not say otherwise.
            let right_taper = taper_in((&rm, true));
            if let Some(lo_is_tip) = tip_is_low_end([0, 0], right_taper, 0, p) {
                let leans = match taper {
                    [Some(lo), Some(hi)] => (lo < hi) == lo_is_tip,
                    _ => by_taper.is_none_or(|b| b == lo_is_tip),
                };
                if leans && tip_is_low_end(threads, right_taper, jaw_score, p) == Some(lo_is_tip) {
                    decided = Some(lo_is_tip);
                }
            }
        }
        diag.thread_px = threads;
        let Some(tip_is_lo) = decided else {
            return Err(PerceptionError::AmbiguousEndpoints {
                why: format!(
                    "thread pixels near the two ends: {} and {}; width at the ends against 3 mm in: {} and {}",
                    threads[0],
                    threads[1],
                    taper[0].map_or("–".into(), |t| format!("{t:.2}")),
                    taper[1].map_or("–".into(), |t| format!("{t:.2}")),
                ),
            });
        };
        // The half circle sits on an end known to be real: the swage's if the whole arc is
        // seen (within the tolerance: the taper's last millimetres may be lost) or the tip's
        // end is not seen tapering (a jaw or the thread hides it); the tapered tip's
        // otherwise (a jaw hides the swage), placed past the observed end by what the image
        // lost of the taper. (Thread near the swage's end is no sign the end is seen: it
        // leaves the swage from behind the jaw that hides it.)
        let swage_cap = SWAGE_RADIUS_SCALE * self.needle.wire_diameter_m / 2.0 / r;
        let tip_i = if tip_is_lo { 0 } else { 1 };
        // An observed end where the wire runs into an instrument's dark steel is where the
        // tool hides it, not where it ends: the half circle does not sit on it while the
        // other end is seen clear; where the wire runs into steel at both ends (the arc
        // short of a half circle, the tip not seen tapering) nothing says where it sits.
        let by_tool = [(lo_end, -1.0), (hi_end, 1.0)]
            .map(|(end, outward)| self.runs_into_tool(left, &circle, end, outward));
        let swage_by_tool = !full && !tip_like[tip_i] && by_tool[1 - tip_i];
        if swage_by_tool && by_tool[tip_i] {
            return Err(PerceptionError::AmbiguousEndpoints {
                why: format!(
                    "{:.0}° of the arc seen, the wire running into an instrument's steel past both its ends and the tip not seen tapering: where the needle's ends lie along it cannot be told",
                    arc.extent.to_degrees()
                ),
            });
        }
        let anchor = if full || (!tip_like[tip_i] && !swage_by_tool) {
            Anchor::Swage
        } else {
            let (end, inward) = if tip_is_lo {
                (arc.start, step)
            } else {
                (arc.start + arc.extent, -step)
            };
            Anchor::Tip {
                lost_rad: self.taper_lost_m(&lm, &circle, end, inward) / r,
            }
        };
        let (tip_angle, swage_angle) =
            half_circle_ends(arc.start, arc.extent, tip_is_lo, anchor, swage_cap);
        // Tip to swage runs counter-clockwise about the needle's +z.
        let z = if swage_angle > tip_angle {
            circle.normal
        } else {
            -circle.normal
        };
        let tip = at(tip_angle);
        let x = (tip - circle.center).normalize();
        let y = z.cross(&x);
        let rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[x, y, z]));
        let pose = Pose::from_parts(
            nalgebra::Translation3::from(circle.center.coords),
            UnitQuaternion::from_rotation_matrix(&rot),
        );
        let confidence = confidence(&arc, share, tight, full);
        diag.times.fit = t3.elapsed();
        if confidence < p.min_confidence {
            return Err(PerceptionError::Uncertain { confidence });
        }
        Ok(PipelineOutput {
            pose,
            confidence,
            diagnostics: diag,
        })
    }

    /// A fit whose arc a half-circle needle can lie on: at least `min_arc` of it seen (rad),
    /// and no more than a half circle and its ends.
    fn check_arc(&self, f: Fitted, min_arc: f64) -> Result<Fitted, PerceptionError> {
        let p = &self.params;
        if f.arc.extent < min_arc {
            return Err(PerceptionError::BadFit {
                why: format!(
                    "only {:.0}° of the needle's arc seen (at least {:.0}° needed)",
                    f.arc.extent.to_degrees(),
                    min_arc.to_degrees()
                ),
            });
        }
        if f.arc.extent > PI + p.max_overshoot_rad {
            return Err(PerceptionError::BadFit {
                why: format!(
                    "points cover {:.0}° of the circle, more than a half-circle needle",
                    f.arc.extent.to_degrees()
                ),
            });
        }
        Ok(f)
    }

    /// The circle from the cloud (RANSAC plane, then circle of the needle's radius),
    /// refined against both views' masks; the images decide if they hold it, the cloud's
    /// share test otherwise. `rays`: the cloud's [`Self::ray_discounts`].
    fn fit_cloud(
        &self,
        cloud: &[Point],
        rays: &[fit::RayDiscount],
        images: &Images,
        rng: &mut ChaCha8Rng,
        diag: &mut Diagnostics,
    ) -> Result<Fitted, PerceptionError> {
        let p = &self.params;
        let r = self.needle.radius_m;
        let (plane, plane_inliers) =
            fit::ransac_plane(cloud, rays, &p.ransac, rng).ok_or_else(|| {
                PerceptionError::BadFit {
                    why: "no plane through the points".into(),
                }
            })?;
        diag.plane_inliers = plane_inliers.len();
        let on_plane: Vec<Point> = plane_inliers.iter().map(|&i| cloud[i]).collect();
        let plane_rays: Vec<fit::RayDiscount> = plane_inliers
            .iter()
            .filter_map(|&i| rays.get(i).copied())
            .collect();
        let (circle, inliers) =
            fit::ransac_circle(&on_plane, &plane_rays, &plane, r, &p.ransac, rng).ok_or_else(
                || PerceptionError::BadFit {
                    why: format!("no {:.1} mm circle through the points", r * 1e3),
                },
            )?;
        let pts: Vec<usize> = inliers.iter().map(|&i| plane_inliers[i]).collect();
        self.judge_cloud_circle(cloud, rays, pts, circle, images, diag)
    }

    /// The circle through the cloud with no plane first ([`fit::ransac_circle_free`]), judged
    /// as [`Self::fit_cloud`]'s is: for a cloud in which the needle's points are a minority
    /// beside glare or a jaw's metal, whose plane is not the needle's.
    fn fit_cloud_free(
        &self,
        cloud: &[Point],
        rays: &[fit::RayDiscount],
        images: &Images,
        rng: &mut ChaCha8Rng,
        diag: &mut Diagnostics,
    ) -> Result<Fitted, PerceptionError> {
        let p = &self.params;
        let (circle, inliers) = fit::ransac_circle_free(
            cloud,
            rays,
            self.needle.radius_m,
            p.share_zone_m,
            &p.ransac,
            p.free_circle_iterations,
            rng,
        )
        .ok_or_else(|| PerceptionError::BadFit {
            why: format!(
                "no {:.1} mm circle through the points",
                self.needle.radius_m * 1e3
            ),
        })?;
        // The cloud is cluttered (its plane did not hold the needle): only a circle both
        // views' masks hold is taken, not one the cloud's share test alone passes.
        let f = self.judge_cloud_circle(cloud, rays, inliers, circle, images, diag)?;
        if diag.image_support.is_none() {
            return Err(PerceptionError::BadFit {
                why: "the circle through the cloud with no plane first: the images do not hold it"
                    .into(),
            });
        }
        Ok(f)
    }

    /// The cloud's points' [`fit::RayDiscount`]s, on a rig coarser in depth than
    /// `depth_step_ref_m` at them (none where every point's step is within it).
    fn ray_discounts(&self, cloud: &[Point]) -> Vec<fit::RayDiscount> {
        if self.params.depth_step_ref_m <= 0.0 {
            return Vec::new();
        }
        let rays: Vec<fit::RayDiscount> = cloud.iter().map(|q| self.ray_discount(q)).collect();
        if rays.iter().all(|d| d.k <= 0.0) {
            return Vec::new();
        }
        rays
    }

    /// The [`fit::RayDiscount`] at `q` (robot frame): its ray's part counts for
    /// `depth_step_ref_m` over the rig's disparity step there, if that is less than one.
    fn ray_discount(&self, q: &Point) -> fit::RayDiscount {
        let c = &self.calibration;
        let eye = Point::from(c.camera_to_robot.translation.vector);
        let axis = c.camera_to_robot.rotation * Vector::z();
        let to = q - eye;
        let depth = to.dot(&axis);
        let step = depth * depth / (c.fx * c.baseline_m);
        let reference = self.params.depth_step_ref_m.max(0.0);
        let s = if step > reference {
            reference / step
        } else {
            1.0
        };
        fit::RayDiscount {
            dir: to.try_normalize(1e-12).unwrap_or(axis),
            k: 1.0 - s * s,
        }
    }

    /// A circle found in the cloud with its inliers (indices into `cloud`): held if enough
    /// of the points near it are on it, or moved onto the wire if both views' masks hold it
    /// there. Distances discounted along the rays as `rays` say.
    fn judge_cloud_circle(
        &self,
        cloud: &[Point],
        rays: &[fit::RayDiscount],
        inliers: Vec<usize>,
        circle: Circle,
        images: &Images,
        diag: &mut Diagnostics,
    ) -> Result<Fitted, PerceptionError> {
        let p = &self.params;
        let distance = |i: usize| match rays.get(i) {
            Some(d) => d.length(&circle.offset(&cloud[i])),
            None => circle.distance(&cloud[i]),
        };
        let pts: Vec<Point> = inliers.iter().map(|&i| cloud[i]).collect();
        diag.circle_inliers = pts.len();
        diag.rms_m = (inliers.iter().map(|&i| distance(i).powi(2)).sum::<f64>()
            / pts.len().max(1) as f64)
            .sqrt();
        // The share of the points near the circle that are on it: clutter beside the
        // needle (glints, a jaw's metal) counts against a fit, things farther off do not.
        let near = (0..cloud.len())
            .filter(|&i| distance(i) <= p.share_zone_m)
            .count()
            .max(pts.len());
        let share = pts.len() as f64 / near as f64;
        let arc = arc_extent(&pts, &circle).ok_or_else(|| PerceptionError::BadFit {
            why: "no arc".into(),
        })?;
        // The circle moved onto the wire in both views' masks; if the images hold it, it
        // and the arc they show replace the cloud's.
        let tried = images.refine(&circle, arc.start, arc.extent, p.image_tolerance_px);
        // A cloud that passes its own tests is trusted over a refinement that moved far
        // from it: the silhouettes of a wire seen near edge-on, or beside a jaw or the
        // thread, can hold a tilted circle as well as the right one.
        let cloud_held = pts.len() >= p.min_points && share >= p.min_inlier_share;
        let at_centre = self.ray_discount(&circle.center);
        let refined = tried.filter(|f| {
            f.support >= p.min_image_support
                && !self.edge_on(&f.circle)
                && !(cloud_held
                    && (at_centre.length(&(f.circle.center - circle.center)) > p.image_max_shift_m
                        || f.circle.normal.dot(&circle.normal).abs() < p.image_max_tilt_rad.cos()))
        });
        diag.image_support = refined.map(|f| f.support);
        let (circle, arc, share, tight) = match refined {
            Some(f) => {
                // The cloud's arc on the refined circle, or the images' if they show more
                // of it without running past a half circle (onto the thread or a jaw).
                let arc = self
                    .image_arc(images, &f, arc.extent)
                    .filter(|a| a.extent > arc.extent && a.extent <= PI + p.max_overshoot_rad)
                    .unwrap_or(fit::ArcExtent {
                        start: f.start,
                        ..arc
                    });
                (f.circle, arc, f.support, self.image_tightness(&f))
            }
            None => {
                if pts.len() < p.min_points || share < p.min_inlier_share {
                    return Err(PerceptionError::BadFit {
                        why: format!(
                            "{} of {} points near the best circle on it ({:.0} %); {}",
                            pts.len(),
                            near,
                            100.0 * share,
                            tried.map_or("the images do not show it".into(), |f| format!(
                                "both views' wire on {:.0} % of its arc (RMS {:.1} px)",
                                100.0 * f.support,
                                f.rms_px
                            ))
                        ),
                    });
                }
                let t = p.ransac.circle_threshold_m;
                (
                    circle,
                    arc,
                    share,
                    (2.0 * (t - diag.rms_m) / t).clamp(0.0, 1.0),
                )
            }
        };
        Ok(Fitted {
            circle,
            arc,
            share,
            tight,
        })
    }

    /// The circle from the silhouettes alone, for a cloud that cannot be fitted (a rig whose
    /// disparity step spans more depth than the RANSAC thresholds, clutter beside the
    /// wire): the two circles the left mask's ellipse allows, each refined against both
    /// views; the one the images hold best, if they hold it.
    fn fit_silhouettes(
        &self,
        images: &Images,
        rng: &mut ChaCha8Rng,
        diag: &mut Diagnostics,
    ) -> Option<Fitted> {
        let p = &self.params;
        let step = 1f64.to_radians();
        let f = images
            .circles_from_left_silhouette(self.needle.radius_m, rng)
            .iter()
            .filter_map(|k| {
                let (start, extent) =
                    images.left_arc(k, 2.0 * p.image_tolerance_px, step, p.image_gap_rad)?;
                let extent = extent.min(PI + p.max_overshoot_rad);
                Some((
                    images.refine(k, start, extent, p.image_tolerance_px)?,
                    extent,
                ))
            })
            .filter(|(f, _)| f.support >= p.min_image_support && !self.edge_on(&f.circle))
            .max_by(|a, b| a.0.support.total_cmp(&b.0.support))?;
        let (f, extent) = f;
        let arc = self.image_arc(images, &f, extent)?;
        diag.image_support = Some(f.support);
        diag.from_silhouettes = true;
        Some(Fitted {
            circle: f.circle,
            arc,
            share: f.support,
            tight: self.image_tightness(&f),
        })
    }

    /// Whether the camera sees the circle within `image_min_view_rad` of edge on: its
    /// silhouette is then nearly a line that many circles project onto, and the images
    /// cannot decide the fit.
    fn edge_on(&self, circle: &Circle) -> bool {
        let eye = self.calibration.camera_to_robot.translation.vector;
        let ray = (circle.center.coords - eye).normalize();
        circle.normal.dot(&ray).abs() < self.params.image_min_view_rad.sin()
    }

    /// How tightly the wire hugs a refined circle, 0 to 1: full marks within half the
    /// tolerance.
    fn image_tightness(&self, f: &Refined) -> f64 {
        let t = self.params.image_tolerance_px;
        (2.0 * (t - f.rms_px) / t).clamp(0.0, 1.0)
    }

    /// The arc the images show on a refined circle: the cloud's arc (`extent` from the
    /// refined start), followed past either end while the wire lies on the circle in both
    /// views, over gaps up to `image_gap_rad`; `None` if none of it is seen.
    fn image_arc(&self, images: &Images, f: &Refined, extent: f64) -> Option<fit::ArcExtent> {
        let p = &self.params;
        let step = 0.5f64.to_radians();
        let seen = |a: f64| images.seen_at(&f.circle, a, p.image_tolerance_px);
        let core: Vec<f64> = (0..=(extent / step) as usize)
            .map(|i| f.start + i as f64 * step)
            .filter(|&a| seen(a))
            .collect();
        let (mut lo, mut hi) = (*core.first()?, *core.last()?);
        let limit = PI + p.max_overshoot_rad + p.image_gap_rad;
        let mut angles = core;
        for dir in [-1.0, 1.0] {
            let mut a = if dir < 0.0 { lo } else { hi };
            let mut gap = 0.0;
            while gap <= p.image_gap_rad && hi - lo <= limit {
                a += dir * step;
                gap += step;
                if seen(a) {
                    angles.push(a);
                    gap = 0.0;
                    if dir < 0.0 { lo = a } else { hi = a }
                }
            }
        }
        let (e1, e2) = plane_basis(&f.circle.normal);
        let pts: Vec<Point> = angles
            .iter()
            .map(|a| f.circle.center + (e1 * a.cos() + e2 * a.sin()) * f.circle.radius)
            .collect();
        arc_extent(&pts, &f.circle)
    }

    /// The needle mask's width across the projected arc at `angle` on `circle`, pixels
    /// (`None` where the arc does not project); `right`: the masks are the right view's.
    fn width_at(&self, (masks, right): (&Masks, bool), circle: &Circle, a: f64) -> Option<f64> {
        let c = &self.calibration;
        let (e1, e2) = plane_basis(&circle.normal);
        let r = circle.radius;
        // The camera whose view the masks are: the right one of a rectified pair sits a
        // baseline along the left one's x axis.
        let shift = Vector::new(if right { c.baseline_m } else { 0.0 }, 0.0, 0.0);
        let to_cam = c.camera_to_robot.inverse();
        let p = to_cam * (circle.center + (e1 * a.cos() + e2 * a.sin()) * r) - shift;
        let q =
            to_cam * (circle.center + (e1 * (a + 1e-3).cos() + e2 * (a + 1e-3).sin()) * r) - shift;
        if p.z <= 1e-6 || q.z <= 1e-6 {
            return None;
        }
        let proj = |v: &Point| (c.fx * v.x / v.z + c.cx, c.fy * v.y / v.z + c.cy);
        let (pu, pv) = proj(&p);
        let (qu, qv) = proj(&q);
        let (tu, tv) = (qu - pu, qv - pv);
        let n = (tu * tu + tv * tv).sqrt();
        if n < 1e-9 {
            return None;
        }
        let (nu, nv) = (-tv / n, tu / n);
        let reach = 3.0 * c.fx * self.needle.wire_diameter_m / p.z + 2.0;
        let mut count = 0;
        let mut s = -reach;
        while s <= reach {
            let (x, y) = (pu + nu * s, pv + nv * s);
            if x >= 0.0 && y >= 0.0 && masks.is_needle(x as u32, y as u32) {
                count += 1;
            }
            s += 0.25;
        }
        Some(f64::from(count) * 0.25)
    }

    /// The needle mask's width across the projected arc, pixels, averaged at 0.3, 0.6 and
    /// 0.9 mm from the end at `angle` (moving by `step` rad per mm into the needle), over the
    /// same at 3 mm: `None` if the wire is not seen there.
    fn width_ratio(
        &self,
        masks: (&Masks, bool),
        circle: &Circle,
        angle: f64,
        step: f64,
    ) -> Option<f64> {
        let near: Vec<f64> = [0.3, 0.6, 0.9]
            .iter()
            .filter_map(|mm| self.width_at(masks, circle, angle + step * mm))
            .collect();
        let inner = self.width_at(masks, circle, angle + step * 3.0)?;
        if near.is_empty() || inner < 1.0 {
            return None;
        }
        Some(near.iter().sum::<f64>() / near.len() as f64 / inner)
    }

    /// How much of a tapered tip the mask lost past its observed end at `angle` (`step` rad
    /// per mm into the needle), m: the taper's width profile over the first 2 mm, fitted
    /// with a line and followed to zero width. 0 if the profile does not narrow outward;
    /// at most 2 mm.
    fn taper_lost_m(&self, masks: &Masks, circle: &Circle, angle: f64, step: f64) -> f64 {
        let masks = (masks, false);
        let Some(full) = self.width_at(masks, circle, angle + step * 3.0) else {
            return 0.0;
        };
        // (mm in from the observed end, width) where the wire is still narrowing.
        let pts: Vec<(f64, f64)> = (1..=10)
            .map(|k| f64::from(k) * 0.2)
            .filter_map(|mm| Some((mm, self.width_at(masks, circle, angle + step * mm)?)))
            .filter(|&(_, w)| w > 0.0 && w < 0.95 * full)
            .collect();
        if pts.len() < 3 {
            return 0.0;
        }
        let n = pts.len() as f64;
        let (mx, my) = (
            pts.iter().map(|p| p.0).sum::<f64>() / n,
            pts.iter().map(|p| p.1).sum::<f64>() / n,
        );
        let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
        let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
        if sxx <= 0.0 || sxy <= 0.0 {
            return 0.0;
        }
        let slope = sxy / sxx;
        // Width 0 at mm = mx − my / slope; the tip lies that far past the end if negative.
        let zero_mm = mx - my / slope;
        (-zero_mm).clamp(0.0, 2.0) * 1e-3
    }

    /// Stages 1 to 3: masks, disparity, the cloud in the robot frame; the diagnostics so far.
    fn cloud(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        region: Option<Region>,
        candidate: usize,
    ) -> Result<Option<Found>, PerceptionError> {
        let c = &self.calibration;
        let t0 = Instant::now();
        let Some((lm, rm, range)) = self.masks(left, right, None, region, candidate)? else {
            return Ok(None);
        };
        let range = self.narrowed(left, right, &lm, &rm, range);
        let t1 = Instant::now();
        let disp = self.matcher.disparity(&StereoInput {
            left,
            right,
            left_masks: &lm,
            right_masks: &rm,
            min_disparity: range[0],
            max_disparity: range[1],
            segmenter: self.segmenter.as_ref(),
            parallel: self.parallel,
        })?;
        let t2 = Instant::now();
        let cloud = point_cloud(&disp, &lm, c, self.params.max_points);
        let t3 = Instant::now();
        let diag = Diagnostics {
            rois: [lm.roi, rm.roi],
            disparity_range: range,
            needle_px: lm.needle_count(),
            cloud_points: cloud.len(),
            plane_inliers: 0,
            circle_inliers: 0,
            rms_m: 0.0,
            arc_rad: 0.0,
            thread_px: [0, 0],
            taper: [None, None],
            image_support: None,
            from_silhouettes: false,
            free_circle: false,
            times: StageTimes {
                segment: t1 - t0,
                disparity: t2 - t1,
                cloud: t3 - t2,
                fit: Duration::ZERO,
            },
        };
        Ok(Some((lm, rm, cloud, diag)))
    }

    /// The pose of a needle lodged in tissue through known holes: the circle of the needle's
    /// radius through the entry and exit (one free angle about their chord; the needle
    /// dips under the tissue between them) that the visible points fit best, refined with
    /// the holes as soft constraints; the tip is the farthest point seen past the exit.
    /// Checks and failures as [`Self::estimate`]'s.
    pub fn estimate_in_tissue(
        &self,
        left: &stitch_robot::RgbImage,
        right: &stitch_robot::RgbImage,
        holes: &TissueHint,
        seed: u64,
    ) -> Result<PipelineOutput, PerceptionError> {
        let c = &self.calibration;
        let p = &self.params;
        check_image(left, c.width, c.height, "left")?;
        check_image(right, c.width, c.height, "right")?;
        let (e, x) = (holes.entry, holes.exit);
        let mid = Point::from((e.coords + x.coords) / 2.0);
        let region = Region {
            whole: true,
            ..self.region_near(&mid)
        };
        let (_, rm, cloud, mut diag) = self.cloud(left, right, Some(region), 0)?.ok_or(no_left())?;
        // Wire one view sees and the other does not (a jaw just opened off the needle hides it
        // from the right camera) gets disparities matched to whatever lies there: kept only
        // points whose match in the right view is needle too.
        let to_camera = self.calibration.camera_to_robot.inverse();
        let cloud: Vec<Point> = cloud
            .into_iter()
            .filter(|q| self.needle_in_right(&rm, &(to_camera * q)))
            .collect();
        diag.cloud_points = cloud.len();
        let t3 = Instant::now();
        if cloud.len() < p.min_points_in_tissue {
            return Err(PerceptionError::TooFewPoints {
                found: cloud.len(),
                needed: p.min_points_in_tissue,
            });
        }
        let r = self.needle.radius_m;
        let chord = x - e;
        let half = chord.norm() / 2.0;
        if !(half > 1e-4 && half < r) {
            return Err(PerceptionError::Config {
                message: format!(
                    "entry and exit {:.1} mm apart: a {:.1} mm needle cannot pass through both",
                    2.0 * half * 1e3,
                    r * 1e3
                ),
            });
        }
        let u = chord / (2.0 * half);
        let rho = (r * r - half * half).sqrt();
        let (a, b) = plane_basis(&u);
        let t = p.ransac.circle_threshold_m;
        let circle_at = |phi: f64| {
            let center = mid + (a * phi.cos() + b * phi.sin()) * rho;
            let normal = (e - center).cross(&(x - center)).normalize();
            Circle {
                center,
                normal,
                radius: r,
            }
        };
        // First the free fit (the holes are where the plan aimed, up to the insertion's
        // error of a few millimetres); then, if too little is seen for it, the circle
        // through the holes that the points fit best, the holes as soft constraints.
        let mut rng = ChaCha8Rng::seed_from_u64(seed);
        let free = fit::ransac_plane(&cloud, &[], &p.ransac, &mut rng).and_then(|(plane, on)| {
            let pts: Vec<Point> = on.iter().map(|&i| cloud[i]).collect();
            fit::ransac_circle(&pts, &[], &plane, r, &p.ransac, &mut rng)
                .map(|(c, inl)| (c, inl.iter().map(|&i| pts[i]).collect::<Vec<_>>()))
        });
        let enough = |n: usize| {
            n >= p.min_points_in_tissue && n as f64 >= p.min_inlier_share * cloud.len() as f64
        };
        // A circle fitted with no regard to the holes may be another needle's, or one not in
        // the tissue at all (still hanging where a jaw left it): it must pass both holes.
        let free = free.filter(|(c, _)| {
            c.distance(&e) <= p.max_hole_miss_m && c.distance(&x) <= p.max_hole_miss_m
        });
        let (circle, inliers) = match free {
            Some((c, inl)) if enough(inl.len()) => (c, inl),
            _ => {
                let mut best: Option<(usize, f64, f64)> = None;
                for k in 0..720 {
                    let phi = f64::from(k) * PI / 360.0;
                    let circle = circle_at(phi);
                    // The needle dips under the tissue between the holes: its centre is
                    // above them.
                    if circle.center.z < mid.z {
                        continue;
                    }
                    let (n, sum) = cloud.iter().fold((0usize, 0.0), |(n, sum), q| {
                        let d = circle.distance(q);
                        if d <= t { (n + 1, sum + d) } else { (n, sum) }
                    });
                    if best.is_none_or(|(bn, bs, _)| n > bn || (n == bn && sum < bs)) {
                        best = Some((n, sum, phi));
                    }
                }
                let (_, _, phi) = best.ok_or_else(|| PerceptionError::BadFit {
                    why: "no circle through the holes".into(),
                })?;
                let circle = circle_at(phi);
                let inliers: Vec<Point> = cloud
                    .iter()
                    .copied()
                    .filter(|q| circle.distance(q) <= t)
                    .collect();
                if !enough(inliers.len()) {
                    return Err(PerceptionError::BadFit {
                        why: format!(
                            "{} of {} points on the best circle near the holes",
                            inliers.len(),
                            cloud.len()
                        ),
                    });
                }
                let mut with_holes = inliers.clone();
                for _ in 0..5 {
                    with_holes.push(e);
                    with_holes.push(x);
                }
                (fit::refine_circle(&with_holes, &[], circle, 8), inliers)
            }
        };
        let share = inliers.len() as f64 / cloud.len() as f64;
        diag.circle_inliers = inliers.len();
        diag.rms_m = (inliers
            .iter()
            .map(|q| circle.distance(q).powi(2))
            .sum::<f64>()
            / inliers.len() as f64)
            .sqrt();
        // Angles about the circle; the needle runs from the entry to the exit the short way.
        let (e1, e2) = plane_basis(&circle.normal);
        let angle = |q: &Point| {
            let d = q - circle.center;
            d.dot(&e2).atan2(d.dot(&e1))
        };
        let wrap = |v: f64| (v + PI).rem_euclid(2.0 * PI) - PI;
        let (ae, ax) = (angle(&e), angle(&x));
        let dir = wrap(ax - ae).signum();
        let span = wrap(ax - ae).abs();
        // Past the exit (the tip's side) and before the entry (the swage's side).
        let past_exit = inliers
            .iter()
            .map(|q| dir * wrap(angle(q) - ax))
            .filter(|&v| v > 0.0 && v < PI - span)
            .fold(0.0f64, f64::max);
        let before_entry = inliers
            .iter()
            .map(|q| -dir * wrap(angle(q) - ae))
            .filter(|&v| v > 0.0 && v < PI - span)
            .fold(0.0f64, f64::max);
        diag.arc_rad = past_exit + span + before_entry;
        let min_seen = p.min_tip_seen_m / r;
        let (tip_angle, swage_angle) = if past_exit >= min_seen {
            let tip = ax + dir * past_exit;
            (tip, tip - dir * PI)
        } else if before_entry >= min_seen {
            let swage = ae - dir * before_entry;
            (swage + dir * PI, swage)
        } else {
            return Err(PerceptionError::BadFit {
                why: format!(
                    "under {:.0} mm of the needle seen past either hole",
                    p.min_tip_seen_m * 1e3
                ),
            });
        };
        let z = if swage_angle > tip_angle {
            circle.normal
        } else {
            -circle.normal
        };
        let tip = circle.center + (e1 * tip_angle.cos() + e2 * tip_angle.sin()) * r;
        let xa = (tip - circle.center).normalize();
        let ya = z.cross(&xa);
        let rot = Rotation3::from_matrix_unchecked(Matrix3::from_columns(&[xa, ya, z]));
        let pose = Pose::from_parts(
            nalgebra::Translation3::from(circle.center.coords),
            UnitQuaternion::from_rotation_matrix(&rot),
        );
        let tight = (2.0 * (t - diag.rms_m) / t).clamp(0.0, 1.0);
        let confidence = (share.sqrt() * tight).clamp(0.0, 1.0);
        diag.times.fit = t3.elapsed();
        if confidence < p.min_confidence {
            return Err(PerceptionError::Uncertain { confidence });
        }
        Ok(PipelineOutput {
            pose,
            confidence,
            diagnostics: diag,
        })
    }

    /// Whether the right view's needle mask holds camera-frame point `q` (within a pixel
    /// along its row).
    fn needle_in_right(&self, rm: &Masks, q: &Point) -> bool {
        let c = &self.calibration;
        if q.z <= 1e-6 {
            return false;
        }
        let ur = c.fx * (q.x - c.baseline_m) / q.z + c.cx;
        let v = c.fy * q.y / q.z + c.cy;
        if ur < 1.0 || v < 0.0 {
            return false;
        }
        let (x, y) = (ur.floor() as u32, v.floor() as u32);
        (x - 1..=x + 1).any(|x| rm.is_needle(x, y))
    }

    /// The share of the left image's pixels within `swage_search_m` of a robot-frame point
    /// that are dark grey ([`dark_grey_share`]); 0 if it is not in view.
    fn instrument_share(&self, left: &stitch_robot::RgbImage, p: &Point) -> f64 {
        let Some(([u, v], rad)) = self.left_disc(p, self.params.swage_search_m, 2.0) else {
            return 0.0;
        };
        dark_grey_share(left, u, v, rad)
    }

    /// Where a robot-frame point falls in the left view (pixels), and how many pixels a
    /// distance of `radius_m` spans there (at least `least_px`); `None` if it is not in view.
    fn left_disc(&self, p: &Point, radius_m: f64, least_px: f64) -> Option<([f64; 2], f64)> {
        let c = &self.calibration;
        let uv = c.left_pixel(p)?;
        let z = (c.camera_to_robot.inverse() * p).z;
        Some((uv, (c.fx * radius_m / z).max(least_px)))
    }

    /// Whether the wire seen to end at `end` (rad on `circle`) runs into an instrument: past
    /// it along the circle (`outward` +1 or −1, the direction of increasing or decreasing
    /// angle), at two or more of 0.5, 1 and 1.5 mm, half or more of the left image's pixels
    /// within a wire's width are dark grey ([`dark_grey_share`]). A tool beside an end that
    /// the wire passes clear of does not hide it.
    fn runs_into_tool(
        &self,
        left: &stitch_robot::RgbImage,
        circle: &Circle,
        end: f64,
        outward: f64,
    ) -> bool {
        let (e1, e2) = plane_basis(&circle.normal);
        let r = circle.radius;
        let dark = [0.5e-3, 1.0e-3, 1.5e-3]
            .iter()
            .filter(|&&m| {
                let a = end + outward * m / r;
                let q = circle.center + (e1 * a.cos() + e2 * a.sin()) * r;
                self.left_disc(&q, self.needle.wire_diameter_m, 1.5)
                    .is_some_and(|([u, v], rad)| dark_grey_share(left, u, v, rad) >= 0.5)
            })
            .count();
        dark >= 2
    }

    /// Thread pixels in the left view within `swage_search_m` of a robot-frame end of the
    /// wire, on its `outward` side (the direction past the end along the circle); of all the
    /// thread there, or only of the pieces that do not pass by ([`Strands`]).
    fn thread_near(&self, masks: &Masks, p: &Point, outward: &Vector, strands: Strands) -> usize {
        let (Some(([u, v], rad)), Some([ou, ov])) = (
            self.left_disc(p, self.params.swage_search_m, 2.0),
            self.calibration
                .left_pixel(&(p + outward * self.params.swage_search_m)),
        ) else {
            return 0;
        };
        // The thread leaves the swage from its end: pixels more than a fifth of the radius
        // back along the wire are a thread lying across the needle, not leaving it.
        let len = (ou - u).hypot(ov - v).max(1e-9);
        let (du, dv) = ((ou - u) / len, (ov - v) / len);
        let disc = Disc::new(u, v, rad, &masks.roi);
        let passing = match strands {
            Strands::All => None,
            Strands::Leaving => Some(disc.passing_pieces(masks)),
        };
        let mut n = 0;
        for y in disc.y0..=disc.y1 {
            for x in disc.x0..=disc.x1 {
                let (dx, dy) = (x as f64 + 0.5 - u, y as f64 + 0.5 - v);
                if dx * dx + dy * dy <= rad * rad
                    && dx * du + dy * dv >= -0.2 * rad
                    && masks.is_thread(x, y)
                    && passing.as_ref().is_none_or(|m| !m[disc.index(x, y)])
                {
                    n += 1;
                }
            }
        }
        n
    }
}

/// The share of `image`'s pixels within `rad` of `(u, v)` that are dark and grey (the
/// brightest channel under 90 of 255, the channels within 35 % of it): an instrument's
/// black shaft and steel fingers in shade; not tissue or its shadows (red), the thread
/// (violet) or the needle (bright). 0 if none of the disc is in the image.
fn dark_grey_share(image: &stitch_robot::RgbImage, u: f64, v: f64, rad: f64) -> f64 {
    if image.width == 0 || image.height == 0 || !(u.is_finite() && v.is_finite()) {
        return 0.0;
    }
    let clip = |c: f64, n: u32| (c.max(0.0) as u32).min(n - 1);
    let (x0, x1) = (clip(u - rad, image.width), clip(u + rad, image.width));
    let (y0, y1) = (clip(v - rad, image.height), clip(v + rad, image.height));
    let (mut all, mut dark) = (0usize, 0usize);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (dx, dy) = (x as f64 + 0.5 - u, y as f64 + 0.5 - v);
            if dx * dx + dy * dy > rad * rad {
                continue;
            }
            let i = (y as usize * image.width as usize + x as usize) * 3;
            let Some(px) = image.data.get(i..i + 3) else {
                continue;
            };
            let (hi, lo) = (px.iter().max().copied(), px.iter().min().copied());
            let (hi, lo) = (f64::from(hi.unwrap_or(0)), f64::from(lo.unwrap_or(0)));
            all += 1;
            if hi < 90.0 && hi - lo <= 0.35 * hi {
                dark += 1;
            }
        }
    }
    dark as f64 / all.max(1) as f64
}

/// Which thread [`NeedlePipeline::thread_near`] counts near an end of the wire.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Strands {
    /// Every thread pixel.
    All,
    /// Only pieces that could be the thread leaving the swage: not a strand that passes
    /// by the end (in the disc at one side of its rim and out at another).
    Leaving,
}

/// The pixels within `rad` of `(u, v)` in the image, and the box round them inside a mask
/// region (no pixel outside it is thread), for [`NeedlePipeline::thread_near`].
struct Disc {
    u: f64,
    v: f64,
    rad: f64,
    x0: u32,
    x1: u32,
    y0: u32,
    y1: u32,
}

impl Disc {
    /// The disc's box cut to `roi` (empty, `x1 < x0` or `y1 < y0`, if they do not meet).
    fn new(u: f64, v: f64, rad: f64, roi: &Rect) -> Self {
        let lo = |c: f64, r0: u32| ((c - rad).floor().max(0.0) as u32).max(r0);
        let hi = |c: f64, r1: u32| ((c + rad).ceil().max(0.0) as u32).min(r1.saturating_sub(1));
        Self {
            u,
            v,
            rad,
            x0: lo(u, roi.x0),
            x1: hi(u, roi.x1),
            y0: lo(v, roi.y0),
            y1: hi(v, roi.y1),
        }
    }

    fn width(&self) -> usize {
        (self.x1 + 1).saturating_sub(self.x0) as usize
    }

    fn height(&self) -> usize {
        (self.y1 + 1).saturating_sub(self.y0) as usize
    }

    /// Index of an image pixel inside the box, row by row.
    fn index(&self, x: u32, y: u32) -> usize {
        (y - self.y0) as usize * self.width() + (x - self.x0) as usize
    }

    fn contains(&self, x: u32, y: u32) -> bool {
        let (dx, dy) = (x as f64 + 0.5 - self.u, y as f64 + 0.5 - self.v);
        (self.x0..=self.x1).contains(&x)
            && (self.y0..=self.y1).contains(&y)
            && dx * dx + dy * dy <= self.rad * self.rad
    }

    /// For each pixel of the box, whether it is thread on a strand passing by: an
    /// 8-connected piece of the thread inside the disc that meets the disc's rim in two or
    /// more places. The thread leaving the swage at the centre meets it once; a strand
    /// passing the end goes in and out again. (A strand that leaves the swage and comes back
    /// within the disc counts as passing too, which is why it is asked only when the cues
    /// disagree.) A flood fill written here: the labelling crates (imageproc's connected
    /// components) bridge no gaps, and the disc is a few hundred pixels.
    fn passing_pieces(&self, masks: &Masks) -> Vec<bool> {
        const GAP: i32 = 3;
        let (w, h) = (self.width(), self.height());
        let thread = |x: u32, y: u32| self.contains(x, y) && masks.is_thread(x, y);
        // The pieces, labelled 1.. by a flood fill.
        let mut label = vec![0u32; w * h];
        let mut pieces = 0;
        let mut stack = Vec::new();
        for y in self.y0..=self.y1 {
            for x in self.x0..=self.x1 {
                if label[self.index(x, y)] != 0 || !thread(x, y) {
                    continue;
                }
                pieces += 1;
                label[self.index(x, y)] = pieces;
                stack.push((x, y));
                while let Some((cx, cy)) = stack.pop() {
                    for (ox, oy) in (-GAP..=GAP).flat_map(|oy| (-GAP..=GAP).map(move |ox| (ox, oy)))
                    {
                        let (Some(nx), Some(ny)) =
                            (cx.checked_add_signed(ox), cy.checked_add_signed(oy))
                        else {
                            continue;
                        };
                        if thread(nx, ny) && label[self.index(nx, ny)] == 0 {
                            label[self.index(nx, ny)] = pieces;
                            stack.push((nx, ny));
                        }
                    }
                }
            }
        }
        // Each piece's runs along the rim, sampled about a pixel apart just inside it. (Where
        // the disc reaches past the masks' region, a strand running out of the region is
        // not known to cross the rim there: the region may end at the image's edge, with the
        // swage just beyond it.)
        let ring = (self.rad - 1.0).max(0.5);
        let n = (2.0 * PI * ring).ceil().max(8.0) as usize;
        let on_rim: Vec<u32> = (0..n)
            .map(|k| {
                let a = 2.0 * PI * k as f64 / n as f64;
                let (x, y) = (self.u + ring * a.cos(), self.v + ring * a.sin());
                if x < 0.0 || y < 0.0 || !self.contains(x as u32, y as u32) {
                    0
                } else {
                    label[self.index(x as u32, y as u32)]
                }
            })
            .collect();
        // A run goes on across gaps of up to `GAP` samples (a ragged mask's crossing is one).
        let hits: Vec<(usize, u32)> = on_rim
            .iter()
            .enumerate()
            .filter(|&(_, &l)| l != 0)
            .map(|(k, &l)| (k, l))
            .collect();
        let mut runs = vec![0u32; pieces as usize + 1];
        for (i, &(k, l)) in hits.iter().enumerate() {
            let (pk, pl) = hits[(i + hits.len() - 1) % hits.len()];
            let gap = (k + n - pk - 1) % n;
            if hits.len() == 1 || pl != l || gap > GAP as usize {
                runs[l as usize] += 1;
            }
        }
        label
            .iter()
            .map(|&l| l != 0 && runs[l as usize] >= 2)
            .collect()
    }
}

/// How much to trust a fit, 0 to 1: the product of the share of points on the circle (or of
/// the arc the images hold), how much of the half circle is seen (full marks from half of
/// it), how tightly the points or the wire hug the circle (`tight`: full marks within half
/// the threshold), and 0.9 if an end is hidden.
fn confidence(arc: &fit::ArcExtent, inlier_share: f64, tight: f64, full: bool) -> f64 {
    let observed = ((arc.extent - arc.largest_inner_gap) / PI).clamp(0.0, 1.0);
    let coverage = (observed / 0.5).min(1.0);
    let both_ends = if full { 1.0 } else { 0.9 };
    (inlier_share.clamp(0.0, 1.0).sqrt() * coverage * tight * both_ends).clamp(0.0, 1.0)
}

fn no_left() -> PerceptionError {
    PerceptionError::NoMask {
        view: "left".into(),
    }
}

/// The needle's points in the robot frame: every left-image pixel that is needle and has a
/// disparity, back-projected through the calibration; evenly subsampled to at most `max`.
pub fn point_cloud(
    disp: &DisparityMap,
    masks: &Masks,
    c: &StereoCalibration,
    max: usize,
) -> Vec<Point> {
    let mut pts = Vec::new();
    let r = disp.roi;
    for y in r.y0..r.y1 {
        for x in r.x0..r.x1 {
            let Some(d) = disp.at(x, y) else { continue };
            if d <= 0.0 || !masks.is_needle(x, y) {
                continue;
            }
            let z = c.fx * c.baseline_m / f64::from(d);
            let xc = (f64::from(x) + 0.5 - c.cx) * z / c.fx;
            let yc = (f64::from(y) + 0.5 - c.cy) * z / c.fy;
            pts.push(Point::new(xc, yc, z));
        }
    }
    if pts.len() > max && max > 0 {
        let step = pts.len() as f64 / max as f64;
        pts = (0..max).map(|i| pts[(i as f64 * step) as usize]).collect();
    }
    pts.iter().map(|p| c.camera_to_robot * p).collect()
}

/// Where in the right view of a rectified pair the points of the left view's region `l` can
/// appear at disparities `range`: its rows, shifted left by them (at least a column wide).
fn right_band(l: &Rect, range: [u32; 2]) -> Rect {
    let x0 = l.x0.saturating_sub(range[1]);
    Rect {
        x0,
        x1: l.x1.saturating_sub(range[0]).max(x0 + 1),
        ..*l
    }
}

/// Whether the observed arc's low end is the tip, from the cues at its two ends (low end
/// first): thread pixels near each, the wire's width near each against 3 mm in, and the
/// jaw's say (`jaw_score`: positive if a known jaw puts the tip at the low end, negative if
/// at the high end, 0 if it has none). `None` when they cannot tell.
///
/// A known jaw decides. Otherwise two cues count alike: the thread, which leaves at the
/// swage, when it marks one end (at least `min_thread_px` there and `swage_ratio` times the
/// other's); and the taper — the end whose wire narrows more towards it is the tip, or with
/// one end measured, a tapered end is the tip and a thick one the swage. Either alone
/// decides; when they contradict each other the answer is `None` (a wrong end is a pose
/// 24 mm off; a typed failure lets the robot look again).
pub fn tip_is_low_end(
    threads: [usize; 2],
    taper: [Option<f64>; 2],
    jaw_score: i32,
    p: &PipelineParams,
) -> Option<bool> {
    if jaw_score != 0 {
        return Some(jaw_score > 0);
    }
    let by_thread = |i: usize| {
        threads[i] >= p.min_thread_px && threads[i] as f64 >= p.swage_ratio * threads[1 - i] as f64
    };
    let thread = i32::from(by_thread(1)) - i32::from(by_thread(0));
    let taper = match taper {
        [Some(lo), Some(hi)] if hi - lo > p.taper_difference => 1,
        [Some(lo), Some(hi)] if lo - hi > p.taper_difference => -1,
        [Some(lo), None] if lo < p.tip_taper_ratio => 1,
        [Some(lo), None] if lo > p.swage_taper_ratio => -1,
        [None, Some(hi)] if hi < p.tip_taper_ratio => -1,
        [None, Some(hi)] if hi > p.swage_taper_ratio => 1,
        _ => 0,
    };
    match thread + taper {
        0 => None,
        s => Some(s > 0),
    }
}

/// Which observed end of the arc places the half circle.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Anchor {
    /// The swage's end is seen whole: the swage's centre lies a cap's width inside it.
    Swage,
    /// Only the tip's end is: the tip lies `lost_rad` past it (the taper's last part, too
    /// thin for the image), rad along the circle.
    Tip {
        /// How far past the observed end the tip lies, rad.
        lost_rad: f64,
    },
}

/// The tip's and the swage's angles on the fitted circle (in its `plane_basis`) from the
/// arc observed over `[start, start + extent]` (rad): the needle is a half circle, so its
/// ends lie π apart whatever the image shows of the thin tip, and the observed arc only says
/// where the half circle sits, through the end `anchor` names. `tip_is_lo`: the tip is at
/// the observed arc's low end. `swage_cap_rad`: how far the swage's rounded end reaches
/// past its centre, rad.
pub fn half_circle_ends(
    start: f64,
    extent: f64,
    tip_is_lo: bool,
    anchor: Anchor,
    swage_cap_rad: f64,
) -> (f64, f64) {
    let (lo, hi) = (start, start + extent);
    // From the tip towards the swage along the circle: +1 if the tip is the low end.
    let along = if tip_is_lo { 1.0 } else { -1.0 };
    match anchor {
        Anchor::Swage => {
            let swage = if tip_is_lo { hi } else { lo } - along * swage_cap_rad;
            (swage - along * PI, swage)
        }
        Anchor::Tip { lost_rad } => {
            let tip = if tip_is_lo { lo } else { hi } - along * lost_rad.max(0.0);
            (tip, tip + along * PI)
        }
    }
}

/// The pipeline behind [`NeedleEstimator`]: captures a pair from a camera and estimates.
#[derive(Debug)]
pub struct PipelineEstimator<C> {
    camera: C,
    pipeline: NeedlePipeline,
    estimates: u64,
    seed: u64,
}

impl<C: StereoCamera + std::fmt::Debug> PipelineEstimator<C> {
    /// An estimator over `camera`; RANSAC draws are seeded from `seed` and a counter.
    pub fn new(camera: C, pipeline: NeedlePipeline, seed: u64) -> Self {
        Self {
            camera,
            pipeline,
            estimates: 0,
            seed,
        }
    }

    /// The camera.
    pub fn camera(&self) -> &C {
        &self.camera
    }
}

impl<C: StereoCamera + std::fmt::Debug> NeedleEstimator for PipelineEstimator<C> {
    fn estimate_needle(&mut self) -> Result<NeedleEstimate, PerceptionError> {
        self.estimate_needle_with(None)
    }

    fn estimate_needle_with(
        &mut self,
        hint: Option<&NeedleHint>,
    ) -> Result<NeedleEstimate, PerceptionError> {
        let StereoFrame { stamp, left, right } =
            self.camera.capture().map_err(|e| PerceptionError::Camera {
                message: e.to_string(),
            })?;
        self.estimates += 1;
        let seed = self
            .seed
            .wrapping_mul(0x9E37_79B9)
            .wrapping_add(self.estimates);
        let out = match hint {
            Some(NeedleHint::InTissue(holes)) => self
                .pipeline
                .estimate_in_tissue(&left, &right, holes, seed)?,
            Some(NeedleHint::Held(jaw)) => {
                self.pipeline.estimate(&left, &right, Some(jaw), seed)?
            }
            None => self.pipeline.estimate(&left, &right, None, seed)?,
        };
        Ok(NeedleEstimate {
            pose: out.pose,
            confidence: out.confidence,
            stamp,
        })
    }

    fn trace_thread(
        &mut self,
        hint: &crate::ThreadHint,
    ) -> Result<crate::ThreadTrace, PerceptionError> {
        let StereoFrame { left, right, .. } =
            self.camera.capture().map_err(|e| PerceptionError::Camera {
                message: e.to_string(),
            })?;
        crate::thread::trace(
            &crate::ThreadParams::default(),
            &*self.pipeline.segmenter,
            &self.pipeline.calibration,
            &left,
            &right,
            hint,
        )
    }
}

/// Helper for tests and benches: the error between an estimate and the truth.
#[derive(Clone, Copy, Debug, PartialEq, Serialize)]
pub struct PoseError {
    /// Centre distance, m.
    pub center_m: f64,
    /// Tip distance, m.
    pub tip_m: f64,
    /// Swage distance, m.
    pub swage_m: f64,
    /// Angle between the normals, rad.
    pub normal_rad: f64,
}

impl PoseError {
    /// Compare `estimate` with `truth` for `needle`.
    pub fn between(needle: &Needle, estimate: &Pose, truth: &Pose) -> Self {
        let (a, b) = (needle.in_world(estimate), needle.in_world(truth));
        Self {
            center_m: (a.center - b.center).norm(),
            tip_m: (a.tip - b.tip).norm(),
            swage_m: (a.swage - b.swage).norm(),
            normal_rad: a.normal.angle(&b.normal),
        }
    }

    /// The larger endpoint error, m.
    pub fn endpoints_m(&self) -> f64 {
        self.tip_m.max(self.swage_m)
    }
}

/// The segmenter's places for the needle, and after them the likeliest joined with each
/// other place beside it (a gap no more than twice the larger's longer side): the thread
/// lying along the needle, or a jaw across it, can cut its mask in two, each piece
/// ranked a place of its own with too short an arc to fit. The joined places are tried only
/// after the pieces.
fn joined(mut places: Vec<Rect>) -> Vec<Rect> {
    let Some(&a) = places.first() else {
        return places;
    };
    let side = |r: &Rect| r.width().max(r.height());
    let gap = |lo0: u32, hi0: u32, lo1: u32, hi1: u32| {
        lo1.saturating_sub(hi0).max(lo0.saturating_sub(hi1))
    };
    let extra: Vec<Rect> = places[1..]
        .iter()
        .filter(|b| {
            let g = gap(a.x0, a.x1, b.x0, b.x1).max(gap(a.y0, a.y1, b.y0, b.y1));
            g > 0 && g <= 2 * side(&a).max(side(b))
        })
        .map(|b| Rect {
            x0: a.x0.min(b.x0),
            y0: a.y0.min(b.y0),
            x1: a.x1.max(b.x1),
            y1: a.y1.max(b.y1),
        })
        .collect();
    places.extend(extra);
    places
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rect(x0: u32, y0: u32, x1: u32, y1: u32) -> Rect {
        Rect { x0, y0, x1, y1 }
    }

    /// Masks over `roi` with thread at `thread`'s pixels.
    fn thread_masks(roi: Rect, thread: impl Fn(u32, u32) -> bool) -> Masks {
        let mut m = Masks {
            roi,
            needle: vec![0; (roi.width() * roi.height()) as usize],
            thread: vec![0; (roi.width() * roi.height()) as usize],
        };
        for y in roi.y0..roi.y1 {
            for x in roi.x0..roi.x1 {
                m.thread[((y - roi.y0) * roi.width() + (x - roi.x0)) as usize] =
                    u8::from(thread(x, y));
            }
        }
        m
    }

    /// Thread pixels within 20 px of (100.5, 100.5) on strands passing by.
    fn passing(m: &Masks) -> usize {
        let d = Disc::new(100.5, 100.5, 20.0, &m.roi);
        d.passing_pieces(m).iter().filter(|&&p| p).count()
    }

    #[test]
    fn a_strand_passing_an_end_is_told_from_one_leaving_it() {
        let roi = rect(0, 0, 200, 200);
        let disc = Disc::new(100.5, 100.5, 20.0, &roi);
        let in_disc = |f: &dyn Fn(u32, u32) -> bool| {
            (0..200)
                .flat_map(|x| (0..200).map(move |y| (x, y)))
                .filter(|&(x, y)| f(x, y) && disc.contains(x, y))
                .count()
        };
        // The thread leaving the end: a strand from the centre out past the rim.
        let leaving = |x: u32, y: u32| (100..=101).contains(&y) && x >= 100;
        assert_eq!(passing(&thread_masks(roi, leaving)), 0);
        // A strand passing 10 px from the end, broken every 5 px by gaps of 2 (a thin
        // thread's mask is ragged): one strand, in and out again, all of it set aside.
        let by = |x: u32, y: u32| (110..=111).contains(&y) && x % 5 < 3;
        assert!(in_disc(&by) > 0);
        assert_eq!(passing(&thread_masks(roi, by)), in_disc(&by));
        // Both: only the passing strand's pixels are set aside.
        let both = |x: u32, y: u32| leaving(x, y) || by(x, y);
        assert_eq!(passing(&thread_masks(roi, both)), in_disc(&by));
        // A strand 8 px beside the end, across the disc: passing. Where the masks' region
        // (here the image) ends inside the disc 10 px below the end, the same strand runs
        // out of sight there: not known to pass (the swage may lie just beyond the edge).
        let down = |x: u32, _: u32| (108..=109).contains(&x);
        assert!(passing(&thread_masks(roi, down)) > 0);
        assert_eq!(passing(&thread_masks(rect(0, 0, 200, 110), down)), 0);
        // A stub that ends inside the disc without reaching the rim is not passing.
        let stub = |x: u32, y: u32| y == 95 && (90..110).contains(&x);
        assert_eq!(passing(&thread_masks(roi, stub)), 0);
    }

    #[test]
    fn an_instruments_dark_steel_is_told_from_tissue_and_its_shadows() {
        // Red tissue, its shadow (dark red), a black shaft over the right half.
        let mut image = stitch_robot::RgbImage::new(100, 100);
        for y in 0..100u32 {
            for x in 0..100u32 {
                let px = match (x, y) {
                    (50.., _) => [30, 32, 35],
                    (_, 50..) => [70, 20, 22],
                    _ => [180, 70, 70],
                };
                let i = (y as usize * 100 + x as usize) * 3;
                image.data[i..i + 3].copy_from_slice(&px);
            }
        }
        // Round a point on the shaft's edge, half the disc is the shaft.
        let s = dark_grey_share(&image, 50.0, 25.0, 10.0);
        assert!((s - 0.5).abs() < 0.06, "{s}");
        // Tissue and its shadow alone: none.
        assert!(dark_grey_share(&image, 20.0, 50.0, 10.0) < 1e-12);
        // On the shaft: all; off the image: none, never a panic.
        assert!(dark_grey_share(&image, 80.0, 80.0, 5.0) > 1.0 - 1e-12);
        assert!(dark_grey_share(&image, -500.0, 20.0, 10.0) < 1e-12);
        assert!(dark_grey_share(&image, f64::NAN, 20.0, 10.0) < 1e-12);
    }

    #[test]
    fn pieces_beside_the_likeliest_place_are_joined_after_the_places() {
        // The needle cut in two by the thread (seed 2's independent pair 123): two places
        // 63 px apart, the first 150 px wide.
        let a = rect(243, 426, 393, 549);
        let b = rect(456, 396, 552, 549);
        let far = rect(900, 100, 1000, 200);
        assert_eq!(
            joined(vec![a, b, far]),
            vec![a, b, far, rect(243, 396, 552, 549)]
        );
        // A needle cut by a jaw (as in seed 2's independent pairs 83, 115 and 182): pieces
        // farther apart than half the larger's side, up to twice that side.
        let tip = rect(600, 300, 660, 340);
        let swage = rect(640, 440, 700, 470);
        let beyond = rect(840, 300, 880, 340);
        assert_eq!(
            joined(vec![tip, swage, beyond]),
            vec![tip, swage, beyond, rect(600, 300, 700, 470)]
        );
        // Overlapping places are one place drawn twice, not pieces; nothing is added.
        let c = rect(300, 500, 420, 600);
        assert_eq!(joined(vec![a, c]), vec![a, c]);
        // Nor for a single place, or none.
        assert_eq!(joined(vec![a]), vec![a]);
        assert_eq!(joined(Vec::new()), Vec::<Rect>::new());
    }
}
