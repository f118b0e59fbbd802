//! `stitch trials`: the paper's ablation (Table I, Fig. 4) on the mock, in parallel, with
//! every file written deterministically.

use crate::{PerceptionKind, RobotKind, exit, record};
use anyhow::Context;
use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use stitch_engine::trials::{Estimate, Metrics, TrialRecord, metrics};
use stitch_primitives::MockPerception;

/// The policies run by default: the paper's, in its order, then STITCH+.
pub const DEFAULT_POLICIES: [&str; 5] = [
    "sensing_only",
    "thread_handling",
    "stitch",
    "stitch_human",
    "stitch_plus",
];

#[derive(Debug, clap::Args)]
#[command(args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
pub struct TrialsArgs {
    #[command(subcommand)]
    command: Option<TrialsCommand>,
    /// Trials per policy.
    #[arg(long, default_value_t = 15)]
    trials: usize,
    /// Trial i (counted from 0) of every policy runs with seed SEED + i: the policies meet
    /// the same draws (common random numbers), and results do not depend on --jobs.
    #[arg(long, default_value_t = 1)]
    seed: u64,
    /// Policies: names of scripts in scripts/ (without .rhai) or paths to plan scripts.
    #[arg(long, value_delimiter = ',', default_values_t = DEFAULT_POLICIES.map(String::from))]
    policies: Vec<String>,
    /// Worker threads [default: the cores available].
    #[arg(long)]
    jobs: Option<usize>,
    /// Directory to write table.md, trials.csv, trials.json, histogram.svg, histogram.png and
    /// journals/ (one file per trial) into (created if missing).
    #[arg(long, required = true)]
    out: Option<PathBuf>,
    /// Run only shard K of N (K from 1): trial i (from 0) of every policy where i mod N is
    /// K − 1, with seed SEED + i as always; write its records (shard.json) and journals into
    /// --out for `stitch trials merge` (docs/experiments.md, "Running on several machines").
    #[arg(long, value_name = "K/N")]
    shard: Option<crate::shard::Shard>,
    /// How the mock estimates the needle pose (see `stitch run --help`).
    #[arg(long, value_enum, default_value_t = PerceptionKind::Model)]
    perception: PerceptionKind,
    /// The mock's scene, models and faults (TOML; see docs/mock-dvrk.md).
    #[arg(long)]
    mock_config: Option<PathBuf>,
    /// Each trial's journal: `mcap`, the flight recorder's file, streamed while the trial
    /// runs (docs/journal.md), or `jsonl`, the engine's events only, written at its end.
    #[arg(long, value_enum, default_value_t = JournalFormat::Mcap)]
    journal_format: JournalFormat,
    /// With MCAP journals and --perception pipeline: record each trial's stereo pairs
    /// (JPEG) at most this often, Hz; 0 (the default): none.
    #[arg(long, default_value_t = 0.0, value_name = "HZ")]
    record_frames: f64,
    /// The simulated surgeon's commands in every trial (JSON, as `stitch run --commands`):
    /// at simulated times, mid-step included. Without it, none (the paper's trials).
    #[arg(long, value_name = "FILE")]
    commands: Option<PathBuf>,
    /// Plan parameters, as `stitch run --param`, given to every policy; each must be declared
    /// by at least one policy (trials.json lists what each policy ran with).
    #[command(flatten)]
    params: crate::ParamArgs,
}

/// `stitch trials merge`.
#[derive(Debug, clap::Subcommand)]
pub enum TrialsCommand {
    /// Merge the shard directories of one `stitch trials … --shard K/N` run into what the
    /// run would have written on one machine: the same table, CSV, JSON, histograms and
    /// journals, byte for byte. Refuses missing, duplicated or mismatched shards.
    Merge {
        /// The shard directories (each with its shard.json), in any order.
        #[arg(required = true)]
        dirs: Vec<PathBuf>,
        /// Directory to write the merged results into (created if missing).
        #[arg(long)]
        out: PathBuf,
    },
}

/// How `stitch trials` writes each trial's journal.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum, serde::Serialize)]
#[serde(rename_all = "lowercase")]
pub enum JournalFormat {
    /// `journals/POLICY-SEED.mcap`: the flight recorder's file.
    Mcap,
    /// `journals/POLICY-SEED.jsonl`: the engine's events as JSON Lines.
    Jsonl,
}

