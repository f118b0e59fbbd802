//! `stitch perceive thread`, `stitch perceive render --thread` and `stitch bench thread`:
//! the stereo thread tracer on a lab's own pairs, on rendered ones, and its accuracy tables
//! on the two evaluation sets (docs/perception.md, "The thread tracer").

use anyhow::Context;
use serde::Serialize;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::time::Instant;
use stitch_cli::inputs::CalibrationFile;
use stitch_eval::thread::{self as eval, ThreadAccuracy, ThreadResult};
use stitch_perception::segment::Segmenter;
use stitch_perception::thread::{ThreadHint, ThreadParams, ThreadTrace, trace};
use stitch_robot::{Needle, Point, Pose};

use crate::perceive::{EvalSet, NO_ESTIMATE, failure_json, mock_renderer, parse_point};
use crate::perceive::{read_calibration, read_png, write_png};
use crate::segmenter::SegmenterChoice;

/// `stitch perceive thread`.
#[derive(Debug, clap::Args)]
pub struct ThreadArgs {
    /// Left image (PNG, 8-bit RGB or grey).
    left: PathBuf,
    /// Right image.
    right: PathBuf,
    /// The stereo calibration (TOML; see docs/perception.md).
    #[arg(long)]
    calib: PathBuf,
    /// The needle's swage, robot frame, metres: x,y,z (from `perceive needle`'s swage_m).
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
    swage: [f64; 3],
    /// Where the thread leaves the tissue (the last stitch's exit point), robot frame,
    /// metres: x,y,z. Without it the trace runs from the swage to the farthest thread.
    #[arg(long, value_parser = parse_point, allow_hyphen_values = true)]
    start: Option<[f64; 3]>,
    /// How much thread runs between the two ends, metres, if known (a length prior, taken
    /// as good to 10 %): it chooses the fit's smoothing, and a trace that falls short of it
    /// takes in thread the view shows apart from its path (a loop whose neck is hidden).
    #[arg(long, value_parser = parse_length)]
    length_m: Option<f64>,
    /// The segmenter whose thread mask is traced: classical, onnx, onnx-fast or onnx:FILE.
    #[arg(long, default_value = "classical")]
    segmenter: SegmenterChoice,
}

/// `stitch bench thread`.
#[derive(Debug, clap::Args)]
pub struct BenchThreadArgs {
    /// Pairs of the own set (the mock's renderer, its chain thread).
    #[arg(long, default_value_t = 200)]
    frames: usize,
    /// Pairs of the independent set (the independent ray tracer).
    #[arg(long, default_value_t = 100)]
    independent_frames: usize,
    /// Which sets to measure.
    #[arg(long, value_enum, value_delimiter = ',', default_values_t = [EvalSet::Own, EvalSet::Independent])]
    sets: Vec<EvalSet>,
    /// Seed of both sets.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Keep the independent set's rendered pairs here and reuse them (as `bench perception`).
    #[arg(long)]
    render_cache: Option<PathBuf>,
    /// The segmenter: classical, onnx, onnx-fast or onnx:FILE.
    #[arg(long, default_value = "classical")]
    segmenter: SegmenterChoice,
    /// Write each pair's result as JSON Lines into this file.
    #[arg(long)]
    details: Option<PathBuf>,
    /// Tell the tracer how much thread runs between the ends: the true length, off by a
    /// normal error of this share of it (one σ, drawn from the seed), as a plan that knows
    /// its thread would. Without it the tracer has no length prior.
    #[arg(long, value_parser = parse_share)]
    length_prior: Option<f64>,
    /// Print JSON instead of a table.
    #[arg(long)]
    json: bool,
}

fn parse_share(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if (0.0..=1.0).contains(&v) => Ok(v),
        _ => Err(format!("{s:?}: expected a share from 0 to 1 (0.1 = 10 %)")),
    }
}

fn parse_length(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("{s:?}: expected a length in metres, more than 0")),
    }
}

/// A trace as printed.
#[derive(Debug, Serialize)]
struct TraceJson {
    /// From the first end to the swage, robot frame, m.
    points_m: Vec<[f64; 3]>,
    /// Each point's uncertainty, m (with `--length-m`, widened near the hidden spans to
    /// half the farthest the thread hidden there can reach).
    sigma_m: Vec<f64>,
    length_m: f64,
    /// Stretches the left view does not show, `[from, to]` along the thread, m.
    hidden_m: Vec<[f64; 2]>,
    seen_share: f64,
    matched: usize,
    left_path_px: Vec<[f64; 2]>,
}

