//! The flight recorder in the binary: `stitch run --journal FILE.mcap` streams the run to an
//! MCAP file as it goes (`stitch-recorder`), and `stitch journal` reads, recovers and exports
//! such files, finished or not.

use anyhow::Context;
use std::path::{Path, PathBuf};
use stitch_recorder::{Recorder, RecorderOptions, RunInfo};

/// Whether `path` names an MCAP journal (by its extension).
pub fn is_mcap(path: &Path) -> bool {
    path.extension()
        .is_some_and(|e| e.eq_ignore_ascii_case("mcap"))
}

/// Start recording the run of `plan` to `path`: its metadata and attachments are on disk
/// before anything moves.
pub fn start(
    path: &Path,
    plan: &Path,
    seed: Option<u64>,
    robot: &str,
    mock_config: Option<&Path>,
    real_time: bool,
    frames_hz: f64,
) -> anyhow::Result<Recorder> {
    if !(frames_hz.is_finite() && frames_hz >= 0.0) {
        anyhow::bail!("--record-frames {frames_hz}: expected a rate ≥ 0 Hz (0: no frames)");
    }
    let plan_text =
        std::fs::read_to_string(plan).with_context(|| format!("cannot read {}", plan.display()))?;
    let mock_config = mock_config
        .map(|p| std::fs::read_to_string(p).with_context(|| format!("cannot read {}", p.display())))
        .transpose()?;
    let info = RunInfo {
        program: format!("stitch {}", env!("CARGO_PKG_VERSION")),
        plan_file: plan.display().to_string(),
        plan_text,
        seed,
        robot: robot.into(),
        mock_config,
    };
    Recorder::create(
        path,
        &info,
        RecorderOptions {
            wall_flush: real_time,
            max_frame_queue_bytes: 0,
            frame_period: (frames_hz > 0.0)
                .then(|| std::time::Duration::from_secs_f64(1.0 / frames_hz)),
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