/// Most trials per policy one command runs (each writes a journal file).
const MAX_TRIALS: usize = 100_000;

/// A row of the paper's Table I.
struct PaperRow {
    mean: f64,
    /// Single-suture, three-throw and full-wound success, %.
    success: [f64; 3],
    time_s: f64,
    errors: [u32; 4],
    to_intervention: Option<f64>,
}

/// The paper's Table I row of a policy, by plan name.
fn paper_row(name: &str) -> Option<PaperRow> {
    let row = |mean, success, time_s, errors, to_intervention| PaperRow {
        mean,
        success,
        time_s,
        errors,
        to_intervention,
    };
    match name {
        "Sensing Only" => Some(row(1.40, [51.6, 0.0, 0.0], 106.8, [9, 6, 0, 0], None)),
        "Thread Handling" => Some(row(1.80, [55.9, 20.0, 0.0], 117.9, [6, 5, 2, 2], None)),
        "STITCH" => Some(row(2.93, [69.4, 73.3, 0.0], 159.3, [8, 5, 0, 2], None)),
        "STITCH + Human" => Some(row(
            4.47,
            [83.3, 100.0, 20.0],
            141.9,
            [16, 10, 0, 2],
            Some(2.25),
        )),
        _ => None,
    }
}

/// One trial's outcome as a worker leaves it (its journal already written).
type TrialResult = anyhow::Result<TrialRecord>;

pub(crate) struct Policy {
    /// As given on the command line (file names use it).
    key: String,
    /// The plan's mission name.
    name: String,
    loaded: stitch_engine::Loaded,
    /// The plan script.
    path: PathBuf,
}

/// One `stitch trials` run, as the command line or a sweep's point gives it.
#[derive(Clone, Debug)]
pub struct Run {
    pub trials: usize,
    pub seed: u64,
    pub policies: Vec<String>,
    pub jobs: Option<usize>,
    pub out: PathBuf,
    pub perception: PerceptionKind,
    pub mock_config: Option<PathBuf>,
    pub shard: Option<crate::shard::Shard>,
    pub journal_format: JournalFormat,
    pub record_frames: f64,
    pub commands: Option<PathBuf>,
    /// Values for the policies' `param(name, default)` calls.
    pub params: stitch_engine::Params,
    /// Print no table (a sweep prints its own).
    pub quiet: bool,
}

impl Run {
    /// A run with the command line's defaults for what a sweep does not set.
    #[allow(clippy::too_many_arguments)]
    pub fn of_sweep(
        trials: usize,
        seed: u64,
        policies: Vec<String>,
        jobs: Option<usize>,
        out: PathBuf,
        perception: PerceptionKind,
        mock_config: PathBuf,
        shard: Option<crate::shard::Shard>,
        params: stitch_engine::Params,
    ) -> Self {
        Self {
            trials,
            seed,
            policies,
            jobs,
            out,
            perception,
            mock_config: Some(mock_config),
            shard,
            journal_format: JournalFormat::Mcap,
            record_frames: 0.0,
            commands: None,
            params,
            quiet: true,
        }
    }
}

pub fn trials(args: TrialsArgs) -> anyhow::Result<u8> {
    if let Some(TrialsCommand::Merge { dirs, out }) = &args.command {
        return crate::shard::merge(dirs, out);
    }
    run(Run {
        out: args.out.clone().context("--out is required")?,
        trials: args.trials,
        seed: args.seed,
        policies: args.policies,
        jobs: args.jobs,
        perception: args.perception,
        mock_config: args.mock_config,
        shard: args.shard,
        journal_format: args.journal_format,
        record_frames: args.record_frames,
        commands: args.commands,
        params: args.params.get()?,
        quiet: false,
    })
}

