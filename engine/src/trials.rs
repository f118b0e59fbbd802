//! Trials: one record per simulated mission, and the paper's metrics over a policy's trials
//! (Table I, "Trial Specifications and Error Classification"), with 95 % confidence
//! intervals.
//!
//! Definitions (the paper's, made exact):
//! - **sutures** of a trial: throws completed before it ended;
//! - **errors**: every failure that ended the trial or made the robot ask for an
//!   intervention, classed I, E, H or T as the engine classes them;
//! - **suture attempts** of a trial: its sutures plus its errors (each error is a throw
//!   that did not complete at that attempt);
//! - **mean sutures to failure**: the mean of the trials' sutures;
//! - **single-suture success rate**: all sutures over all suture attempts;
//! - **three-throw success rate**: the share of trials with at least three sutures;
//! - **full-wound success rate**: the share of trials that completed every throw;
//! - **mean time per suture**: all simulated time over all sutures;
//! - **mean sutures to intervention**: over every intervention request, the sutures completed
//!   since the previous request (or the trial's start).
//!
//! Intervals: Wilson score for shares, Student's t for the mean of sutures; none for the
//! ratio of time to sutures.

use crate::journal::RunOutcome;
use crate::plan::{FailureClass, Plan};
use crate::runner::Report;
use crate::supervisor::InterventionResult;
use serde::{Deserialize, Serialize};
use stitch_primitives::StepOutcome;

/// One trial.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TrialRecord {
    /// The policy's name.
    pub policy: String,
    /// The trial's seed.
    pub seed: u64,
    /// Throws in the plan.
    pub throws: usize,
    /// Throws completed.
    pub sutures: usize,
    /// "completed", "failed" or "aborted".
    pub outcome: String,
    /// The class of the error that ended the trial, if one did ("I", "E", "H", "T").
    pub failure: Option<String>,
    /// Errors by class, I, E, H, T: the trial-ending one and every one that led to an
    /// intervention.
    pub errors: [u32; 4],
    /// Interventions requested.
    pub interventions: u32,
    /// For each intervention request, the sutures completed since the previous one.
    pub sutures_before_interventions: Vec<u32>,
    /// Simulated time of the whole trial, s.
    pub duration_s: f64,
    /// Mean entry error at the holes over the trial's passes, mm.
    pub entry_error_mm: Option<f64>,
    /// Mean exit error at the holes over the trial's passes, mm.
    pub exit_error_mm: Option<f64>,
}

fn class_index(c: FailureClass) -> usize {
    match c {
        FailureClass::Insertion => 0,
        FailureClass::Extraction => 1,
        FailureClass::Handover => 2,
        FailureClass::Thread => 3,
    }
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

impl TrialRecord {
    /// The record of one run of `plan`.
    pub fn from_report(policy: &str, seed: u64, plan: &Plan, report: &Report) -> Self {
        let mut errors = [0u32; 4];
        let mut before = Vec::new();
        let mut since = 0u32;
        let (mut entry, mut exit) = (Vec::new(), Vec::new());
        for (t, throw) in report.throws.iter().enumerate() {
            for a in &throw.attempts {
                let m = a.outcome.measured();
                if a.primitive == "insert" {
                    entry.extend(m.entry_error_m.map(|e| e * 1e3));
                    exit.extend(m.exit_error_m.map(|e| e * 1e3));
                }
                if let Some(result) = a.intervention {
                    // Every request counts for sutures to intervention; its error is counted
                    // here if the trial went on, by the outcome if the intervention failed
                    // and ended it.
                    before.push(since);
                    since = 0;
                    if result == InterventionResult::Recovered {
                        let class = match &a.outcome {
                            StepOutcome::Failed(f) if f.kind.is_thread() => FailureClass::Thread,
                            _ => plan.phase_class(t, a.step),
                        };
                        errors[class_index(class)] += 1;
                    }
                }
            }
            if throw.completed {
                since += 1;
            }
        }
        let sutures = report.throws.iter().filter(|t| t.completed).count();
        let (outcome, failure) = match &report.outcome {
            RunOutcome::Completed => ("completed", None),
            RunOutcome::Failed { class, .. } => {
                errors[class_index(*class)] += 1;
                ("failed", Some(class.code().to_string()))
            }
            RunOutcome::Aborted { .. } => ("aborted", None),
        };
        Self {
            policy: policy.to_string(),
            seed,
            throws: plan.throws.len(),
            sutures,
            outcome: outcome.into(),
            failure,
            errors,
            interventions: u32::from(report.interventions),
            sutures_before_interventions: before,
            duration_s: report.duration_s,
            entry_error_mm: mean(&entry),
            exit_error_mm: mean(&exit),
        }
    }

    /// Suture attempts: sutures plus errors.
    pub fn attempts(&self) -> u32 {
        self.sutures as u32 + self.errors.iter().sum::<u32>()
    }
}

/// An estimate with its 95 % interval.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Estimate {
    /// The value.
    pub value: f64,
    /// Lower end of the 95 % interval (the value itself where none is computed).
    pub low: f64,
    /// Upper end.
    pub high: f64,
}

