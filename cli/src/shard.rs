//! `stitch trials --shard K/N` and `stitch trials merge`: one run of trials split over
//! machines (a cluster's job array, a Ray job) and put back together, byte for byte what one
//! machine writes.
//!
//! Trial i (from 0) of every policy runs with seed SEED + i whatever the split, so a shard
//! is just the trials with i mod N = K − 1. A shard writes its journals and `shard.json`:
//! the settings every shard must share (program, seed, trials, plans' hashes, perception,
//! mock configuration, commands, journal format) and its trials' records. The merge checks
//! that the shards are one run's, all there, each once, and writes the results through the
//! same code as a run on one machine.

use anyhow::{Context, bail};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};
use stitch_engine::trials::TrialRecord;

/// The program, as shards record it: shards from other builds are not merged.
pub const PROGRAM: &str = concat!(
    "stitch ",
    env!("CARGO_PKG_VERSION"),
    " ",
    env!("STITCH_BUILD")
);

/// What a shard directory's `shard.json` starts with.
const FORMAT: &str = "stitch trials shard, version 1";

/// The file a shard writes beside its journals.
pub const SHARD_FILE: &str = "shard.json";

/// Shard K of N (K from 1).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shard {
    /// Which, from 1.
    pub k: u32,
    /// Of how many.
    pub n: u32,
}

/// Most shards a run is split into.
const MAX_SHARDS: u32 = 1_000_000;

impl Shard {
    /// 1 ≤ K ≤ N ≤ [`MAX_SHARDS`].
    fn valid(self) -> bool {
        (1..=self.n).contains(&self.k) && self.n <= MAX_SHARDS
    }

    /// Whether trial `i` (from 0) falls to this shard.
    pub fn holds(self, i: u64) -> bool {
        i % u64::from(self.n) == u64::from(self.k - 1)
    }
}

impl std::fmt::Display for Shard {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.k, self.n)
    }
}

impl std::str::FromStr for Shard {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("{s:?}: expected K/N with 1 ≤ K ≤ N ≤ {MAX_SHARDS}, e.g. 2/8");
        let (k, n) = s.split_once('/').ok_or_else(bad)?;
        let (k, n): (u32, u32) = (
            k.trim().parse().map_err(|_| bad())?,
            n.trim().parse().map_err(|_| bad())?,
        );
        let shard = Shard { k, n };
        if !shard.valid() {
            return Err(bad());
        }
        Ok(shard)
    }
}

#[derive(Debug, Serialize, Deserialize)]
struct ShardFile {
    format: String,
    shard: Shard,
    settings: serde_json::Value,
    /// Per policy, in the run's order, its trials' records in seed order.
    records: Vec<Vec<TrialRecord>>,
}

/// Write `shard.json` into `out` (the journals are already there).
pub fn write(
    out: &Path,
    shard: Shard,
    settings: &serde_json::Value,
    records: &[Vec<TrialRecord>],
) -> anyhow::Result<()> {
    let file = ShardFile {
        format: FORMAT.into(),
        shard,
        settings: settings.clone(),
        records: records.to_vec(),
    };
    let path = out.join(SHARD_FILE);
    std::fs::write(&path, serde_json::to_string(&file)? + "\n")
        .with_context(|| format!("cannot write {}", path.display()))
}

fn read(dir: &Path) -> anyhow::Result<ShardFile> {
    let path = dir.join(SHARD_FILE);
    let text = std::fs::read_to_string(&path).with_context(|| {
        format!(
            "{}: not a shard directory (no readable {SHARD_FILE}; is the shard still running?)",
            dir.display()
        )
    })?;
    let file: ShardFile = serde_json::from_str(&text)
        .with_context(|| format!("{}: not a shard file", path.display()))?;
    if !file.shard.valid() {
        bail!(
            "{}: shard {}: expected K/N with 1 ≤ K ≤ N ≤ {MAX_SHARDS}",
            path.display(),
            file.shard
        );
    }
    if file.format != FORMAT {
        bail!("{}: {:?}, expected {FORMAT:?}", path.display(), file.format);
    }
    Ok(file)
}

/// The first setting in which `b` differs from `a`, with both values.
fn first_difference(a: &serde_json::Value, b: &serde_json::Value) -> Option<String> {
    let (Some(a), Some(b)) = (a.as_object(), b.as_object()) else {
        return (a != b).then(|| format!("{a} against {b}"));
    };
    let mut keys: Vec<&String> = a.keys().chain(b.keys()).collect();
    keys.sort();
    keys.dedup();
    keys.into_iter().find_map(|k| {
        let (x, y) = (&a.get(k), &b.get(k));
        (x != y).then(|| {
            let show =
                |v: &Option<&serde_json::Value>| v.map_or("nothing".into(), |v| v.to_string());
            format!("{k}: {} against {}", show(x), show(y))
        })
    })
}

/// `stitch trials merge DIR… --out OUT`: the table printed.
pub fn merge(dirs: &[PathBuf], out: &Path) -> anyhow::Result<u8> {
    let table = merge_quiet(dirs, out)?;
    print!("{table}");
    Ok(crate::exit::OK)
}