/// Run `args`' trials and write their files (or, with a shard, the shard's).
pub fn run(args: Run) -> anyhow::Result<u8> {
    let out = args.out.clone();
    if !(1..=MAX_TRIALS).contains(&args.trials) {
        anyhow::bail!("--trials {}: expected 1 to {MAX_TRIALS}", args.trials);
    }
    if args.seed.checked_add(args.trials as u64).is_none() {
        anyhow::bail!(
            "--seed {} with --trials {}: the seeds would pass 2^64",
            args.seed,
            args.trials
        );
    }
    if args.policies.is_empty() {
        anyhow::bail!("--policies names no policy");
    }
    let mock = crate::read_mock_config(args.mock_config.as_deref())?;
    // Read once, refused before any trial runs.
    if let Some(path) = &args.commands {
        crate::read_commands(path)?;
    }
    let Some(policies) = load_policies(&args.policies, &mock.scene.wound, &args.params)? else {
        return Ok(exit::INVALID_PLAN);
    };
    std::fs::create_dir_all(out.join("journals"))
        .with_context(|| format!("cannot create {}", out.display()))?;
    if args.record_frames != 0.0 && args.journal_format != JournalFormat::Mcap {
        anyhow::bail!("--record-frames records into MCAP journals: drop --journal-format jsonl");
    }
    let perception = args
        .perception
        .of(&mock, &crate::segmenter::SegmenterChoice::Classical)?;
    let shard = args.shard;
    let jobs: Vec<(usize, u64)> = (0..policies.len())
        .flat_map(|p| {
            (0..args.trials as u64)
                .filter(move |&i| shard.is_none_or(|s| s.holds(i)))
                .map(move |i| (p, args.seed + i))
        })
        .collect();
    if jobs.is_empty() {
        // A shard past the trials (--shard 9/10 of 5 trials): nothing to run, still a shard.
        let shard = shard.context("no trials to run")?;
        crate::shard::write(&out, shard, &settings(&args, &policies)?, &[])?;
        eprintln!(
            "shard {shard}: no trials fall to it; wrote {}",
            out.display()
        );
        return Ok(exit::OK);
    }
    let workers = args
        .jobs
        .unwrap_or_else(|| std::thread::available_parallelism().map_or(1, |n| n.get()))
        .clamp(1, jobs.len());
    let started = std::time::Instant::now();
    let bar = indicatif::ProgressBar::new(jobs.len() as u64);
    bar.set_style(
        indicatif::ProgressStyle::with_template("{bar:40} {pos}/{len} trials, {elapsed} {msg}")
            .unwrap_or_else(|_| indicatif::ProgressStyle::default_bar()),
    );
    let results: Mutex<Vec<Option<TrialResult>>> =
        Mutex::new((0..jobs.len()).map(|_| None).collect());
    let next = AtomicUsize::new(0);
    let done = AtomicUsize::new(0);
    // In a batch log (no terminal) the bar draws nothing: plain lines, about every 5 %.
    let lines = !std::io::IsTerminal::is_terminal(&std::io::stderr());
    let every = jobs.len().div_ceil(20).max(1);
    let label = shard.map_or_else(|| "trials".to_string(), |s| format!("shard {s}"));
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                loop {
                    let j = next.fetch_add(1, Ordering::Relaxed);
                    let Some(&(p, seed)) = jobs.get(j) else { break };
                    let policy = &policies[p];
                    let result = trial(policy, seed, &args, &out, &mock, &perception);
                    results
                        .lock()
                        .unwrap_or_else(std::sync::PoisonError::into_inner)[j] = Some(result);
                    bar.inc(1);
                    let n = done.fetch_add(1, Ordering::Relaxed) + 1;
                    if lines && (n % every == 0 || n == jobs.len()) {
                        eprintln!(
                            "{label}: {n}/{} trials done, {:.1} s",
                            jobs.len(),
                            started.elapsed().as_secs_f64()
                        );
                    }
                }
            });
        }
    });
    bar.finish_and_clear();
    let results = results
        .into_inner()
        .unwrap_or_else(std::sync::PoisonError::into_inner);
    let mut records: Vec<Vec<TrialRecord>> = policies.iter().map(|_| Vec::new()).collect();
    for (&(p, seed), r) in jobs.iter().zip(results) {
        let record = r.context("a trial did not run")?.with_context(|| {
            format!(
                "trial {} of {} (seed {seed})",
                seed - args.seed + 1,
                policies[p].key
            )
        })?;
        records[p].push(record);
    }
    let took = |what: &str| {
        eprintln!(
            "{} trials of {} policies in {:.1} s on {workers} threads; wrote {what}{}",
            jobs.len(),
            policies.len(),
            started.elapsed().as_secs_f64(),
            out.display()
        );
    };
    if let Some(shard) = shard {
        crate::shard::write(&out, shard, &settings(&args, &policies)?, &records)?;
        took(&format!("shard {shard} into "));
        return Ok(exit::OK);
    }
    let summary = Summary {
        seed: args.seed,
        trials: args.trials,
        perception: perception_name(args.perception),
        policies: policies.iter().map(|p| p.name.clone()).collect(),
        params: policies
            .iter()
            .map(|p| p.loaded.plan.params.clone())
            .collect(),
    };
    let table = write_results(&out, &summary, &records)?;
    if !args.quiet {
        print!("{table}");
    }
    took("");
    Ok(exit::OK)
}

