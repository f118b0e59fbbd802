//! The flight recorder in the binary: `stitch run --journal FILE.mcap` streams the run to an
//! MCAP file as it goes (`stitch-recorder`), and `stitch journal` reads, recovers and exports
//! such files, finished or not.

use anyhow::Context;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Duration;
use stitch_engine::Loaded;
use stitch_recorder::{Recorder, RecorderOptions, RunInfo};
use stitch_robot::WoundSpec;

/// Whether `path` names an MCAP journal (by its extension).
pub fn is_mcap(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
}

/// What decides a run, to be recorded with it (and replayed from it).
#[derive(Debug)]
pub struct RunSettings<'a> {
    /// The plan script.
    pub plan: &'a Path,
    /// The seed, where it decides the run.
    pub seed: Option<u64>,
    /// `mock`, `scripted`, `ros2`.
    pub robot: &'static str,
    /// The mock configuration file, if given.
    pub mock_config: Option<&'a Path>,
    /// The outcome schedule replayed, if any.
    pub outcomes: Option<&'a Path>,
    /// The supervisor's command schedule (`--commands`), if any.
    pub commands: Option<&'a Path>,
    /// `--perception`.
    pub perception: &'static str,
    /// `--segmenter`.
    pub segmenter: &'a crate::segmenter::SegmenterChoice,
    /// The wound the plan was evaluated against.
    pub wound: &'a WoundSpec,
    /// The plan as evaluated.
    pub loaded: &'a Loaded,
    /// `--record-frames`, Hz.
    pub frames_hz: f64,
}

/// The metadata and attachments a recording of this run begins with.
pub fn run_info(s: &RunSettings<'_>) -> anyhow::Result<RunInfo> {
    let read = |p: &Path| {
        std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display()))
    };
    let mut settings = BTreeMap::new();
    settings.insert("perception".to_string(), s.perception.to_string());
    settings.insert("segmenter".to_string(), s.segmenter.to_string());
    settings.insert("wound".to_string(), serde_json::to_string(s.wound)?);
    settings.insert(
        "steps_per_throw".to_string(),
        s.loaded
            .plan
            .throws
            .iter()
            .map(|t| t.program.len().to_string())
            .collect::<Vec<_>>()
            .join(","),
    );
    settings.insert("record_frames_hz".to_string(), s.frames_hz.to_string());
    // The values of the plan's parameters, which `stitch replay` gives it again (only when it
    // has any: a plan without parameters records what it always did).
    if !s.loaded.plan.params.is_empty() {
        settings.insert(
            "params".to_string(),
            serde_json::to_string(&s.loaded.plan.params)?,
        );
    }
    let mut files = Vec::new();
    if let Some(p) = s.outcomes {
        files.push((
            OUTCOMES.to_string(),
            "application/json".to_string(),
            read(p)?,
        ));
    }
    if let Some(p) = s.commands {
        files.push((
            COMMANDS.to_string(),
            "application/json".to_string(),
            read(p)?,
        ));
    }
    Ok(RunInfo {
        program: format!("stitch {}", env!("CARGO_PKG_VERSION")),
        plan_file: s.plan.display().to_string(),
        plan_text: read(s.plan)?,
        seed: s.seed,
        robot: s.robot.into(),
        mock_config: s.mock_config.map(read).transpose()?,
        settings,
        files,
    })
}

/// The attachment an outcome schedule is recorded as.
pub const OUTCOMES: &str = "outcomes.json";
/// The attachment a supervisor's command schedule (`--commands`) is recorded as.
pub const COMMANDS: &str = "commands.json";

/// Start recording a run to `path`: its metadata and attachments are on disk before
/// anything moves.
pub fn start(
    path: &Path,
    info: &RunInfo,
    real_time: bool,
    frames_hz: f64,
) -> anyhow::Result<Recorder> {
    if !(frames_hz.is_finite() && frames_hz >= 0.0) {
        anyhow::bail!("--record-frames {frames_hz}: expected a rate ≥ 0 Hz (0: no frames)");
    }
    Recorder::create(
        path,
        info,
        RecorderOptions {
            wall_flush: real_time,
            max_frame_queue_bytes: 0,
            frame_period: (frames_hz > 0.0).then(|| Duration::from_secs_f64(1.0 / frames_hz)),
        },
    )
    .with_context(|| format!("cannot record the journal to {}", path.display()))
}

/// Let the recorder write what is left and the file's summary.
pub fn finish(recorder: Recorder) -> anyhow::Result<()> {
    let path = recorder.path().display().to_string();
    recorder
        .finish()
        .with_context(|| format!("cannot finish the journal {path}"))?;
    Ok(())
}

/// `stitch journal`.
#[derive(Debug, clap::Subcommand)]
pub enum JournalCommand {
    /// The per-throw timeline of a recorded run, as `stitch run` printed it, from a finished
    /// or an unfinished file.
    Show {
        /// The recording (MCAP).
        file: PathBuf,
        /// The rebuilt run as JSON (plan, throws with every attempt, outcome) instead.
        #[arg(long)]
        json: bool,
    },
    /// Write a recorded run's journal as JSON Lines (the records `--journal FILE.jsonl`
    /// writes), from a finished or an unfinished file.
    Export {
        /// The recording (MCAP).
        file: PathBuf,
        /// JSON Lines (the only export format so far).
        #[arg(long, required = true)]
        jsonl: bool,
        /// Write here instead of standard output.
        #[arg(long)]
        out: Option<PathBuf>,
    },
    /// Write a complete file from one a crash or a kill left unfinished: everything up to its
    /// last closed chunk, metadata and attachments included.
    Recover {
        /// The unfinished recording.
        file: PathBuf,
        /// The complete file to write (default: FILE with `.recovered.mcap`).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

/// Run a `stitch journal` command.
pub fn journal(command: JournalCommand) -> anyhow::Result<u8> {
    match command {
        JournalCommand::Show { file, json } => crate::replay::show(&file, json),
        JournalCommand::Export { file, out, .. } => {
            let got = stitch_recorder::read(&file)?;
            if !got.complete {
                eprintln!(
                    "{}: unfinished (the run did not end cleanly): read up to its last closed \
                     chunk, {} records",
                    file.display(),
                    got.records.len()
                );
            }
            let text = stitch_recorder::to_jsonl(&got.records);
            match out {
                Some(path) => std::fs::write(&path, text)
                    .with_context(|| format!("cannot write {}", path.display()))?,
                None => {
                    use std::io::Write;
                    std::io::stdout().lock().write_all(text.as_bytes())?;
                }
            }
            Ok(crate::exit::OK)
        }
        JournalCommand::Recover { file, out } => {
            let out = out.unwrap_or_else(|| file.with_extension("recovered.mcap"));
            let got = stitch_recorder::recover(&file, &out)?;
            eprintln!(
                "{} → {}: {} messages, {} records (the last at {:.3} s), {} attachments{}",
                file.display(),
                out.display(),
                got.messages.len(),
                got.records.len(),
                got.records.last().map_or(0.0, |r| r.t_s),
                got.attachments.len(),
                if got.complete {
                    "; the file was already complete"
                } else {
                    ""
                }
            );
            Ok(crate::exit::OK)
        }
    }
}
