//! `stitch sweep SPEC.toml`: a parameter sweep over the mock's configuration, each point a
//! `stitch trials` run (sharded the same way: `--shard K/N` runs shard K of every point, and
//! `stitch sweep merge` merges them point by point), then a table of every point's metrics and
//! a plot of the chosen metric against each parameter (docs/experiments.md, "Sweeps").

use crate::shard::Shard;
use anyhow::{Context, bail};
use rand::Rng;
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use serde::{Deserialize, Serialize};
use std::collections::BTreeMap;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};

#[derive(Debug, clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct SweepArgs {
    #[command(subcommand)]
    command: Option<SweepCommand>,
    /// The sweep: policies, trials, seed, perception, the metric to plot, and a [grid] or
    /// [random] over mock configuration keys (TOML; docs/experiments.md, "Sweeps").
    #[arg(required = true)]
    spec: Option<PathBuf>,
    /// Directory to write points/NNN/ (each a trials run, with its mock.toml), sweep.md,
    /// sweep.csv and one sweep-KEY.svg per parameter into.
    #[arg(long, required = true)]
    out: Option<PathBuf>,
    /// Worker threads per point [default: the cores available].
    #[arg(long)]
    jobs: Option<usize>,
    /// Run only shard K of N of every point's trials (as `stitch trials --shard`); merge the
    /// shards' directories with `stitch sweep merge`.
    #[arg(long, value_name = "K/N")]
    shard: Option<Shard>,
}

#[derive(Debug, clap::Subcommand)]
pub enum SweepCommand {
    /// Merge the directories of one sweep's shards, point by point, into what the sweep
    /// writes on one machine, byte for byte.
    Merge {
        /// The shards' output directories.
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// Directory to write the merged sweep into.
        #[arg(long)]
        out: PathBuf,
    },
}

/// A sweep file.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct Spec {
    /// Policies (script names in scripts/ or paths), as `stitch trials --policies`.
    #[serde(default = "default_policies")]
    policies: Vec<String>,
    /// Trials per policy at each point.
    trials: usize,
    /// The first trial's seed at every point (the points meet the same draws).
    #[serde(default = "one")]
    seed: u64,
    /// `model`, `fitted`, `pipeline` or `perfect`.
    #[serde(default = "model")]
    perception: String,
    /// A mock configuration every point starts from (relative to the sweep file).
    #[serde(default)]
    mock_config: Option<PathBuf>,
    /// The metric plotted: mean_sutures_to_failure, single_suture_success,
    /// three_throw_success, full_wound_success or mean_time_per_suture_s.
    #[serde(default = "default_metric")]
    metric: String,
    /// Every combination of these values (keys are dotted mock configuration keys, or
    /// `param.NAME` for the plans' `param("NAME", default)`).
    #[serde(default)]
    grid: BTreeMap<String, Vec<toml::Value>>,
    /// Or a seeded uniform sample.
    #[serde(default)]
    random: Option<RandomSpec>,
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct RandomSpec {
    /// How many points.
    samples: usize,
    /// The sample's seed.
    seed: u64,
    /// Each key's range, [low, high].
    ranges: BTreeMap<String, [f64; 2]>,
}

fn default_policies() -> Vec<String> {
    vec!["stitch".into()]
}
fn one() -> u64 {
    1
}
fn model() -> String {
    "model".into()
}
fn default_metric() -> String {
    "mean_sutures_to_failure".into()
}

const METRICS: [&str; 5] = [
    "mean_sutures_to_failure",
    "single_suture_success",
    "three_throw_success",
    "full_wound_success",
    "mean_time_per_suture_s",
];

/// Most points a sweep may have.
const MAX_POINTS: usize = 10_000;

/// What the shards of one sweep share and the merge needs: the points, written as
/// `sweep.json` beside them.
#[derive(Debug, PartialEq, Serialize, Deserialize)]
struct Plan {
    keys: Vec<String>,
    /// Each point's value of each key.
    points: Vec<Vec<toml::Value>>,
    metric: String,
}

