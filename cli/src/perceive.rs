//! `stitch perceive …` and `stitch bench perception`: the stereo pipeline on a lab's own
//! images, on rendered pairs, and its latency and accuracy tables.

use anyhow::Context;
use clap::{Subcommand, ValueEnum};
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};
use stitch_cli::inputs::{self, CalibrationFile};
use stitch_eval::own as evaluate;
use stitch_eval::{Accuracy, FrameResult, failure_kind, percentile};
use stitch_perception::{
    JawHint, LeftRight, MaskRowMatcher, NeedleEnd, NeedlePipeline, PerceptionError, Rect,
    SemiGlobalMatcher, SgmPaths, StereoMatcher, TissueHint,
};
use stitch_robot::{Needle, Pose, RgbImage, StereoCalibration};
use stitch_sim::{CameraConfig, MockDvrk, SceneConfig, StereoRenderer, Streams};

use crate::segmenter::SegmenterChoice;

/// Exit code of `perceive needle` when the pipeline gives a typed failure instead of a pose.
pub const NO_ESTIMATE: u8 = 6;

#[derive(Debug, Subcommand)]
pub enum PerceiveCommand {
    /// Trace the thread in a rectified stereo pair, from the exit point (--start) to the
    /// needle's swage (--swage); print the trace as JSON (points, their uncertainty, length,
    /// hidden stretches), or the typed failure (exit code 6).
    Thread(crate::perceive_thread::ThreadArgs),
    /// Estimate the needle pose from a rectified stereo pair; print it as JSON, or the
    /// typed failure (exit code 6).
    Needle {
        /// Left image (PNG, 8-bit RGB or grey).
        left: PathBuf,
        /// Right image.
        right: PathBuf,
        /// The stereo calibration (TOML; see docs/perception.md).
        #[arg(long)]
        calib: PathBuf,
        /// The holding jaw's tool-tip position, robot frame, metres: x,y,z. The pipeline
        /// then searches around it and takes the end nearer it to be --holds.
        #[arg(long, value_parser = parse_point, allow_hyphen_values = true, requires = "holds")]
        jaw: Option<[f64; 3]>,
        /// Which needle end the jaw holds it nearer to.
        #[arg(long, value_enum, requires = "jaw")]
        holds: Option<HeldEnd>,
        /// With --exit: the needle is lodged in tissue, through this entry hole (robot frame,
        /// metres: x,y,z); the pose is the circle of the wire seen, through or within 5 mm of
        /// both holes, as a mission's extraction estimates it (docs/perception.md).
        #[arg(long, value_parser = parse_point, allow_hyphen_values = true, requires = "exit", conflicts_with = "jaw")]
        entry: Option<[f64; 3]>,
        /// With --entry: the exit hole (robot frame, metres: x,y,z).
        #[arg(long, value_parser = parse_point, allow_hyphen_values = true, requires = "entry")]
        exit: Option<[f64; 3]>,
        #[command(flatten)]
        options: PipelineOptions,
    },
    /// Dense disparity of a rectified pair over the whole left image (or --roi), or over the
    /// needle's region (--needle), written as PFM (little-endian, one channel, invalid = +inf,
    /// bottom row first as PFM requires). The search range: --min-disparity/--max-disparity,
    /// or from --calib and --depth-range.
    Disparity {
        /// Left image (PNG).
        left: PathBuf,
        /// Right image.
        right: PathBuf,
        /// The stereo calibration (TOML): the disparity range from its focal length and
        /// baseline and --depth-range; needed for --needle.
        #[arg(long)]
        calib: Option<PathBuf>,
        /// Where to write the disparity map; it covers the whole left image.
        #[arg(long)]
        out: PathBuf,
        /// Match over this left-image region: x0,y0,x1,y1 pixels.
        #[arg(long, value_parser = parse_rect)]
        roi: Option<Rect>,
        /// Least disparity searched, pixels (left x − right x).
        #[arg(long, requires = "max_disparity")]
        min_disparity: Option<u32>,
        /// Greatest disparity searched, pixels.
        #[arg(long, requires = "min_disparity")]
        max_disparity: Option<u32>,
        /// Nearest and farthest depth to search, metres: near,far (with --calib; default the
        /// needle pipeline's 0.05,0.6).
        #[arg(long, value_parser = parse_depths, requires = "calib", conflicts_with = "min_disparity")]
        depth_range: Option<[f64; 2]>,
        /// Match the needle's region as the pipeline does (its masks and its range; needs
        /// --calib) instead of every pixel.
        #[arg(long, requires = "calib", conflicts_with_all = ["min_disparity", "depth_range"])]
        needle: bool,
        /// Semi-global matching's aggregation paths (dense matching; --needle uses the
        /// pipeline's four).
        #[arg(long, value_enum, default_value_t = PathsArg::Five)]
        paths: PathsArg,
        /// Match on one thread (four and eight paths use two by default; five, one).
        #[arg(long)]
        single_thread: bool,
        /// Dense matching: the best cost must beat the second best (more than a pixel away)
        /// by this share, or the pixel has no answer.
        #[arg(long, default_value_t = SemiGlobalMatcher::default().uniqueness, value_parser = parse_share)]
        uniqueness: f32,
        /// Dense matching: the most the left and right views' disparities may differ, pixels.
        #[arg(long, default_value_t = SemiGlobalMatcher::default().lr_max_diff, value_parser = parse_pixels)]
        lr_max_diff: f32,
        /// Dense matching's left-right check (docs/perception.md): winners (OpenCV's),
        /// between, or nearest (the needle pipeline's).
        #[arg(long, value_enum, default_value_t = LeftRightArg::Winners)]
        left_right: LeftRightArg,
        /// Dense matching: leave out the 3×3 median filter that follows the checks (a pixel
        /// with no answer counts as larger than any; docs/perception.md).
        #[arg(long)]
        no_median: bool,
        #[command(flatten)]
        options: PipelineOptions,
    },
    /// Render a pair of the evaluation set (or of the mock's start) to PNG, with its
    /// calibration (TOML) and truth (JSON, with the holding jaw for --jaw/--holds): what the
    /// other commands read.
    Render {
        /// Directory to write left.png, right.png, calib.toml and truth.json into.
        #[arg(long)]
        out: PathBuf,
        /// Seed of the evaluation set and of the image noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Which frame of the evaluation set; without it, the mock's start (own set only).
        #[arg(long)]
        sample: Option<usize>,
        /// Which evaluation set: the mock's renderer (own) or the independent ray tracer
        /// (docs/perception.md).
        #[arg(long, value_enum, default_value_t = EvalSet::Own)]
        set: EvalSet,
        /// A pair of the thread tracer's evaluation set instead (--sample of it, default
        /// the first), with thread-truth.json: the true curve, the exit point, the swage.
        #[arg(long)]
        thread: bool,
    },
    /// Labelled crops around the needle, to train or test a learned segmenter on: for each
    /// view with the needle in it, NNNNN.png (the needle's box grown by 24 px) and
    /// NNNNN-labels.png (grey, one byte a pixel: 0 background, 1 needle, 2 thread,
    /// 3 instrument). See docs/perception.md, "A learned segmenter".
    Dataset {
        /// Directory to write the crops into (made if missing).
        #[arg(long)]
        out: PathBuf,
        /// Which frames: training (the mock's renderer under randomised cameras, both
        /// views), own or independent (the evaluation sets' left views).
        #[arg(long, value_enum, default_value_t = DatasetKind::Training)]
        set: DatasetKind,
        /// Scenes to render.
        #[arg(long, default_value_t = 400)]
        frames: usize,
        /// Seed of the scenes, cameras and noise.
        #[arg(long, default_value_t = 1)]
        seed: u64,
    },
}