/// The policies' plans, evaluated with `params` and validated (`None`, errors printed, if a
/// plan is invalid); a parameter no policy declares is refused.
pub(crate) fn load_policies(
    keys: &[String],
    wound: &stitch_robot::WoundSpec,
    params: &stitch_engine::Params,
) -> anyhow::Result<Option<Vec<Policy>>> {
    let mut policies = Vec::new();
    for key in keys {
        let path = if key.ends_with(".rhai") {
            PathBuf::from(key)
        } else {
            Path::new("scripts").join(format!("{key}.rhai"))
        };
        if !path.is_file() {
            anyhow::bail!(
                "unknown policy {key:?}: no {} (the policies are the scripts in scripts/: {})",
                path.display(),
                DEFAULT_POLICIES.join(", ")
            );
        }
        let Some(loaded) = crate::load(&path, wound, params, false)? else {
            return Ok(None);
        };
        let key = path
            .file_stem()
            .map_or_else(|| key.clone(), |s| s.to_string_lossy().into_owned());
        policies.push(Policy {
            key,
            name: loaded.plan.name.clone(),
            loaded,
            path,
        });
    }
    // A value no policy asks for would change nothing: refused, not silently ignored.
    for name in params.keys() {
        if policies.iter().all(|p| !p.loaded.params.contains_key(name)) {
            anyhow::bail!(
                "--param {name}: no policy declares it ({})",
                policies
                    .iter()
                    .map(|p| format!("{}: {}", p.key, crate::declared_params(&p.loaded)))
                    .collect::<Vec<_>>()
                    .join("; ")
            );
        }
    }
    Ok(Some(policies))
}

/// What the results' files say about the run besides its records.
#[derive(Clone, Debug, PartialEq)]
pub struct Summary {
    /// The first trial's seed.
    pub seed: u64,
    /// Trials per policy.
    pub trials: usize,
    /// `--perception`, as trials.json writes it.
    pub perception: String,
    /// The policies' plan names, in their order.
    pub policies: Vec<String>,
    /// Each policy's parameters (`param(name, default)`) as it ran with them, in that order.
    pub params: Vec<stitch_engine::Params>,
}

fn perception_name(p: PerceptionKind) -> String {
    format!("{p:?}").to_lowercase()
}

/// Everything that decides a trial's record and journal besides its seed, and the program:
/// shards of one run must agree on all of it (`stitch trials merge` compares).
fn settings(args: &Run, policies: &[Policy]) -> anyhow::Result<serde_json::Value> {
    use sha2::Digest as _;
    let hash = |p: &Path| -> anyhow::Result<String> {
        let bytes = std::fs::read(p).with_context(|| format!("cannot read {}", p.display()))?;
        Ok(sha2::Sha256::digest(&bytes)
            .iter()
            .map(|b| format!("{b:02x}"))
            .collect())
    };
    let mut plans = Vec::new();
    for p in policies {
        plans.push(serde_json::json!({
            "key": p.key,
            "name": p.name,
            "plan_sha256": hash(&p.path)?,
            "params": p.loaded.plan.params,
        }));
    }
    Ok(serde_json::json!({
        "program": crate::shard::PROGRAM,
        "seed": args.seed,
        "trials_per_policy": args.trials,
        "policies": plans,
        "perception": perception_name(args.perception),
        "mock_config_sha256": args.mock_config.as_deref().map(hash).transpose()?,
        "commands_sha256": args.commands.as_deref().map(hash).transpose()?,
        "journal_format": args.journal_format,
        "record_frames_hz": args.record_frames,
    }))
}