/// The points of `spec`: the grid's combinations (keys in alphabetical order, the first
/// varying slowest), or the random sample.
fn points(spec: &Spec) -> anyhow::Result<Plan> {
    if !METRICS.contains(&spec.metric.as_str()) {
        bail!(
            "metric {:?}: expected one of {}",
            spec.metric,
            METRICS.join(", ")
        );
    }
    let (keys, points) = match (&spec.random, spec.grid.is_empty()) {
        (Some(_), false) => bail!("give a [grid] or a [random] sample, not both"),
        (None, true) => bail!("no parameters: give a [grid] or a [random] sample"),
        (None, false) => {
            let keys: Vec<String> = spec.grid.keys().cloned().collect();
            let mut points: Vec<Vec<toml::Value>> = vec![vec![]];
            for (k, values) in &spec.grid {
                if values.is_empty() {
                    bail!("grid key {k:?} has no values");
                }
                points = points
                    .into_iter()
                    .flat_map(|p| {
                        values.iter().map(move |v| {
                            let mut q = p.clone();
                            q.push(v.clone());
                            q
                        })
                    })
                    .take(MAX_POINTS + 1)
                    .collect();
            }
            (keys, points)
        }
        (Some(r), true) => {
            if r.ranges.is_empty() {
                bail!("[random] has no ranges");
            }
            for (k, [lo, hi]) in &r.ranges {
                if !(lo.is_finite() && hi.is_finite() && lo <= hi) {
                    bail!("random range {k:?}: [{lo}, {hi}] is not a range");
                }
            }
            let mut rng = ChaCha8Rng::seed_from_u64(r.seed);
            let points = (0..r.samples.min(MAX_POINTS + 1))
                .map(|_| {
                    r.ranges
                        .values()
                        .map(|&[lo, hi]| toml::Value::Float(lo + (hi - lo) * rng.random::<f64>()))
                        .collect()
                })
                .collect();
            (r.ranges.keys().cloned().collect(), points)
        }
    };
    if points.is_empty() || points.len() > MAX_POINTS {
        bail!(
            "{} points: expected 1 to {MAX_POINTS}",
            if points.len() > MAX_POINTS {
                format!("more than {MAX_POINTS}")
            } else {
                "0".into()
            }
        );
    }
    Ok(Plan {
        keys,
        points,
        metric: spec.metric.clone(),
    })
}

/// The prefix of a sweep key that names a plan parameter rather than a mock key.
const PARAM: &str = "param.";

/// A point's plan parameters: its `param.NAME` keys' values.
fn params_of(keys: &[String], values: &[toml::Value]) -> anyhow::Result<stitch_engine::Params> {
    use stitch_engine::ParamValue as V;
    let mut out = stitch_engine::Params::new();
    for (key, value) in keys.iter().zip(values) {
        let Some(name) = key.strip_prefix(PARAM) else {
            continue;
        };
        if !stitch_engine::valid_param_name(name) {
            bail!(
                "{key:?}: a parameter's name is ASCII letters, digits and _, not starting with \
                 a digit"
            );
        }
        let v = match value {
            toml::Value::Integer(i) => V::Int(*i),
            toml::Value::Float(x) => V::Float(*x),
            toml::Value::Boolean(b) => V::Bool(*b),
            toml::Value::String(s) => V::Text(s.clone()),
            other => bail!(
                "{key} = {other}: a parameter's value is an integer, number, boolean or string"
            ),
        };
        out.insert(name.to_string(), v);
    }
    Ok(out)
}

/// `base` with each dotted mock key (not the `param.` ones) set to its value.
fn with_keys(
    base: &toml::Table,
    keys: &[String],
    values: &[toml::Value],
) -> anyhow::Result<toml::Table> {
    let mut t = base.clone();
    for (key, value) in keys.iter().zip(values) {
        if key.starts_with(PARAM) {
            continue;
        }
        let parts: Vec<&str> = key.split('.').collect();
        if parts.iter().any(|p| p.is_empty()) {
            bail!("{key:?} is not a dotted key (e.g. sensing.p_dropout_thread)");
        }
        let mut at = &mut t;
        for p in &parts[..parts.len() - 1] {
            let next = at
                .entry(p.to_string())
                .or_insert_with(|| toml::Value::Table(toml::Table::new()));
            at = next
                .as_table_mut()
                .with_context(|| format!("{key:?}: {p} is a value, not a table"))?;
        }
        at.insert(parts[parts.len() - 1].to_string(), value.clone());
    }
    Ok(t)
}