/// Which frames `perceive dataset` writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum DatasetKind {
    /// The mock's renderer under randomised cameras, noise, defocus and light.
    Training,
    /// The own evaluation set.
    Own,
    /// The independent evaluation set (a ray tracer; a second or two a frame).
    Independent,
}

#[derive(Debug, Subcommand)]
pub enum BenchCommand {
    /// Latency per stage and end to end, and accuracy on a fixed rendered set.
    Perception {
        /// Frames of the own set (the mock's renderer).
        #[arg(long, default_value_t = 500)]
        frames: usize,
        /// Frames of the independent set (the independent ray tracer).
        #[arg(long, default_value_t = 200)]
        independent_frames: usize,
        /// Which sets to measure.
        #[arg(long, value_enum, value_delimiter = ',', default_values_t = [EvalSet::Own, EvalSet::Independent])]
        sets: Vec<EvalSet>,
        /// Seed of the set.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// Print JSON instead of tables.
        #[arg(long)]
        json: bool,
        /// Write each frame's result (error or typed failure) as JSON Lines into this
        /// directory, one file per matcher and mode.
        #[arg(long)]
        details: Option<PathBuf>,
        /// Keep the independent set's rendered pairs in this directory (raw RGB, about 9 MB
        /// a pair) and reuse them on later runs: the ray tracer takes a second or two a pair.
        #[arg(long)]
        render_cache: Option<PathBuf>,
        /// Matchers to measure (the default pipeline uses sgm).
        #[arg(long, value_enum, value_delimiter = ',', default_values_t = [MatcherKind::Sgm, MatcherKind::MaskRow])]
        matchers: Vec<MatcherKind>,
        /// The pipeline's segmenter: classical, onnx, onnx-fast or onnx:FILE (as `perceive needle`).
        #[arg(long, default_value = "classical")]
        segmenter: SegmenterChoice,
    },
    /// Segmenters against the truth: needle and thread intersection over union on the
    /// regions around the needle, and time per region, on the own set and the independent
    /// set (docs/perception.md, "A learned segmenter").
    Segmentation {
        /// Views of the own set (the mock's renderer), left images.
        #[arg(long, default_value_t = 200)]
        frames: usize,
        /// Views of the independent set (the independent ray tracer), left images.
        #[arg(long, default_value_t = 100)]
        independent_frames: usize,
        /// Seed of both sets.
        #[arg(long, default_value_t = 2)]
        seed: u64,
        /// Segmenters to compare: classical, onnx, onnx-fast, onnx:FILE.
        #[arg(long, value_delimiter = ',', default_values_t = [SegmenterChoice::Classical])]
        segmenters: Vec<SegmenterChoice>,
        /// Time every region this many times, the segmenters taking turns round by round
        /// (each in a different order each round), and report the median of each region's
        /// times: a load that comes and goes then falls on all of them alike.
        #[arg(long, default_value_t = 1, value_parser = clap::value_parser!(u32).range(1..=100))]
        rounds: u32,
        /// Print JSON instead of a table.
        #[arg(long)]
        json: bool,
    },
    /// A supervisor's command to both arms' hold, while an arm moves: median and p99, on the
    /// mock at --pace 1.0 in process and (--ros2) over ROS 2 against a sim-node in this
    /// process (docs/cli.md).
    Supervision(crate::bench_supervision::BenchSupervisionArgs),
    /// The thread tracer against the truth on the own and independent sets: 3D error, length
    /// error, how much of the truth its 2σ band covers, time per pair (docs/perception.md).
    Thread(crate::perceive_thread::BenchThreadArgs),
    /// `servo_cp` streamed over ROS 2 (real DDS on loopback) to a sim-node in this process:
    /// one-way latency at 1 kHz against a 100 Hz baseline.
    #[cfg(feature = "ros2")]
    Ros2(crate::ros2::BenchRos2Args),
}