/// Write table.md, trials.csv, trials.json, histogram.svg and histogram.png into `out` from
/// every policy's records (in seed order); the table's text. One run on one machine and a
/// merge of its shards both end here, so their files are the same bytes.
pub fn write_results(
    out: &Path,
    summary: &Summary,
    records: &[Vec<TrialRecord>],
) -> anyhow::Result<String> {
    let all: Vec<Metrics> = summary
        .policies
        .iter()
        .zip(records)
        .map(|(name, r)| metrics(name, r))
        .collect();
    let write = |name: &str, text: &[u8]| {
        let path = out.join(name);
        std::fs::write(&path, text).with_context(|| format!("cannot write {}", path.display()))
    };
    let table = table_md(&all, summary);
    write("table.md", table.as_bytes())?;
    write("trials.csv", csv(records).as_bytes())?;
    let mut json = serde_json::json!({
        "seed": summary.seed,
        "trials_per_policy": summary.trials,
        "perception": summary.perception,
        "seeds": "trial i (from 0) of every policy runs with seed + i",
        "metrics": all,
        "trials": records.iter().flatten().collect::<Vec<_>>(),
    });
    // Only where a policy has parameters: a run without them writes what it always did.
    if summary.params.iter().any(|p| !p.is_empty()) {
        json["params"] = serde_json::Value::Array(
            summary
                .policies
                .iter()
                .zip(&summary.params)
                .map(|(name, p)| serde_json::json!({ "policy": name, "params": p }))
                .collect(),
        );
    }
    write(
        "trials.json",
        (serde_json::to_string_pretty(&json)? + "\n").as_bytes(),
    )?;
    let hist = histogram(&summary.policies, records);
    write("histogram.svg", histogram_svg(&hist).as_bytes())?;
    crate::plot::histogram_png(&out.join("histogram.png"), &hist)?;
    Ok(table)
}

/// One trial, its journal written as it runs (MCAP) or at its end (JSON Lines): memory holds
/// only the records, however many trials run.
fn trial(
    policy: &Policy,
    seed: u64,
    args: &Run,
    out: &Path,
    mock: &crate::MockConfig,
    perception: &MockPerception,
) -> TrialResult {
    let ext = match args.journal_format {
        JournalFormat::Mcap => "mcap",
        JournalFormat::Jsonl => "jsonl",
    };
    let path = out
        .join("journals")
        .join(format!("{}-{seed}.{ext}", policy.key));
    let recorder = match args.journal_format {
        JournalFormat::Mcap => {
            // What `stitch run POLICY --seed SEED --journal FILE.mcap` records: the same file.
            let info = record::run_info(&record::RunSettings {
                plan: &policy.path,
                seed: Some(seed),
                robot: RobotKind::Mock.name(),
                mock_config: args.mock_config.as_deref(),
                outcomes: None,
                commands: args.commands.as_deref(),
                perception: args.perception.name(),
                segmenter: &crate::segmenter::SegmenterChoice::Classical,
                wound: &mock.scene.wound,
                loaded: &policy.loaded,
                frames_hz: args.record_frames,
            })?;
            Some(record::start(&path, &info, false, args.record_frames)?)
        }
        JournalFormat::Jsonl => None,
    };
    let report = crate::run_mock(
        &policy.loaded,
        &mock.scene,
        perception.clone(),
        seed,
        recorder.as_ref(),
        &crate::Supervision {
            commands: args
                .commands
                .as_deref()
                .map(crate::read_commands)
                .transpose()?
                .unwrap_or_default(),
            ..crate::Supervision::default()
        },
    )?;
    let record = TrialRecord::from_report(&policy.name, seed, &policy.loaded.plan, &report);
    match recorder {
        Some(r) => record::finish(r)?,
        None => {
            let file = std::fs::File::create(&path)
                .with_context(|| format!("cannot write {}", path.display()))?;
            report
                .journal
                .write_jsonl(std::io::BufWriter::new(file))
                .with_context(|| format!("cannot write {}", path.display()))?;
        }
    }
    Ok(record)
}

fn ci(e: &Estimate, scale: f64, digits: usize) -> String {
    format!(
        "{:.d$} [{:.d$}, {:.d$}]",
        e.value * scale,
        e.low * scale,
        e.high * scale,
        d = digits
    )
}