/// The paper's metrics over one policy's trials.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// The policy.
    pub policy: String,
    /// Trials.
    pub trials: usize,
    /// Mean sutures to failure (Student's t interval).
    pub mean_sutures_to_failure: Estimate,
    /// Single-suture success rate, 0–1 (Wilson).
    pub single_suture_success: Estimate,
    /// Three-throw success rate, 0–1 (Wilson).
    pub three_throw_success: Estimate,
    /// Full-wound success rate, 0–1 (Wilson).
    pub full_wound_success: Estimate,
    /// Mean simulated time per suture, s (`None` without sutures).
    pub mean_time_per_suture_s: Option<f64>,
    /// Errors I, E, H, T.
    pub errors: [u32; 4],
    /// Mean sutures to intervention (`None` without interventions).
    pub mean_sutures_to_intervention: Option<f64>,
}

/// The Wilson score interval of `k` successes in `n`, 95 %.
pub fn wilson(k: u64, n: u64) -> Estimate {
    if n == 0 {
        return Estimate {
            value: 0.0,
            low: 0.0,
            high: 1.0,
        };
    }
    let z = 1.959_964;
    let (k, n) = (k as f64, n as f64);
    let p = k / n;
    let d = 1.0 + z * z / n;
    let c = (p + z * z / (2.0 * n)) / d;
    let h = z * ((p * (1.0 - p) + z * z / (4.0 * n)) / n).sqrt() / d;
    Estimate {
        value: p,
        low: (c - h).max(0.0),
        high: (c + h).min(1.0),
    }
}

/// Student's t, two-sided 95 %, for `df` degrees of freedom (a table to 30, then the normal
/// value's approach).
pub fn t95(df: usize) -> f64 {
    const T: [f64; 30] = [
        12.706, 4.303, 3.182, 2.776, 2.571, 2.447, 2.365, 2.306, 2.262, 2.228, 2.201, 2.179, 2.160,
        2.145, 2.131, 2.120, 2.110, 2.101, 2.093, 2.086, 2.080, 2.074, 2.069, 2.064, 2.060, 2.056,
        2.052, 2.048, 2.045, 2.042,
    ];
    match df {
        0 => f64::INFINITY,
        1..=30 => T[df - 1],
        _ => 1.96 + 2.4 / df as f64,
    }
}

/// The mean of `v` with its t interval.
pub fn mean_interval(v: &[f64]) -> Estimate {
    let n = v.len();
    let Some(m) = mean(v) else {
        return Estimate {
            value: 0.0,
            low: 0.0,
            high: 0.0,
        };
    };
    if n < 2 {
        return Estimate {
            value: m,
            low: m,
            high: m,
        };
    }
    let var = v.iter().map(|x| (x - m).powi(2)).sum::<f64>() / (n - 1) as f64;
    let h = t95(n - 1) * (var / n as f64).sqrt();
    Estimate {
        value: m,
        low: m - h,
        high: m + h,
    }
}

/// The metrics of `records` (all of one policy).
pub fn metrics(policy: &str, records: &[TrialRecord]) -> Metrics {
    let n = records.len();
    let sutures: Vec<f64> = records.iter().map(|r| r.sutures as f64).collect();
    let total_sutures: u64 = records.iter().map(|r| r.sutures as u64).sum();
    let attempts: u64 = records.iter().map(|r| u64::from(r.attempts())).sum();
    let three = records.iter().filter(|r| r.sutures >= 3).count() as u64;
    let full = records.iter().filter(|r| r.outcome == "completed").count() as u64;
    let time: f64 = records.iter().map(|r| r.duration_s).sum();
    let mut errors = [0u32; 4];
    for r in records {
        for (e, x) in errors.iter_mut().zip(r.errors) {
            *e += x;
        }
    }
    let between: Vec<f64> = records
        .iter()
        .flat_map(|r| r.sutures_before_interventions.iter().map(|&s| f64::from(s)))
        .collect();
    Metrics {
        policy: policy.to_string(),
        trials: n,
        mean_sutures_to_failure: mean_interval(&sutures),
        single_suture_success: wilson(total_sutures, attempts),
        three_throw_success: wilson(three, n as u64),
        full_wound_success: wilson(full, n as u64),
        mean_time_per_suture_s: (total_sutures > 0).then(|| time / total_sutures as f64),
        errors,
        mean_sutures_to_intervention: mean(&between),
    }
}