/// The two evaluation sets.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum EvalSet {
    /// Pairs from the mock's renderer, which the pipeline was tuned on.
    Own,
    /// Pairs ray-traced independently: other rigs, tissue, light, needles, jaws or none.
    Independent,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum MatcherKind {
    /// Row-run matching of the needle masks (fastest).
    MaskRow,
    /// Census semi-global matching around the needle mask (the default).
    Sgm,
}

/// The most cost cells (pixels × disparities) `perceive disparity` matches densely.
pub const DENSE_MAX_CELLS: usize = 1 << 29;

/// The left-right check's reading of the right view.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum LeftRightArg {
    /// The least winning sum landing on a right pixel decides it; both right pixels must
    /// disagree (OpenCV's StereoSGBM's check).
    Winners,
    /// Every left pixel's sums decide a right pixel; either right pixel may agree.
    Between,
    /// As between, read at the nearest right pixel only (the needle pipeline's).
    Nearest,
}

/// Semi-global matching's aggregation paths.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum PathsArg {
    /// → ← ↓ ↑.
    Four,
    /// → ← ↓ ↘ ↙ in one pass over the rows (no cost volume held; one thread).
    Five,
    /// The four and the diagonals.
    Eight,
}

#[derive(Debug, clap::Args)]
pub struct PipelineOptions {
    /// The disparity matcher.
    #[arg(long, value_enum, default_value_t = MatcherKind::Sgm)]
    matcher: MatcherKind,
    /// The segmenter: classical (colour rules), onnx (the built-in U-Net; a stitch built
    /// with --features onnx), onnx-fast (the built-in U-Net from half resolution, about half
    /// the time) or onnx:FILE (a model keeping the contract in docs/perception.md).
    #[arg(long, default_value = "classical")]
    segmenter: SegmenterChoice,
    /// Needle radius, mm.
    #[arg(long, default_value_t = 12.0)]
    needle_radius_mm: f64,
    /// Seed of RANSAC's draws.
    #[arg(long, default_value_t = 1)]
    seed: u64,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
pub enum HeldEnd {
    /// Nearer the swage (the right jaw's grasp for insertion).
    Swage,
    /// Nearer the tip (the left jaw's after extraction).
    Tip,
}

pub(crate) fn parse_point(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{s:?}: {e}; expected x,y,z in metres"))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => Err(format!(
            "{s:?}: expected three finite numbers x,y,z in metres"
        )),
    }
}

fn parse_share(s: &str) -> Result<f32, String> {
    match s.trim().parse::<f32>() {
        Ok(v) if (0.0..1.0).contains(&v) => Ok(v),
        _ => Err(format!(
            "{s:?}: expected a share from 0 up to (not including) 1"
        )),
    }
}

fn parse_pixels(s: &str) -> Result<f32, String> {
    match s.trim().parse::<f32>() {
        Ok(v) if v.is_finite() && v >= 0.0 => Ok(v),
        _ => Err(format!("{s:?}: expected a number of pixels, 0 or more")),
    }
}

fn parse_depths(s: &str) -> Result<[f64; 2], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|p| p.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{s:?}: {e}; expected near,far in metres"))?;
    match v[..] {
        [near, far] if near.is_finite() && far.is_finite() && 0.0 < near && near < far => {
            Ok([near, far])
        }
        _ => Err(format!(
            "{s:?}: expected near,far in metres with 0 < near < far"
        )),
    }
}

fn parse_rect(s: &str) -> Result<Rect, String> {
    let v: Vec<u32> = s
        .split(',')
        .map(|p| p.trim().parse::<u32>())
        .collect::<Result<_, _>>()
        .map_err(|e| format!("{s:?}: {e}; expected x0,y0,x1,y1 in pixels"))?;
    match v[..] {
        [x0, y0, x1, y1] if x1 > x0 && y1 > y0 => Ok(Rect { x0, y0, x1, y1 }),
        _ => Err(format!(
            "{s:?}: expected x0,y0,x1,y1 with x1 > x0 and y1 > y0"
        )),
    }
}

fn matcher(kind: MatcherKind) -> Box<dyn StereoMatcher> {
    match kind {
        MatcherKind::MaskRow => Box::new(MaskRowMatcher::default()),
        MatcherKind::Sgm => Box::new(SemiGlobalMatcher::default()),
    }
}

pub(crate) fn read_calibration(path: &Path) -> anyhow::Result<StereoCalibration> {
    let text =
        std::fs::read_to_string(path).with_context(|| format!("cannot read {}", path.display()))?;
    inputs::calibration(&text).with_context(|| format!("invalid calibration {}", path.display()))
}

pub(crate) fn read_png(path: &Path) -> anyhow::Result<RgbImage> {
    let bytes =
        std::fs::read(path).with_context(|| format!("cannot read the image {}", path.display()))?;
    inputs::image(&bytes).with_context(|| format!("cannot read the image {}", path.display()))
}

pub(crate) fn write_png(path: &Path, img: &RgbImage) -> anyhow::Result<()> {
    let buf = image::RgbImage::from_raw(img.width, img.height, img.data.clone())
        .context("image buffer of the wrong size")?;
    buf.save_with_format(path, image::ImageFormat::Png)
        .with_context(|| format!("cannot write {}", path.display()))
}