fn table_md(all: &[Metrics], args: &Summary) -> String {
    let mut s = String::new();
    let _ = writeln!(
        s,
        "# Table I on the mock dVRK\n\n{} trials per policy, seeds {}–{} (trial i, counted from 0, of every policy uses seed {} + i), perception `{}`. 95 % intervals in brackets. Each policy's row from this run is followed by the paper's (15 physical trials).\n",
        args.trials,
        args.seed,
        args.seed + args.trials as u64 - 1,
        args.seed,
        args.perception
    );
    for (name, params) in args.policies.iter().zip(&args.params) {
        if !params.is_empty() {
            let values: Vec<String> = params.iter().map(|(k, v)| format!("{k} = {v}")).collect();
            let _ = writeln!(s, "Parameters of {name}: {}.\n", values.join(", "));
        }
    }
    s += "| policy | mean sutures to failure | single-suture success | three-throw success | full-wound success | mean time per suture | I | E | H | T | mean sutures to intervention |\n|---|---|---|---|---|---|---|---|---|---|---|\n";
    for m in all {
        let _ = writeln!(
            s,
            "| {} | {} | {} % | {} % | {} % | {} | {} | {} | {} | {} | {} |",
            m.policy,
            ci(&m.mean_sutures_to_failure, 1.0, 2),
            ci(&m.single_suture_success, 100.0, 1),
            ci(&m.three_throw_success, 100.0, 1),
            ci(&m.full_wound_success, 100.0, 1),
            m.mean_time_per_suture_s
                .map_or("–".into(), |t| format!("{t:.1} s")),
            m.errors[0],
            m.errors[1],
            m.errors[2],
            m.errors[3],
            m.mean_sutures_to_intervention
                .map_or("–".into(), |v| format!("{v:.2}")),
        );
        if let Some(p) = paper_row(&m.policy) {
            let _ = writeln!(
                s,
                "| *paper* | *{:.2}* | *{:.1} %* | *{:.1} %* | *{:.1} %* | *{:.1} s* | *{}* | *{}* | *{}* | *{}* | *{}* |",
                p.mean,
                p.success[0],
                p.success[1],
                p.success[2],
                p.time_s,
                p.errors[0],
                p.errors[1],
                p.errors[2],
                p.errors[3],
                p.to_intervention.map_or("–".into(), |v| format!("{v:.2}"))
            );
        }
    }
    s += "\nMetrics (the paper's definitions, made exact):\n\n\
- **mean sutures to failure**: the mean over trials of the throws completed before the trial ended (Student's t interval);\n\
- **single-suture success**: all completed throws over all suture attempts, an attempt being a completed throw or an error (Wilson interval);\n\
- **three-throw success**: the share of trials with at least three completed throws (Wilson);\n\
- **full-wound success**: the share of trials that completed every throw (Wilson);\n\
- **mean time per suture**: all simulated time over all completed throws (no interval);\n\
- **I, E, H, T**: errors by class: the trial-ending error and every error that led to an intervention (insertion, extraction, handover, thread management, as the engine classes them);\n\
- **mean sutures to intervention**: over every intervention request, the throws completed since the previous request or the trial's start.\n\
\nThe paper's numbers are physical trials, 15 per policy; the mock's are simulated (docs/experiments.md says which of its parameters are physical and which are modelling choices).\n";
    s
}

fn csv(records: &[Vec<TrialRecord>]) -> String {
    let mut s = String::from(
        "policy,seed,throws,sutures,outcome,failure,errors_I,errors_E,errors_H,errors_T,interventions,duration_s,time_per_suture_s,entry_error_mm,exit_error_mm\n",
    );
    let opt = |v: Option<f64>, d: usize| v.map_or(String::new(), |v| format!("{v:.d$}"));
    for r in records.iter().flatten() {
        let _ = writeln!(
            s,
            "\"{}\",{},{},{},{},{},{},{},{},{},{},{:.3},{},{},{}",
            r.policy.replace('"', "\"\""),
            r.seed,
            r.throws,
            r.sutures,
            r.outcome,
            r.failure.as_deref().unwrap_or(""),
            r.errors[0],
            r.errors[1],
            r.errors[2],
            r.errors[3],
            r.interventions,
            r.duration_s,
            opt((r.sutures > 0).then(|| r.duration_s / r.sutures as f64), 3),
            opt(r.entry_error_mm, 4),
            opt(r.exit_error_mm, 4),
        );
    }
    s
}

/// Per policy, trials by sutures to failure (0 to the most throws).
pub struct Histogram {
    pub policies: Vec<String>,
    /// `counts[p][k]`: trials of policy p with k sutures.
    pub counts: Vec<Vec<u32>>,
}