impl From<&ThreadTrace> for TraceJson {
    fn from(t: &ThreadTrace) -> Self {
        Self {
            points_m: t.points.iter().map(|p| [p.x, p.y, p.z]).collect(),
            sigma_m: t.sigma_m.clone(),
            length_m: t.length_m,
            hidden_m: t.hidden.clone(),
            seen_share: t.seen_share,
            matched: t.matched,
            left_path_px: t.left_path_px.clone(),
        }
    }
}

fn point(p: [f64; 3]) -> Point {
    Point::new(p[0], p[1], p[2])
}

/// `stitch perceive thread`: the trace as JSON, or the typed failure (exit code 6).
pub fn perceive(args: ThreadArgs) -> anyhow::Result<u8> {
    let c = read_calibration(&args.calib)?;
    let (l, r) = (read_png(&args.left)?, read_png(&args.right)?);
    let segmenter = args.segmenter.load()?;
    let hint = ThreadHint {
        start: args.start.map(point),
        swage: point(args.swage),
        length_m: args.length_m,
    };
    let mut out = std::io::stdout().lock();
    match trace(&ThreadParams::default(), &segmenter, &c, &l, &r, &hint) {
        Ok(t) => {
            serde_json::to_writer_pretty(&mut out, &TraceJson::from(&t))?;
            writeln!(out)?;
            Ok(crate::exit::OK)
        }
        Err(e) => {
            failure_json(&mut out, &e)?;
            eprintln!("no trace: {e}");
            Ok(NO_ESTIMATE)
        }
    }
}

/// `stitch perceive render --thread`: a pair of a thread evaluation set with its
/// calibration and `thread-truth.json` (the true curve, the exit point and the swage).
pub fn render(out: &Path, seed: u64, sample: Option<usize>, set: EvalSet) -> anyhow::Result<u8> {
    let k = sample.unwrap_or(0);
    let (left, right, calib, truth) = match set {
        EvalSet::Own => {
            let (renderer, world) = mock_renderer(seed)?;
            let set = eval::own_set(k + 1, seed, Needle::default(), &world.phantom());
            // The noise `bench thread` draws for this sample: the set's pairs in order.
            let mut rng = <rand_chacha::ChaCha8Rng as rand::SeedableRng>::seed_from_u64(seed);
            let mut pair = None;
            for s in &set {
                pair = Some(renderer.render(&s.scene, &Pose::identity(), &mut rng));
            }
            let (pair, s) = pair.zip(set.into_iter().nth(k)).context("no such sample")?;
            (
                pair.left,
                pair.right,
                renderer.calibration().clone(),
                s.sample,
            )
        }
        EvalSet::Independent => {
            let (s, t) = eval::independent_set(k + 1, seed, Needle::default())
                .into_iter()
                .nth(k)
                .context("no such sample")?;
            let (l, r) = stitch_eval::independent::render(&s);
            (l, r, s.calibration, t)
        }
    };
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    write_png(&out.join("left.png"), &left)?;
    write_png(&out.join("right.png"), &right)?;
    std::fs::write(
        out.join("calib.toml"),
        toml::to_string(&CalibrationFile::from_calibration(&calib))?,
    )
    .with_context(|| format!("cannot write into {}", out.display()))?;
    let a = |p: &Point| [p.x, p.y, p.z];
    let json = serde_json::json!({
        "start_m": truth.hint.start.as_ref().map(a),
        "swage_m": a(&truth.hint.swage),
        "points_m": truth.truth.iter().map(a).collect::<Vec<_>>(),
        "length_m": truth.truth.windows(2).map(|w| (w[1] - w[0]).norm()).sum::<f64>(),
        "occluded": truth.occluded,
    });
    std::fs::write(
        out.join("thread-truth.json"),
        serde_json::to_string_pretty(&json)? + "\n",
    )?;
    println!(
        "wrote left.png, right.png, calib.toml and thread-truth.json into {}",
        out.display()
    );
    Ok(crate::exit::OK)
}

#[derive(Debug, Serialize)]
struct BenchRow {
    set: EvalSet,
    accuracy: ThreadAccuracy,
    /// Over the pairs with another tool over the thread.
    occluded: ThreadAccuracy,
}