/// PFM (Portable Float Map), one channel: a three-line header and little-endian f32 rows,
/// bottom row first. Written by hand: it is those three lines and a loop.
fn write_pfm(path: &Path, width: u32, height: u32, data: &[f32]) -> anyhow::Result<()> {
    let mut out = Vec::with_capacity(data.len() * 4 + 32);
    write!(out, "Pf\n{width} {height}\n-1.0\n")?;
    for y in (0..height as usize).rev() {
        for v in &data[y * width as usize..(y + 1) * width as usize] {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    std::fs::write(path, out).with_context(|| format!("cannot write {}", path.display()))
}

fn pipeline(
    calibration: StereoCalibration,
    options: &PipelineOptions,
) -> anyhow::Result<NeedlePipeline> {
    let needle = Needle::new(options.needle_radius_mm * 1e-3)?;
    let mut p = NeedlePipeline::classical(calibration, needle)?;
    p.matcher = matcher(options.matcher);
    if let Some(s) = options.segmenter.load_learned()? {
        p.segmenter = Box::new(s);
    }
    Ok(p)
}

/// The estimate as printed.
#[derive(Debug, Serialize)]
struct PoseJson {
    center_m: [f64; 3],
    normal: [f64; 3],
    tip_m: [f64; 3],
    swage_m: [f64; 3],
    /// Needle frame in the robot frame: translation and quaternion (x, y, z, w).
    translation_m: [f64; 3],
    rotation_xyzw: [f64; 4],
    confidence: f64,
    diagnostics: stitch_perception::pipeline::Diagnostics,
}

pub fn perceive(command: PerceiveCommand) -> anyhow::Result<u8> {
    match command {
        PerceiveCommand::Needle {
            left,
            right,
            calib,
            jaw,
            holds,
            entry,
            exit,
            options,
        } => {
            let c = read_calibration(&calib)?;
            let (l, r) = (read_png(&left)?, read_png(&right)?);
            let p = pipeline(c, &options)?;
            let point = |a: [f64; 3]| stitch_robot::Point::new(a[0], a[1], a[2]);
            let hint = jaw.zip(holds).map(|(j, h)| JawHint {
                jaw: point(j),
                end: match h {
                    HeldEnd::Swage => NeedleEnd::Swage,
                    HeldEnd::Tip => NeedleEnd::Tip,
                },
            });
            let holes = entry.zip(exit).map(|(e, x)| TissueHint {
                entry: point(e),
                exit: point(x),
            });
            let mut out = std::io::stdout().lock();
            let estimate = match &holes {
                Some(h) => p.estimate_in_tissue(&l, &r, h, options.seed),
                None => p.estimate(&l, &r, hint.as_ref(), options.seed),
            };
            match estimate {
                Ok(o) => {
                    let g = p.needle.in_world(&o.pose);
                    let t = o.pose.translation.vector;
                    let q = o.pose.rotation.coords;
                    let a = |p: stitch_robot::Point| [p.x, p.y, p.z];
                    let json = PoseJson {
                        center_m: a(g.center),
                        normal: [g.normal.x, g.normal.y, g.normal.z],
                        tip_m: a(g.tip),
                        swage_m: a(g.swage),
                        translation_m: [t.x, t.y, t.z],
                        rotation_xyzw: [q.x, q.y, q.z, q.w],
                        confidence: o.confidence,
                        diagnostics: o.diagnostics,
                    };
                    serde_json::to_writer_pretty(&mut out, &json)?;
                    writeln!(out)?;
                    Ok(crate::exit::OK)
                }
                Err(e) => {
                    failure_json(&mut out, &e)?;
                    eprintln!("no estimate: {e}");
                    Ok(NO_ESTIMATE)
                }
            }
        }
        PerceiveCommand::Disparity {
            left,
            right,
            calib,
            out,
            roi,
            min_disparity,
            max_disparity,
            depth_range,
            needle,
            paths,
            single_thread,
            uniqueness,
            lr_max_diff,
            left_right,
            no_median,
            options,
        } => {
            let c = calib.as_deref().map(read_calibration).transpose()?;
            let (l, r) = (read_png(&left)?, read_png(&right)?);
            let (w, h) = (l.width, l.height);
            let t0 = Instant::now();
            let map = if needle {
                let c = c.context("--needle needs --calib")?;
                let p = pipeline(c, &options)?;
                match p.disparity(&l, &r, roi) {
                    Ok(m) => m,
                    Err(e @ PerceptionError::Config { .. }) => anyhow::bail!("{e}"),
                    Err(e) => {
                        failure_json(&mut std::io::stdout().lock(), &e)?;
                        eprintln!("no disparity: {e}");
                        return Ok(NO_ESTIMATE);
                    }
                }
            } else {
                if options.matcher != MatcherKind::Sgm {
                    anyhow::bail!(
                        "--matcher mask-row matches the needle's masks: add --needle, or match every pixel with sgm"
                    );
                }
                let [lo, hi] = match (min_disparity.zip(max_disparity), &c) {
                    (Some((lo, hi)), _) => [lo, hi],
                    (None, Some(c)) => {
                        if (c.width, c.height) != (w, h) {
                            anyhow::bail!(
                                "the calibration is for {}×{} images, {} is {w}×{h}",
                                c.width,
                                c.height,
                                left.display()
                            );
                        }
                        let [near, far] = depth_range.unwrap_or([0.05, 0.6]);
                        let fb = c.fx * c.baseline_m;
                        [(fb / far).floor() as u32, (fb / near).ceil() as u32]
                    }
                    (None, None) => anyhow::bail!(
                        "no disparity range: give --min-disparity and --max-disparity (pixels), or --calib (and --depth-range)"
                    ),
                };
                let sgm = SemiGlobalMatcher {
                    around_mask_px: None,
                    // 3 bytes a cell on one thread, 5 on two: at most about 1.6 or 2.7 GB.
                    max_cells: DENSE_MAX_CELLS,
                    uniqueness,
                    lr_max_diff,
                    left_right: match left_right {
                        LeftRightArg::Winners => LeftRight::Winners,
                        LeftRightArg::Between => LeftRight::Between,
                        LeftRightArg::Nearest => LeftRight::Nearest,
                    },
                    paths: match paths {
                        PathsArg::Four => SgmPaths::Four,
                        PathsArg::Five => SgmPaths::Five,
                        PathsArg::Eight => SgmPaths::Eight,
                    },
                    median: !no_median,
                    ..SemiGlobalMatcher::default()
                };
                let region = roi.unwrap_or(Rect::full(w, h));
                // No pixel of the region matches past its right edge: searching further only
                // costs time.
                let hi = if hi >= region.x1 && lo < region.x1 {
                    eprintln!(
                        "the disparity range {lo}..{hi} is cut to {lo}..{}: no pixel left of x = {} matches farther",
                        region.x1 - 1,
                        region.x1
                    );
                    region.x1 - 1
                } else {
                    hi
                };
                sgm.dense(&l, &r, region, lo, hi, !single_thread)
                    .map_err(|e| anyhow::anyhow!("{e}"))?
            };
            let took = t0.elapsed();
            let mut full = vec![f32::INFINITY; (w * h) as usize];
            for y in map.roi.y0..map.roi.y1 {
                for x in map.roi.x0..map.roi.x1 {
                    if let Some(d) = map.at(x, y) {
                        full[(y * w + x) as usize] = d;
                    }
                }
            }
            write_pfm(&out, w, h, &full)?;
            println!(
                "wrote {} ({}×{}; {} valid disparities over {}..{} × {}..{})",
                out.display(),
                w,
                h,
                map.valid_count(),
                map.roi.x0,
                map.roi.x1,
                map.roi.y0,
                map.roi.y1
            );
            eprintln!("matched in {:.2} ms", took.as_secs_f64() * 1e3);
            Ok(crate::exit::OK)
        }
        PerceiveCommand::Dataset {
            out,
            set,
            frames,
            seed,
        } => {
            use stitch_eval::segmentation;
            let (renderer, world) = mock_renderer(seed)?;
            let phantom = world.phantom_view();
            let views = match set {
                DatasetKind::Training => segmentation::training_views(&phantom, frames, seed)
                    .map_err(anyhow::Error::msg)?,
                DatasetKind::Own => segmentation::own_views(&renderer, &phantom, frames, seed),
                DatasetKind::Independent => segmentation::independent_views(frames, seed),
            };
            std::fs::create_dir_all(&out)
                .with_context(|| format!("cannot make {}", out.display()))?;
            let mut written = 0;
            for v in &views {
                let Some(roi) = v.roi else { continue };
                let (image, labels) = v.crop(roi);
                write_png(&out.join(format!("{written:05}.png")), &image)?;
                let path = out.join(format!("{written:05}-labels.png"));
                image::GrayImage::from_raw(image.width, image.height, labels)
                    .context("label buffer of the wrong size")?
                    .save_with_format(&path, image::ImageFormat::Png)
                    .with_context(|| format!("cannot write {}", path.display()))?;
                written += 1;
            }
            eprintln!(
                "wrote {written} labelled crops ({} views without the needle left out) to {}",
                views.len() - written,
                out.display()
            );
            Ok(0)
        }
        PerceiveCommand::Thread(args) => crate::perceive_thread::perceive(args),
        PerceiveCommand::Render {
            out,
            seed,
            sample,
            set,
            thread: true,
        } => crate::perceive_thread::render(&out, seed, sample, set),
        PerceiveCommand::Render {
            out,
            seed,
            sample,
            set: EvalSet::Independent,
            thread: false,
        } => {
            let k = sample.unwrap_or(0);
            let set = stitch_eval::independent::dataset(k + 1, seed, Needle::default());
            let s = set.into_iter().nth(k).context("no such sample")?;
            let (left, right) = stitch_eval::independent::render(&s);
            write_rendered(
                &out,
                &left,
                &right,
                &s.calibration,
                &s.truth,
                s.jaw.as_ref(),
            )
        }
        PerceiveCommand::Render {
            out,
            seed,
            sample,
            set: EvalSet::Own,
            thread: false,
        } => {
            let (renderer, world) = mock_renderer(seed)?;
            let (scene_and_truth, hint) = match sample {
                Some(k) => {
                    let set =
                        evaluate::dataset(k + 1, seed, Needle::default(), &world.phantom_view());
                    let s = set.into_iter().nth(k).context("no such sample")?;
                    let hint = evaluate::jaw_hint(&s);
                    ((s.scene, s.truth), hint)
                }
                None => {
                    let scene = world.scene_view();
                    let jaw = stitch_robot::Point::from(scene.tools[0].pose.translation.vector);
                    let hint = JawHint {
                        jaw,
                        end: NeedleEnd::Swage,
                    };
                    ((scene, world.needle_truth().pose), hint)
                }
            };
            let mut rng = Streams::new(seed).rng(stitch_sim::Subsystem::Perception);
            let pair = renderer.render(&scene_and_truth.0, &Pose::identity(), &mut rng);
            write_rendered(
                &out,
                &pair.left,
                &pair.right,
                renderer.calibration(),
                &scene_and_truth.1,
                Some(&hint),
            )
        }
    }
}

/// A rendered pair, its calibration and its truth (and the holding jaw, if any) as files.
fn write_rendered(
    out: &Path,
    left: &RgbImage,
    right: &RgbImage,
    calibration: &StereoCalibration,
    truth: &Pose,
    hint: Option<&JawHint>,
) -> anyhow::Result<u8> {
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    write_png(&out.join("left.png"), left)?;
    write_png(&out.join("right.png"), right)?;
    let calib = CalibrationFile::from_calibration(calibration);
    std::fs::write(out.join("calib.toml"), toml::to_string(&calib)?)
        .with_context(|| format!("cannot write into {}", out.display()))?;
    let needle = Needle::default();
    let g = needle.in_world(truth);
    let a = |p: stitch_robot::Point| [p.x, p.y, p.z];
    let mut json = serde_json::json!({
        "center_m": a(g.center),
        "normal": [g.normal.x, g.normal.y, g.normal.z],
        "tip_m": a(g.tip),
        "swage_m": a(g.swage),
    });
    if let Some(h) = hint {
        json["jaw_m"] = serde_json::json!(a(h.jaw));
        json["jaw_holds"] = serde_json::json!(match h.end {
            NeedleEnd::Tip => "tip",
            NeedleEnd::Swage => "swage",
        });
    }
    std::fs::write(
        out.join("truth.json"),
        serde_json::to_string_pretty(&json)? + "\n",
    )?;
    println!(
        "wrote left.png, right.png, calib.toml and truth.json into {}",
        out.display()
    );
    Ok(crate::exit::OK)
}

pub(crate) fn failure_json(out: &mut impl Write, e: &PerceptionError) -> anyhow::Result<()> {
    let json = serde_json::json!({
        "failure": failure_kind(e),
        "message": e.to_string(),
    });
    serde_json::to_writer_pretty(&mut *out, &json)?;
    writeln!(out)?;
    Ok(())
}

/// The mock's default renderer and a world at its start.
pub(crate) fn mock_renderer(seed: u64) -> anyhow::Result<(StereoRenderer, MockDvrk)> {
    let world = MockDvrk::new(
        &SceneConfig::default(),
        Streams::new(seed),
        stitch_robot::SimClock::new(),
    )?;
    let renderer = StereoRenderer::new(CameraConfig::default(), world.phantom_view())?;
    Ok((renderer, world))
}

#[derive(Debug, Serialize)]
struct Latency {
    median_ms: f64,
    p95_ms: f64,
}

fn latency(mut v: Vec<f64>) -> Latency {
    v.sort_by(f64::total_cmp);
    Latency {
        median_ms: percentile(&v, 0.5) * 1e3,
        p95_ms: percentile(&v, 0.95) * 1e3,
    }
}

#[derive(Debug, Serialize)]
struct BenchRow {
    set: EvalSet,
    matcher: MatcherKind,
    mode: &'static str,
    render: Latency,
    segment: Latency,
    disparity: Latency,
    cloud: Latency,
    fit: Latency,
    total: Latency,
    accuracy: Accuracy,
    by_jaw: Vec<(String, Accuracy)>,
    thread_over: Accuracy,
}

pub fn bench(command: BenchCommand) -> anyhow::Result<u8> {
    // Irrefutable when built without the `ros2` feature (no `bench ros2`).
    #[allow(irrefutable_let_patterns)]
    let BenchCommand::Perception {
        frames,
        independent_frames,
        sets,
        seed,
        json,
        details,
        render_cache,
        matchers,
        segmenter,
    } = command
    else {
        return match command {
            BenchCommand::Segmentation {
                frames,
                independent_frames,
                seed,
                segmenters,
                rounds,
                json,
            } => bench_segmentation(frames, independent_frames, seed, &segmenters, rounds, json),
            _ => anyhow::bail!("not a perception benchmark"),
        };
    };
    let learned = segmenter.load_learned()?;
    if let Some(d) = &details {
        std::fs::create_dir_all(d).with_context(|| format!("cannot create {}", d.display()))?;
    }
    let started = Instant::now();
    let mut rows = Vec::new();
    let record = |set: EvalSet,
                  rows: &mut Vec<BenchRow>,
                  r: BenchRow,
                  results: &[FrameResult]|
     -> anyhow::Result<()> {
        if let Some(d) = &details {
            let path = d.join(format!(
                "{}-{}-{}.jsonl",
                set_name(set),
                m_name(r.matcher),
                r.mode.replace([',', ' '], "-").replace("--", "-")
            ));
            let mut text = String::new();
            for (i, f) in results.iter().enumerate() {
                text += &serde_json::to_string(&serde_json::json!({"frame": i, "result": f}))?;
                text.push('\n');
            }
            std::fs::write(&path, text)
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
        eprintln!(
            "{} set, {} {}: {} frames, {:.1} s so far",
            set_name(set),
            m_name(r.matcher),
            r.mode,
            results.len(),
            started.elapsed().as_secs_f64()
        );
        rows.push(r);
        Ok(())
    };
    if sets.contains(&EvalSet::Own) {
        if frames == 0 {
            anyhow::bail!("--frames must be at least 1");
        }
        let (renderer, world) = mock_renderer(seed)?;
        let samples = evaluate::dataset(frames, seed, Needle::default(), &world.phantom_view());
        for &m in &matchers {
            for (parallel, hinted) in [(false, false), (true, false), (false, true), (true, true)] {
                let mut p =
                    NeedlePipeline::classical(renderer.calibration().clone(), Needle::default())?;
                p.matcher = matcher(m);
                p.parallel = parallel;
                if let Some(s) = &learned {
                    p.segmenter = Box::new(s.clone());
                }
                let results = evaluate::run(&p, &renderer, &samples, seed, hinted);
                let r = row(EvalSet::Own, m, parallel, hinted, &results);
                record(EvalSet::Own, &mut rows, r, &results)?;
            }
        }
    }
    if sets.contains(&EvalSet::Independent) {
        if independent_frames == 0 {
            anyhow::bail!("--independent-frames must be at least 1");
        }
        let samples =
            stitch_eval::independent::dataset(independent_frames, seed, Needle::default());
        // Each pair is rendered once and estimated in every mode (rendering costs more than
        // estimating); one thread, full frame and with the jaw known where there is one.
        let makers: Vec<Box<stitch_eval::independent::MakePipeline>> = matchers
            .iter()
            .map(|&m| -> Box<stitch_eval::independent::MakePipeline> {
                let learned = learned.clone();
                Box::new(move |c: &StereoCalibration| {
                    let mut p = NeedlePipeline::classical(c.clone(), Needle::default())?;
                    p.matcher = matcher(m);
                    if let Some(s) = &learned {
                        p.segmenter = Box::new(s.clone());
                    }
                    Ok(p)
                })
            })
            .collect();
        let mut modes: Vec<(bool, &stitch_eval::independent::MakePipeline)> = Vec::new();
        for mk in &makers {
            modes.push((false, mk.as_ref()));
            modes.push((true, mk.as_ref()));
        }
        let all = stitch_eval::independent::run(&samples, &modes, seed, render_cache.as_deref());
        for (k, results) in all.iter().enumerate() {
            let m = matchers[k / 2];
            let r = row(EvalSet::Independent, m, false, k % 2 == 1, results);
            record(EvalSet::Independent, &mut rows, r, results)?;
        }
    }
    let mut out = std::io::stdout().lock();
    if json {
        serde_json::to_writer_pretty(&mut out, &rows)?;
        writeln!(out)?;
    } else {
        write!(
            out,
            "{}",
            tables(&rows, frames, independent_frames, seed, &segmenter)
        )?;
    }
    Ok(crate::exit::OK)
}

fn set_name(s: EvalSet) -> &'static str {
    match s {
        EvalSet::Own => "own",
        EvalSet::Independent => "independent",
    }
}

fn m_name(m: MatcherKind) -> &'static str {
    match m {
        MatcherKind::MaskRow => "mask-row",
        MatcherKind::Sgm => "sgm",
    }
}

fn row(
    set: EvalSet,
    m: MatcherKind,
    parallel: bool,
    hinted: bool,
    results: &[FrameResult],
) -> BenchRow {
    let secs = |f: &dyn Fn(&FrameResult) -> Duration| -> Vec<f64> {
        results
            .iter()
            .filter(|r| r.error.is_some())
            .map(|r| f(r).as_secs_f64())
            .collect()
    };
    let jaws: &[&str] = match set {
        EvalSet::Own => &["right", "left"],
        EvalSet::Independent => &["none", "tip", "swage"],
    };
    let by_jaw = jaws
        .iter()
        .map(|j| {
            let sub: Vec<FrameResult> = results.iter().filter(|r| r.jaw == *j).cloned().collect();
            (j.to_string(), stitch_eval::accuracy(&sub))
        })
        .collect();
    let over: Vec<FrameResult> = results.iter().filter(|r| r.thread_over).cloned().collect();
    BenchRow {
        set,
        matcher: m,
        mode: match (parallel, hinted) {
            (false, false) => "full frame, 1 thread",
            (true, false) => "full frame, all cores",
            (false, true) => "jaw known, 1 thread",
            (true, true) => "jaw known, all cores",
        },
        render: latency(results.iter().map(|r| r.render.as_secs_f64()).collect()),
        segment: latency(secs(&|r| r.times.segment)),
        disparity: latency(secs(&|r| r.times.disparity)),
        cloud: latency(secs(&|r| r.times.cloud)),
        fit: latency(secs(&|r| r.times.fit)),
        total: latency(results.iter().map(|r| r.total.as_secs_f64()).collect()),
        accuracy: stitch_eval::accuracy(results),
        by_jaw,
        thread_over: stitch_eval::accuracy(&over),
    }
}

fn tables(
    rows: &[BenchRow],
    frames: usize,
    independent_frames: usize,
    seed: u64,
    segmenter: &SegmenterChoice,
) -> String {
    let mut s = format!(
        "Stereo needle pipeline, seed {seed}, {segmenter} segmenter, {} cores\n",
        std::thread::available_parallelism().map_or(1, |n| n.get())
    );
    for set in [EvalSet::Own, EvalSet::Independent] {
        let rows: Vec<&BenchRow> = rows.iter().filter(|r| r.set == set).collect();
        if rows.is_empty() {
            continue;
        }
        s += &match set {
            EvalSet::Own => format!(
                "\n## Own set: {frames} pairs from the mock's renderer (1280×960, the set the pipeline was tuned on)\n"
            ),
            EvalSet::Independent => format!(
                "\n## Independent set: {independent_frames} ray-traced pairs (other rigs 1024×768 to 1920×1080, tissue, light, needles; a jaw in about half; \"jaw known\" gives the hint where there is a jaw)\n"
            ),
        };
        s += &set_tables(&rows);
    }
    s
}

fn set_tables(rows: &[&BenchRow]) -> String {
    let mut s = "\nLatency per stereo pair, ms (median / p95; stage times over frames with an estimate; render: the set's renderer)\n\n".to_string();
    s += "| matcher | mode | render | segment | disparity | cloud | fit | end to end |\n|---|---|---|---|---|---|---|---|\n";
    let l = |x: &Latency| format!("{:.2} / {:.2}", x.median_ms, x.p95_ms);
    for r in rows {
        s += &format!(
            "| {} | {} | {} | {} | {} | {} | {} | {} |\n",
            m_name(r.matcher),
            r.mode,
            l(&r.render),
            l(&r.segment),
            l(&r.disparity),
            l(&r.cloud),
            l(&r.fit),
            l(&r.total)
        );
    }
    s += "\nAccuracy (errors median / p95 over estimates; shares over all frames)\n\n";
    s += "| matcher | frames | endpoints mm | centre mm | normal ° | ≤ 1 mm & 5° | ≤ 3 mm or typed failure | typed failures | wrong (> 3 mm) |\n|---|---|---|---|---|---|---|---|---|\n";
    let a = |name: String, x: &Accuracy| {
        format!(
            "| {name} | {} | {:.2} / {:.2} | {:.2} / {:.2} | {:.2} / {:.2} | {:.1} % | {:.1} % | {:.1} % | {} |\n",
            x.frames,
            x.endpoint_mm[0],
            x.endpoint_mm[1],
            x.center_mm[0],
            x.center_mm[1],
            x.normal_deg[0],
            x.normal_deg[1],
            100.0 * x.within_1mm_5deg,
            100.0 * x.within_3mm_or_failure,
            100.0 * x.failures,
            x.wrong
        )
    };
    for r in rows.iter().filter(|r| !r.mode.contains("all cores")) {
        let name = format!(
            "{}, {}",
            m_name(r.matcher),
            r.mode.trim_end_matches(", 1 thread")
        );
        s += &a(name.clone(), &r.accuracy);
        for (j, acc) in &r.by_jaw {
            s += &a(format!("{name} ({j} jaw)"), acc);
        }
        s += &a(format!("{name} (thread over the needle)"), &r.thread_over);
    }
    s += "\nTyped failures by kind\n\n";
    for r in rows.iter().filter(|r| !r.mode.contains("all cores")) {
        let kinds: Vec<String> = r
            .accuracy
            .failure_kinds
            .iter()
            .map(|(k, n)| format!("{k} {n}"))
            .collect();
        s += &format!(
            "- {}, {}: {}\n",
            m_name(r.matcher),
            r.mode.trim_end_matches(", 1 thread"),
            if kinds.is_empty() {
                "none".into()
            } else {
                kinds.join(", ")
            }
        );
    }
    s
}

#[derive(Debug, Serialize)]
struct SegmentationRow {
    set: EvalSet,
    segmenter: String,
    views: usize,
    needle_iou: f64,
    thread_iou: f64,
    region_px_median: f64,
    time: Latency,
}

/// `stitch bench segmentation`: each segmenter on the same views' regions.
fn bench_segmentation(
    frames: usize,
    independent_frames: usize,
    seed: u64,
    segmenters: &[SegmenterChoice],
    rounds: u32,
    json: bool,
) -> anyhow::Result<u8> {
    use stitch_eval::segmentation;
    let loaded = segmenters
        .iter()
        .map(|c| c.load().map(|s| (c.to_string(), s)))
        .collect::<anyhow::Result<Vec<_>>>()?;
    let started = Instant::now();
    let (renderer, world) = mock_renderer(seed)?;
    let phantom = world.phantom_view();
    let mut sets = Vec::new();
    if frames > 0 {
        sets.push((
            EvalSet::Own,
            segmentation::own_views(&renderer, &phantom, frames, seed),
        ));
        eprintln!(
            "own set: {frames} views rendered, {:.1} s",
            started.elapsed().as_secs_f64()
        );
    }
    if independent_frames > 0 {
        sets.push((
            EvalSet::Independent,
            segmentation::independent_views(independent_frames, seed),
        ));
        eprintln!(
            "independent set: {independent_frames} views rendered, {:.1} s",
            started.elapsed().as_secs_f64()
        );
    }
    let mut rows = Vec::new();
    for (set, views) in &sets {
        let mut scores = Vec::new();
        for (name, seg) in &loaded {
            let s = segmentation::score(seg, views).with_context(|| format!("segmenter {name}"))?;
            // Each region's times, one per round.
            let times: Vec<Vec<f64>> = s.times.iter().map(|t| vec![t.as_secs_f64()]).collect();
            scores.push((s, times));
        }
        for round in 1..rounds as usize {
            for k in 0..loaded.len() {
                let i = (k + round) % loaded.len();
                let (name, seg) = &loaded[i];
                let again =
                    segmentation::time(seg, views).with_context(|| format!("segmenter {name}"))?;
                for (ts, t) in scores[i].1.iter_mut().zip(again) {
                    ts.push(t.as_secs_f64());
                }
            }
        }
        for ((name, _), (s, times)) in loaded.iter().zip(scores) {
            let mut px: Vec<f64> = s.pixels.iter().map(|&p| p as f64).collect();
            px.sort_by(f64::total_cmp);
            let medians = times
                .into_iter()
                .map(|mut ts| {
                    ts.sort_by(f64::total_cmp);
                    percentile(&ts, 0.5)
                })
                .collect();
            rows.push(SegmentationRow {
                set: *set,
                segmenter: name.clone(),
                views: s.views,
                needle_iou: s.needle.iou(),
                thread_iou: s.thread.iou(),
                region_px_median: percentile(&px, 0.5),
                time: latency(medians),
            });
        }
    }
    let mut out = std::io::stdout().lock();
    if json {
        serde_json::to_writer_pretty(&mut out, &rows)?;
        writeln!(out)?;
        return Ok(0);
    }
    writeln!(
        out,
        "Segmentation against the truth, seed {seed}: the needle's region (its box + {} px) of each left view; IoU pooled over the views; time per region on one thread{}\n",
        segmentation::MARGIN_PX,
        if rounds > 1 {
            format!(" (each region's median of {rounds} rounds, the segmenters taking turns)")
        } else {
            String::new()
        }
    )?;
    writeln!(
        out,
        "| set | segmenter | views | needle IoU | thread IoU | region px (median) | ms per region (median / p95) |\n|---|---|---|---|---|---|---|"
    )?;
    for r in &rows {
        writeln!(
            out,
            "| {} | {} | {} | {:.3} | {:.3} | {:.0} | {:.2} / {:.2} |",
            set_name(r.set),
            r.segmenter,
            r.views,
            r.needle_iou,
            r.thread_iou,
            r.region_px_median,
            r.time.median_ms,
            r.time.p95_ms
        )?;
    }
    Ok(0)
}