fn show(v: &toml::Value) -> String {
    match v {
        toml::Value::String(s) => s.clone(),
        other => other.to_string(),
    }
}

pub fn sweep(args: SweepArgs) -> anyhow::Result<u8> {
    if let Some(SweepCommand::Merge { dirs, out }) = &args.command {
        return merge(dirs, out);
    }
    let spec_path = args.spec.clone().context("a sweep file is required")?;
    let out = args.out.clone().context("--out is required")?;
    let text = std::fs::read_to_string(&spec_path)
        .with_context(|| format!("cannot read {}", spec_path.display()))?;
    let spec: Spec =
        toml::from_str(&text).with_context(|| format!("invalid sweep {}", spec_path.display()))?;
    let plan = points(&spec).with_context(|| format!("invalid sweep {}", spec_path.display()))?;
    let perception = crate::PerceptionKind::from_name(&spec.perception).with_context(|| {
        format!(
            "{}: perception {:?}: expected model, fitted, pipeline or perfect",
            spec_path.display(),
            spec.perception
        )
    })?;
    let base: toml::Table = match &spec.mock_config {
        None => toml::Table::new(),
        Some(p) => {
            let p = spec_path.parent().unwrap_or(Path::new(".")).join(p);
            let t = std::fs::read_to_string(&p)
                .with_context(|| format!("cannot read {}", p.display()))?;
            toml::from_str(&t)
                .with_context(|| format!("invalid mock configuration {}", p.display()))?
        }
    };
    // Every point's configuration and parameters, checked before anything runs (the
    // parameters' types and names when the point's trials load the policies).
    let mut configs = Vec::new();
    for (k, values) in plan.points.iter().enumerate() {
        let table = with_keys(&base, &plan.keys, values)
            .with_context(|| format!("{}: point {k}", spec_path.display()))?;
        let text = toml::to_string(&table)?;
        let mock = crate::read_mock_text(&text).with_context(|| {
            format!(
                "{}: point {k} ({}) is not a valid mock configuration",
                spec_path.display(),
                describe(&plan.keys, values)
            )
        })?;
        let params = params_of(&plan.keys, values)
            .with_context(|| format!("{}: point {k}", spec_path.display()))?;
        if !params.is_empty() {
            let loaded = crate::trials::load_policies(&spec.policies, &mock.scene.wound, &params)
                .with_context(|| {
                format!(
                    "{}: point {k} ({})",
                    spec_path.display(),
                    describe(&plan.keys, values)
                )
            })?;
            if loaded.is_none() {
                bail!(
                    "{}: point {k} ({}): a policy's plan is invalid with these parameters",
                    spec_path.display(),
                    describe(&plan.keys, values)
                );
            }
        }
        configs.push((text, params));
    }
    std::fs::create_dir_all(&out).with_context(|| format!("cannot create {}", out.display()))?;
    write(
        &out.join("sweep.json"),
        &(serde_json::to_string_pretty(&plan)? + "\n"),
    )?;
    let started = std::time::Instant::now();
    for (k, (config, params)) in configs.into_iter().enumerate() {
        let dir = point_dir(&out, k);
        std::fs::create_dir_all(&dir)
            .with_context(|| format!("cannot create {}", dir.display()))?;
        let mock = dir.join("mock.toml");
        write(&mock, &config)?;
        eprintln!(
            "point {}/{}: {}",
            k + 1,
            plan.points.len(),
            describe(&plan.keys, &plan.points[k])
        );
        let code = crate::trials::run(crate::trials::Run::of_sweep(
            spec.trials,
            spec.seed,
            spec.policies.clone(),
            args.jobs,
            dir,
            perception,
            mock,
            args.shard,
            params,
        ))
        .with_context(|| format!("point {k} ({})", describe(&plan.keys, &plan.points[k])))?;
        if code != crate::exit::OK {
            return Ok(code);
        }
    }
    if let Some(s) = args.shard {
        eprintln!(
            "sweep shard {s}: {} points in {:.1} s; merge the shards with `stitch sweep merge`",
            plan.points.len(),
            started.elapsed().as_secs_f64()
        );
        return Ok(crate::exit::OK);
    }
    let table = summarize(&out, &plan)?;
    print!("{table}");
    eprintln!(
        "{} points in {:.1} s; wrote {}",
        plan.points.len(),
        started.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(crate::exit::OK)
}

fn point_dir(out: &Path, k: usize) -> PathBuf {
    out.join("points").join(format!("{k:04}"))
}

fn describe(keys: &[String], values: &[toml::Value]) -> String {
    keys.iter()
        .zip(values)
        .map(|(k, v)| format!("{k} = {}", show(v)))
        .collect::<Vec<_>>()
        .join(", ")
}

fn write(path: &Path, text: &str) -> anyhow::Result<()> {
    std::fs::write(path, text).with_context(|| format!("cannot write {}", path.display()))
}

/// `stitch sweep merge DIR… --out OUT`.
fn merge(dirs: &[PathBuf], out: &Path) -> anyhow::Result<u8> {
    let read = |d: &Path| -> anyhow::Result<Plan> {
        let p = d.join("sweep.json");
        let t = std::fs::read_to_string(&p)
            .with_context(|| format!("{}: not a sweep's output (no sweep.json)", d.display()))?;
        serde_json::from_str(&t).with_context(|| format!("{}: not a sweep file", p.display()))
    };
    let plan = read(&dirs[0])?;
    for d in &dirs[1..] {
        if read(d)? != plan {
            bail!(
                "{} and {} are not shards of one sweep (their points differ)",
                dirs[0].display(),
                d.display()
            );
        }
    }
    std::fs::create_dir_all(out).with_context(|| format!("cannot create {}", out.display()))?;
    write(
        &out.join("sweep.json"),
        &(serde_json::to_string_pretty(&plan)? + "\n"),
    )?;
    for k in 0..plan.points.len() {
        let shards: Vec<PathBuf> = dirs.iter().map(|d| point_dir(d, k)).collect();
        let dir = point_dir(out, k);
        crate::shard::merge_quiet(&shards, &dir)
            .with_context(|| format!("point {k} ({})", describe(&plan.keys, &plan.points[k])))?;
        let mock = std::fs::read(shards[0].join("mock.toml"))
            .with_context(|| format!("cannot read {}", shards[0].join("mock.toml").display()))?;
        std::fs::write(dir.join("mock.toml"), mock)
            .with_context(|| format!("cannot write {}", dir.join("mock.toml").display()))?;
    }
    let table = summarize(out, &plan)?;
    print!("{table}");
    eprintln!(
        "merged {} shards of {} points; wrote {}",
        dirs.len(),
        plan.points.len(),
        out.display()
    );
    Ok(crate::exit::OK)
}

/// One policy's metrics at one point, as trials.json has them.
struct Row {
    point: usize,
    policy: String,
    metrics: serde_json::Value,
}

/// The chosen metric's value and 95 % interval (the interval is the value's own for the mean
/// time per suture, which has none).
fn metric_of(m: &serde_json::Value, metric: &str) -> Option<(f64, f64, f64)> {
    let v = &m[metric];
    if let Some(x) = v.as_f64() {
        return Some((x, x, x));
    }
    Some((
        v["value"].as_f64()?,
        v["low"].as_f64()?,
        v["high"].as_f64()?,
    ))
}

/// Write sweep.md, sweep.csv and a plot per parameter from the points' trials.json; the
/// table's text.
fn summarize(out: &Path, plan: &Plan) -> anyhow::Result<String> {
    let mut rows = Vec::new();
    for k in 0..plan.points.len() {
        let p = point_dir(out, k).join("trials.json");
        let t =
            std::fs::read_to_string(&p).with_context(|| format!("cannot read {}", p.display()))?;
        let v: serde_json::Value =
            serde_json::from_str(&t).with_context(|| format!("{}: not JSON", p.display()))?;
        for m in v["metrics"].as_array().into_iter().flatten() {
            rows.push(Row {
                point: k,
                policy: m["policy"].as_str().unwrap_or_default().to_string(),
                metrics: m.clone(),
            });
        }
    }
    let est = |m: &serde_json::Value, key: &str, scale: f64, d: usize| -> String {
        metric_of(m, key).map_or("–".into(), |(v, lo, hi)| {
            if key == "mean_time_per_suture_s" {
                format!("{:.d$} s", v * scale)
            } else {
                format!("{:.d$} [{:.d$}, {:.d$}]", v * scale, lo * scale, hi * scale)
            }
        })
    };
    let mut md = format!(
        "# Sweep\n\n{} points over {}; each point's trials in points/NNNN/ (table.md, trials.json, journals). 95 % intervals in brackets.\n\n| point | {} | policy | mean sutures to failure | single-suture success | full-wound success | mean time per suture |\n|---|{}---|---|---|---|---|\n",
        plan.points.len(),
        plan.keys.join(", "),
        plan.keys.join(" | "),
        "---|".repeat(plan.keys.len())
    );
    let mut csv = format!(
        "point,{},policy,mean_sutures_to_failure,mean_sutures_low,mean_sutures_high,single_suture_success,full_wound_success,mean_time_per_suture_s\n",
        plan.keys.join(",")
    );
    for r in &rows {
        let values: Vec<String> = plan.points[r.point].iter().map(show).collect();
        let _ = writeln!(
            md,
            "| {:04} | {} | {} | {} | {} % | {} % | {} |",
            r.point,
            values.join(" | "),
            r.policy,
            est(&r.metrics, "mean_sutures_to_failure", 1.0, 2),
            est(&r.metrics, "single_suture_success", 100.0, 1),
            est(&r.metrics, "full_wound_success", 100.0, 1),
            est(&r.metrics, "mean_time_per_suture_s", 1.0, 1),
        );
        let num =
            |key: &str| metric_of(&r.metrics, key).map_or(String::new(), |(v, _, _)| v.to_string());
        let (_, lo, hi) = metric_of(&r.metrics, "mean_sutures_to_failure").unwrap_or_default();
        let _ = writeln!(
            csv,
            "{},{},\"{}\",{},{lo},{hi},{},{},{}",
            r.point,
            values
                .iter()
                .map(|v| format!("\"{}\"", v.replace('"', "\"\"")))
                .collect::<Vec<_>>()
                .join(","),
            r.policy.replace('"', "\"\""),
            num("mean_sutures_to_failure"),
            num("single_suture_success"),
            num("full_wound_success"),
            num("mean_time_per_suture_s"),
        );
    }
    write(&out.join("sweep.md"), &md)?;
    write(&out.join("sweep.csv"), &csv)?;
    for (i, key) in plan.keys.iter().enumerate() {
        let svg = plot(plan, i, &rows);
        let name = key.replace(|c: char| !c.is_ascii_alphanumeric() && c != '_', "_");
        write(&out.join(format!("sweep-{name}.svg")), &svg)?;
    }
    Ok(md)
}

/// The plan's metric against parameter `i`: a point and its 95 % interval per point and
/// policy, joined in the parameter's order (values that are not numbers are placed in their
/// order in the sweep).
fn plot(plan: &Plan, i: usize, rows: &[Row]) -> String {
    let x_of = |k: usize| -> f64 {
        let v = &plan.points[k][i];
        v.as_float()
            .or_else(|| v.as_integer().map(|n| n as f64))
            .unwrap_or(k as f64)
    };
    // Each row's policy, x and metric (rows without the metric, e.g. no time per suture
    // where nothing was sutured, are left out).
    let pts: Vec<(&str, f64, (f64, f64, f64))> = rows
        .iter()
        .filter_map(|r| {
            Some((
                r.policy.as_str(),
                x_of(r.point),
                metric_of(&r.metrics, &plan.metric)?,
            ))
        })
        .collect();
    let policies: Vec<&str> = {
        let mut p: Vec<&str> = Vec::new();
        for r in rows {
            if !p.contains(&r.policy.as_str()) {
                p.push(&r.policy);
            }
        }
        p
    };
    let (mut x0, mut x1) = (f64::INFINITY, f64::NEG_INFINITY);
    let (mut y0, mut y1) = (0.0f64, f64::NEG_INFINITY);
    for &(_, x, (_, lo, hi)) in &pts {
        x0 = x0.min(x);
        x1 = x1.max(x);
        y0 = y0.min(lo);
        y1 = y1.max(hi);
    }
    // No spread (one point, or none): a unit range around it.
    if x1 <= x0 || !x1.is_finite() || !x0.is_finite() {
        (x0, x1) = if x0.is_finite() {
            (x0 - 1.0, x0 + 1.0)
        } else {
            (0.0, 1.0)
        };
    }
    if y1 <= y0 || !y1.is_finite() {
        y1 = y0 + 1.0;
    }
    let (w, h) = (720.0, 420.0);
    let (left, right, top, bottom) = (70.0, 20.0, 40.0, 90.0);
    let sx = |x: f64| left + (w - left - right) * (x - x0) / (x1 - x0);
    let sy = |y: f64| top + (h - top - bottom) * (1.0 - (y - y0) / (y1 - y0));
    let esc = |s: &str| s.replace('&', "&amp;").replace('<', "&lt;");
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{h}\" viewBox=\"0 0 {w} {h}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"{w}\" height=\"{h}\" fill=\"white\"/>\n<text x=\"{}\" y=\"22\" text-anchor=\"middle\" font-size=\"15\">{} against {}</text>\n",
        w / 2.0,
        esc(&plan.metric),
        esc(&plan.keys[i])
    );
    for t in 0..=4 {
        let y = y0 + (y1 - y0) * f64::from(t) / 4.0;
        let x = x0 + (x1 - x0) * f64::from(t) / 4.0;
        let _ = writeln!(
            s,
            "<line x1=\"{left}\" x2=\"{}\" y1=\"{:.1}\" y2=\"{:.1}\" stroke=\"#ddd\"/><text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{}</text><text x=\"{:.1}\" y=\"{}\" text-anchor=\"middle\">{}</text>",
            w - right,
            sy(y),
            sy(y),
            left - 6.0,
            sy(y) + 4.0,
            trim(y),
            sx(x),
            h - bottom + 18.0,
            trim(x)
        );
    }
    for (p, name) in policies.iter().enumerate() {
        let c = crate::trials::COLORS[p % crate::trials::COLORS.len()];
        let color = format!("rgb({},{},{})", c[0], c[1], c[2]);
        let mut mine: Vec<(f64, (f64, f64, f64))> = pts
            .iter()
            .filter(|(policy, _, _)| policy == name)
            .map(|&(_, x, m)| (x, m))
            .collect();
        mine.sort_by(|a, b| a.0.total_cmp(&b.0));
        let line: Vec<String> = mine
            .iter()
            .map(|(x, (v, _, _))| format!("{:.1},{:.1}", sx(*x), sy(*v)))
            .collect();
        let _ = writeln!(
            s,
            "<polyline fill=\"none\" stroke=\"{color}\" stroke-width=\"1.5\" points=\"{}\"/>",
            line.join(" ")
        );
        for (x, (v, lo, hi)) in &mine {
            let _ = writeln!(
                s,
                "<line x1=\"{0:.1}\" x2=\"{0:.1}\" y1=\"{1:.1}\" y2=\"{2:.1}\" stroke=\"{color}\"/><circle cx=\"{0:.1}\" cy=\"{3:.1}\" r=\"3\" fill=\"{color}\"/>",
                sx(*x),
                sy(*lo),
                sy(*hi),
                sy(*v)
            );
        }
        let lx = left + 200.0 * p as f64;
        let _ = writeln!(
            s,
            "<rect x=\"{lx:.1}\" y=\"{:.1}\" width=\"12\" height=\"12\" fill=\"{color}\"/><text x=\"{:.1}\" y=\"{:.1}\">{}</text>",
            h - 36.0,
            lx + 16.0,
            h - 26.0,
            esc(name)
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{}</text>",
        left + (w - left - right) / 2.0,
        h - bottom + 38.0,
        esc(&plan.keys[i])
    );
    s += "</svg>\n";
    s
}

/// A tick label: up to four significant decimals, no trailing zeros.
fn trim(v: f64) -> String {
    let s = format!("{v:.4}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" { "0".into() } else { s.into() }
}
