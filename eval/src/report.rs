//! Accuracy summaries shared by both evaluation sets.

use serde::Serialize;
use std::time::Duration;
use stitch_perception::PerceptionError;
use stitch_perception::pipeline::{PipelineOutput, PoseError, StageTimes};
use stitch_robot::{Needle, Pose};

/// One frame's result.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct FrameResult {
    /// The error, if there was an estimate.
    pub error: Option<PoseError>,
    /// The typed failure, if there was none.
    pub failure: Option<String>,
    /// The failure's message (what the pipeline said), if there was one.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub message: Option<String>,
    /// The estimate's confidence and the arc it saw, degrees (0 without an estimate).
    pub confidence: f64,
    /// See `confidence`.
    pub arc_deg: f64,
    /// The pipeline's stage times.
    pub times: StageTimes,
    /// End to end, including what the stage times do not split out.
    pub total: Duration,
    /// Rendering the pair.
    pub render: Duration,
    /// Which jaw held the needle.
    pub jaw: &'static str,
    /// Whether the thread lay over the needle.
    pub thread_over: bool,
}

impl FrameResult {
    /// A frame's result from the pipeline's answer (the estimate and the needle it assumed,
    /// or the typed failure) against the true pose.
    pub fn new(
        out: Result<(PipelineOutput, Needle), PerceptionError>,
        truth: &Pose,
        total: Duration,
        render: Duration,
        jaw: &'static str,
        thread_over: bool,
    ) -> Self {
        let (error, failure, message, confidence, arc_deg, times) = match out {
            Ok((o, needle)) => (
                Some(PoseError::between(&needle, &o.pose, truth)),
                None,
                None,
                o.confidence,
                o.diagnostics.arc_rad.to_degrees(),
                o.diagnostics.times,
            ),
            Err(e) => (
                None,
                Some(failure_kind(&e).to_string()),
                Some(e.to_string()),
                0.0,
                0.0,
                StageTimes::default(),
            ),
        };
        Self {
            error,
            failure,
            message,
            confidence,
            arc_deg,
            times,
            total,
            render,
            jaw,
            thread_over,
        }
    }
}

/// A failure's kind, for tables.
pub fn failure_kind(e: &PerceptionError) -> &'static str {
    match e {
        PerceptionError::NotFound => "not_found",
        PerceptionError::Occluded { .. } => "occluded",
        PerceptionError::Uncertain { .. } => "uncertain",
        PerceptionError::NoMask { .. } => "no_mask",
        PerceptionError::TooFewPoints { .. } => "too_few_points",
        PerceptionError::BadFit { .. } => "bad_fit",
        PerceptionError::AmbiguousEndpoints { .. } => "ambiguous_endpoints",
        PerceptionError::Config { .. } => "config",
        PerceptionError::Camera { .. } => "camera",
        PerceptionError::Model { .. } => "model",
        PerceptionError::NoThread { .. } => "no_thread",
        PerceptionError::ThreadHidden { .. } => "thread_hidden",
        PerceptionError::ThreadUntraced { .. } => "thread_untraced",
        _ => "other",
    }
}

/// The accuracy table's numbers.
#[derive(Clone, Debug, PartialEq, Serialize)]
pub struct Accuracy {
    /// Frames.
    pub frames: usize,
    /// Frames with an estimate.
    pub estimates: usize,
    /// Median and p95 endpoint error (the worse of tip and swage) over estimates, mm.
    pub endpoint_mm: [f64; 2],
    /// Median and p95 centre error, mm.
    pub center_mm: [f64; 2],
    /// Median and p95 normal error, degrees.
    pub normal_deg: [f64; 2],
    /// Share of all frames with endpoints within 1 mm and normal within 5°.
    pub within_1mm_5deg: f64,
    /// Share of all frames either within 3 mm (endpoints and centre) or a typed failure.
    pub within_3mm_or_failure: f64,
    /// Share of frames with a typed failure.
    pub failures: f64,
    /// Estimates more than 3 mm off (silent wrong poses).
    pub wrong: usize,
    /// Failures by kind.
    pub failure_kinds: Vec<(String, usize)>,
}

/// Percentile `q` (0–1) of sorted values.
pub fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

fn med_p95(mut v: Vec<f64>) -> [f64; 2] {
    v.sort_by(f64::total_cmp);
    [percentile(&v, 0.5), percentile(&v, 0.95)]
}

/// Summarise results.
pub fn accuracy(results: &[FrameResult]) -> Accuracy {
    let errs: Vec<&PoseError> = results.iter().filter_map(|r| r.error.as_ref()).collect();
    let n = results.len().max(1) as f64;
    let good = errs
        .iter()
        .filter(|e| e.endpoints_m() <= 0.001 && e.normal_rad <= 5f64.to_radians())
        .count();
    let ok3 = |e: &PoseError| e.endpoints_m().max(e.center_m) <= 0.003;
    let wrong = errs.iter().filter(|e| !ok3(e)).count();
    let failures = results.iter().filter(|r| r.failure.is_some()).count();
    let mut kinds: Vec<(String, usize)> = Vec::new();
    for r in results {
        if let Some(f) = &r.failure {
            match kinds.iter_mut().find(|(k, _)| k == f) {
                Some(k) => k.1 += 1,
                None => kinds.push((f.clone(), 1)),
            }
        }
    }
    kinds.sort();
    Accuracy {
        frames: results.len(),
        estimates: errs.len(),
        endpoint_mm: med_p95(errs.iter().map(|e| e.endpoints_m() * 1e3).collect()),
        center_mm: med_p95(errs.iter().map(|e| e.center_m * 1e3).collect()),
        normal_deg: med_p95(errs.iter().map(|e| e.normal_rad.to_degrees()).collect()),
        within_1mm_5deg: good as f64 / n,
        within_3mm_or_failure: (results.len() - wrong) as f64 / n,
        failures: failures as f64 / n,
        wrong,
        failure_kinds: kinds,
    }
}