/// Merge the shard directories `dirs` into `out`; the table's text.
pub fn merge_quiet(dirs: &[PathBuf], out: &Path) -> anyhow::Result<String> {
    let started = std::time::Instant::now();
    let mut shards: Vec<(PathBuf, ShardFile)> = Vec::new();
    for d in dirs {
        shards.push((d.clone(), read(d)?));
    }
    let (first_dir, first) = &shards[0];
    let n = first.shard.n;
    for (dir, s) in &shards[1..] {
        if let Some(diff) = first_difference(&first.settings, &s.settings) {
            bail!(
                "{} and {} are not shards of one run: {diff}",
                first_dir.display(),
                dir.display()
            );
        }
        if s.shard.n != n {
            bail!(
                "{} is shard {} and {} is shard {}: not one split",
                first_dir.display(),
                first.shard,
                dir.display(),
                s.shard
            );
        }
    }
    let mut seen: Vec<Option<&Path>> = vec![None; n as usize];
    for (dir, s) in &shards {
        let slot = &mut seen[(s.shard.k - 1) as usize];
        if let Some(other) = slot {
            bail!(
                "shard {} twice: {} and {}",
                s.shard,
                other.display(),
                dir.display()
            );
        }
        *slot = Some(dir);
    }
    let missing: Vec<String> = (1..=n)
        .filter(|k| seen[(k - 1) as usize].is_none())
        .map(|k| format!("{k}/{n}"))
        .collect();
    eprintln!(
        "shards done: {} of {n}{}",
        shards.len(),
        if missing.is_empty() {
            String::new()
        } else {
            format!("; missing {}", missing.join(", "))
        }
    );
    if !missing.is_empty() {
        bail!(
            "cannot merge: shard{} {} of the run {} not here",
            if missing.len() > 1 { "s" } else { "" },
            missing.join(", "),
            if missing.len() > 1 { "are" } else { "is" }
        );
    }
    let settings = &first.settings;
    let seed = settings["seed"]
        .as_u64()
        .context("shard settings: no seed")?;
    let trials = settings["trials_per_policy"]
        .as_u64()
        .context("shard settings: no trials")? as usize;
    let policies: Vec<String> = settings["policies"]
        .as_array()
        .context("shard settings: no policies")?
        .iter()
        .map(|p| p["name"].as_str().unwrap_or_default().to_string())
        .collect();
    let mut records: Vec<Vec<TrialRecord>> = vec![Vec::new(); policies.len()];
    for (dir, s) in &shards {
        if s.records.len() != policies.len() && !s.records.is_empty() {
            bail!(
                "{}: records for {} policies, the run has {}",
                dir.display(),
                s.records.len(),
                policies.len()
            );
        }
        for (p, rs) in s.records.iter().enumerate() {
            for r in rs {
                let i = r.seed.checked_sub(seed).filter(|&i| (i as usize) < trials);
                if i.is_none_or(|i| !s.shard.holds(i)) || r.policy != policies[p] {
                    bail!(
                        "{}: a record of {} with seed {} does not belong to shard {}",
                        dir.display(),
                        r.policy,
                        r.seed,
                        s.shard
                    );
                }
                records[p].push(r.clone());
            }
        }
    }
    for (p, rs) in records.iter_mut().enumerate() {
        rs.sort_by_key(|r| r.seed);
        let expected = (0..trials as u64).map(|i| seed + i);
        if rs.len() != trials || !rs.iter().map(|r| r.seed).eq(expected) {
            bail!(
                "{}: {} of {trials} trials in the shards (a shard was cut short?)",
                policies[p],
                rs.len()
            );
        }
    }
    // Each record's journal, from the shard that ran it (nothing else a reused directory
    // may hold).
    let keys: Vec<&str> = settings["policies"]
        .as_array()
        .into_iter()
        .flatten()
        .map(|p| p["key"].as_str().unwrap_or_default())
        .collect();
    let ext = settings["journal_format"].as_str().unwrap_or("mcap");
    let journals = out.join("journals");
    std::fs::create_dir_all(&journals)
        .with_context(|| format!("cannot create {}", journals.display()))?;
    let mut copied = 0usize;
    for (dir, s) in &shards {
        for (p, rs) in s.records.iter().enumerate() {
            for r in rs {
                let name = format!("{}-{}.{ext}", keys[p], r.seed);
                let (from, to) = (dir.join("journals").join(&name), journals.join(&name));
                let same = std::fs::canonicalize(&from).ok() == std::fs::canonicalize(&to).ok();
                if !same {
                    std::fs::copy(&from, &to).with_context(|| {
                        format!("cannot copy {} to {}", from.display(), to.display())
                    })?;
                }
                copied += 1;
            }
        }
    }
    let summary = crate::trials::Summary {
        seed,
        trials,
        perception: settings["perception"]
            .as_str()
            .unwrap_or_default()
            .to_string(),
        params: settings["policies"]
            .as_array()
            .into_iter()
            .flatten()
            .map(|p| serde_json::from_value(p["params"].clone()).unwrap_or_default())
            .collect(),
        policies,
    };
    let table = crate::trials::write_results(out, &summary, &records)?;
    eprintln!(
        "merged {} shards: {} trials, {copied} journals, in {:.1} s; wrote {}",
        shards.len(),
        records.iter().map(Vec::len).sum::<usize>(),
        started.elapsed().as_secs_f64(),
        out.display()
    );
    Ok(table)
}