/// `stitch bench thread`.
pub fn bench(args: BenchThreadArgs) -> anyhow::Result<u8> {
    let segmenter = args.segmenter.load()?;
    let params = ThreadParams::default();
    let started = Instant::now();
    let mut rows = Vec::new();
    let mut details = match &args.details {
        Some(p) => Some(std::io::BufWriter::new(
            std::fs::File::create(p).with_context(|| format!("cannot create {}", p.display()))?,
        )),
        None => None,
    };
    for &set in &args.sets {
        let results: Vec<ThreadResult> = match set {
            EvalSet::Own => {
                let (renderer, world) = mock_renderer(args.seed)?;
                let mut samples =
                    eval::own_set(args.frames, args.seed, Needle::default(), &world.phantom());
                if let Some(share) = args.length_prior {
                    eval::give_length_prior(
                        samples.iter_mut().map(|s| &mut s.sample),
                        share,
                        args.seed,
                    );
                }
                eval::run_own(
                    &params,
                    &segmenter as &dyn Segmenter,
                    &renderer,
                    &samples,
                    args.seed,
                )
            }
            EvalSet::Independent => {
                if let Some(d) = &args.render_cache {
                    std::fs::create_dir_all(d)
                        .with_context(|| format!("cannot create {}", d.display()))?;
                }
                let mut samples =
                    eval::independent_set(args.independent_frames, args.seed, Needle::default());
                if let Some(share) = args.length_prior {
                    eval::give_length_prior(samples.iter_mut().map(|(_, t)| t), share, args.seed);
                }
                eval::run_independent(&params, &segmenter, &samples, args.render_cache.as_deref())
            }
        };
        if let Some(d) = &mut details {
            for r in &results {
                serde_json::to_writer(&mut *d, &serde_json::json!({"set": set, "result": r}))?;
                writeln!(d)?;
            }
        }
        let occluded: Vec<ThreadResult> = results.iter().filter(|r| r.occluded).cloned().collect();
        rows.push(BenchRow {
            set,
            accuracy: eval::accuracy(&results),
            occluded: eval::accuracy(&occluded),
        });
    }
    if let Some(d) = &mut details {
        d.flush()?;
    }
    let mut out = std::io::stdout().lock();
    if args.json {
        serde_json::to_writer_pretty(&mut out, &rows)?;
        writeln!(out)?;
    } else {
        writeln!(out, "{}", table(&rows))?;
        writeln!(
            out,
            "segmenter {}, seed {}, {}, {:.0} s in all (rendering included; the time column is \
             the tracer's alone, one core)",
            args.segmenter,
            args.seed,
            match args.length_prior {
                Some(s) => format!("a length prior off by {:.0} % (1σ)", 100.0 * s),
                None => "no length prior".into(),
            },
            started.elapsed().as_secs_f64()
        )?;
    }
    Ok(crate::exit::OK)
}

fn table(rows: &[BenchRow]) -> String {
    let mut s = String::from(
        "| set | pairs | traced | failures | median error (mm) | p90 error (mm) | median length error | true points within 2σ | of them by hidden spans: share, within 2σ | median σ at the truth (mm) | median time (ms) |\n\
         |---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    let line = |name: String, a: &ThreadAccuracy| {
        let failures = if a.failures.is_empty() {
            "none".to_string()
        } else {
            a.failures
                .iter()
                .map(|(k, n)| format!("{k} {n}"))
                .collect::<Vec<_>>()
                .join(", ")
        };
        format!(
            "| {name} | {} | {} | {failures} | {:.2} | {:.2} | {:.1} % | {:.0} % | {:.0} %, {:.0} % | {:.2} | {:.1} |\n",
            a.frames,
            a.traced,
            a.median_error_m * 1e3,
            a.p90_error_m * 1e3,
            a.median_length_error * 100.0,
            a.within_2sigma * 100.0,
            a.hidden_points * 100.0,
            a.within_2sigma_hidden * 100.0,
            a.median_band_sigma_m * 1e3,
            a.median_seconds * 1e3,
        )
    };
    for r in rows {
        let name = match r.set {
            EvalSet::Own => "own",
            EvalSet::Independent => "independent",
        };
        s += &line(name.to_string(), &r.accuracy);
        if r.occluded.frames > 0 {
            s += &line(format!("{name}, a tool over it"), &r.occluded);
        }
    }
    s
}