fn histogram(names: &[String], records: &[Vec<TrialRecord>]) -> Histogram {
    let most = records
        .iter()
        .flatten()
        .map(|r| r.throws.max(r.sutures))
        .max()
        .unwrap_or(6);
    let counts = records
        .iter()
        .map(|rs| {
            let mut c = vec![0u32; most + 1];
            for r in rs {
                c[r.sutures] += 1;
            }
            c
        })
        .collect();
    Histogram {
        policies: names.to_vec(),
        counts,
    }
}

/// The bar colours, one per policy (colour-blind-safe Okabe–Ito).
pub const COLORS: [[u8; 3]; 6] = [
    [230, 159, 0],
    [86, 180, 233],
    [0, 158, 115],
    [213, 94, 0],
    [204, 121, 167],
    [0, 114, 178],
];

fn histogram_svg(h: &Histogram) -> String {
    let (w, ht) = (720.0, 420.0);
    let (left, right, top, bottom) = (60.0, 20.0, 40.0, 90.0);
    let groups = h.counts.first().map_or(1, Vec::len);
    let most = h.counts.iter().flatten().copied().max().unwrap_or(1).max(1);
    let gw = (w - left - right) / groups as f64;
    let bw = gw * 0.8 / h.policies.len().max(1) as f64;
    let y = |v: f64| top + (ht - top - bottom) * (1.0 - v / most as f64);
    let mut s = format!(
        "<svg xmlns=\"http://www.w3.org/2000/svg\" width=\"{w}\" height=\"{ht}\" viewBox=\"0 0 {w} {ht}\" font-family=\"sans-serif\" font-size=\"12\">\n<rect width=\"{w}\" height=\"{ht}\" fill=\"white\"/>\n<text x=\"{}\" y=\"22\" text-anchor=\"middle\" font-size=\"15\">Sutures to failure by policy</text>\n",
        w / 2.0
    );
    for t in 0..=most {
        let yy = y(f64::from(t));
        let _ = writeln!(
            s,
            "<line x1=\"{left}\" x2=\"{}\" y1=\"{yy:.1}\" y2=\"{yy:.1}\" stroke=\"#ddd\"/><text x=\"{}\" y=\"{:.1}\" text-anchor=\"end\">{t}</text>",
            w - right,
            left - 6.0,
            yy + 4.0
        );
    }
    for k in 0..groups {
        let gx = left + gw * k as f64 + gw * 0.1;
        for (p, counts) in h.counts.iter().enumerate() {
            let c = COLORS[p % COLORS.len()];
            let v = f64::from(counts[k]);
            let _ = writeln!(
                s,
                "<rect x=\"{:.1}\" y=\"{:.1}\" width=\"{bw:.1}\" height=\"{:.1}\" fill=\"rgb({},{},{})\"/>",
                gx + bw * p as f64,
                y(v),
                y(0.0) - y(v),
                c[0],
                c[1],
                c[2]
            );
        }
        let _ = writeln!(
            s,
            "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">{k}</text>",
            left + gw * (k as f64 + 0.5),
            y(0.0) + 16.0
        );
    }
    let _ = writeln!(
        s,
        "<text x=\"{:.1}\" y=\"{:.1}\" text-anchor=\"middle\">sutures to failure</text>\n<text x=\"16\" y=\"{:.1}\" transform=\"rotate(-90 16 {:.1})\" text-anchor=\"middle\">trials</text>",
        left + (w - left - right) / 2.0,
        y(0.0) + 34.0,
        (top + ht - bottom) / 2.0,
        (top + ht - bottom) / 2.0
    );
    for (p, name) in h.policies.iter().enumerate() {
        let c = COLORS[p % COLORS.len()];
        let x = left + 160.0 * p as f64;
        let yy = ht - 26.0;
        let _ = writeln!(
            s,
            "<rect x=\"{x:.1}\" y=\"{:.1}\" width=\"12\" height=\"12\" fill=\"rgb({},{},{})\"/><text x=\"{:.1}\" y=\"{yy:.1}\">{}</text>",
            yy - 10.0,
            c[0],
            c[1],
            c[2],
            x + 16.0,
            name.replace('&', "&amp;").replace('<', "&lt;")
        );
    }
    s += "</svg>\n";
    s
}
