//! The primitives on the mock dVRK: the observer that reads the mock's ground truth, and a
//! builder for the whole rig.

use crate::{FailureKind, Layout, Observer, PassObservation, Rig, RobotPrimitives};
use std::sync::Arc;
use std::time::Duration;
use stitch_perception::{NeedleEstimator, NeedlePipeline, PipelineEstimator, SharedSegmenter};
use stitch_robot::{FrameObserver, ObservedCamera, Point, SimClock, WoundPoint};
use stitch_sim::{
    CameraConfig, MockCamera, MockDvrk, SceneConfig, SensingConfig, SensingFailure, Side, SimError,
    StereoRenderer, Streams, Subsystem,
};

/// The mock's ground truth as an [`Observer`].
#[derive(Debug)]
pub struct MockObserver {
    world: MockDvrk,
}

impl MockObserver {
    /// An observer of `world`.
    pub fn new(world: MockDvrk) -> Self {
        Self { world }
    }
}

impl Observer for MockObserver {
    fn begin_pass(&mut self) {
        let _ = self.world.take_tip_path();
    }

    fn end_pass(&mut self, point: &WoundPoint) -> PassObservation {
        let path = self.world.take_tip_path();
        let score = self.world.phantom().score(point, &path);
        PassObservation {
            entry_error_m: score.entry_error_m,
            exit_error_m: score.exit_error_m,
            protrusion_m: score.protrusion_m,
            passed: score.passed(),
        }
    }

    fn problem(&mut self) -> Option<FailureKind> {
        let thread = self.world.thread();
        if self.world.needle_truth().dropped {
            Some(FailureKind::NeedleDropped)
        } else if thread.caught {
            Some(FailureKind::ThreadCaught)
        } else if thread.tangled {
            Some(FailureKind::ThreadTangled)
        } else if thread.short {
            Some(FailureKind::ThreadShort)
        } else {
            None
        }
    }

    fn needle_in_tissue(&mut self) -> bool {
        self.world.lodged().is_some()
    }

    fn cinched(&mut self, _beta_m: f64) {
        // The mock's thread followed the pull itself: it drew what the loop could give.
    }

    fn thread_left_m(&mut self) -> f64 {
        self.world.thread().remaining_m()
    }
}

/// The mock dVRK's perception model behind the estimator trait: the true needle pose plus
/// the noise and dropouts `SensingConfig` describes, drawn from the seed's
/// perception stream (`stitch run --perception model`).
#[derive(Debug)]
pub struct ModelEstimator {
    world: MockDvrk,
    config: SensingConfig,
    rng: rand_chacha::ChaCha8Rng,
}

impl ModelEstimator {
    /// An estimator of `world`'s needle.
    pub fn new(world: MockDvrk, config: SensingConfig, streams: Streams) -> Result<Self, SimError> {
        config.validate()?;
        Ok(Self {
            world,
            config,
            rng: streams.rng(Subsystem::Perception),
        })
    }
}

impl NeedleEstimator for ModelEstimator {
    fn estimate_needle(
        &mut self,
    ) -> Result<stitch_perception::NeedleEstimate, stitch_perception::PerceptionError> {
        match self.world.sense_needle(&self.config, &mut self.rng) {
            Ok((pose, stamp)) => Ok(stitch_perception::NeedleEstimate {
                pose,
                confidence: 1.0,
                stamp,
            }),
            Err(SensingFailure::NotInView) => Err(stitch_perception::PerceptionError::NotFound),
            Err(SensingFailure::Dropout { by_thread }) => {
                Err(stitch_perception::PerceptionError::Occluded { by_thread })
            }
        }
    }

    /// The thread tracer's model: the mock's free thread, each link moved by noise of
    /// [`MODEL_THREAD_SIGMA_M`] per axis; hidden where a tool hides it, and a typed failure
    /// when less than the tracer's least share is seen (the hint is not needed: the model
    /// knows where the thread is).
    fn trace_thread(
        &mut self,
        _hint: &stitch_perception::ThreadHint,
    ) -> Result<stitch_perception::ThreadTrace, stitch_perception::PerceptionError> {
        use rand::Rng;
        let links = self.world.thread_in_view();
        let seen = links.iter().filter(|(_, hidden)| !hidden).count();
        let seen_share = seen as f64 / links.len().max(1) as f64;
        if seen_share < stitch_perception::ThreadParams::default().min_seen_share {
            return Err(stitch_perception::PerceptionError::ThreadHidden { seen_share });
        }
        let s = MODEL_THREAD_SIGMA_M;
        // The sum of three uniforms on [-1, 1]: standard deviation 1 (as the needle's model).
        let mut normal = || {
            (0..3)
                .map(|_| self.rng.random_range(-1.0..=1.0))
                .sum::<f64>()
        };
        let points: Vec<Point> = links
            .iter()
            .map(|(p, _)| p + stitch_robot::Vector::new(normal(), normal(), normal()) * s)
            .collect();
        let mut arc = vec![0.0; points.len()];
        for i in 1..points.len() {
            arc[i] = arc[i - 1] + (points[i] - points[i - 1]).norm();
        }
        let mut hidden: Vec<[f64; 2]> = Vec::new();
        for (i, (_, h)) in links.iter().enumerate() {
            if !h {
                continue;
            }
            let (from, to) = (arc[i.saturating_sub(1)], arc[(i + 1).min(arc.len() - 1)]);
            match hidden.last_mut() {
                Some(last) if last[1] >= from => last[1] = to,
                _ => hidden.push([from, to]),
            }
        }
        // The length from the links themselves, 2 % off (the noisy points' own length would
        // be a sixth too long: independent noise on 2 mm links lengthens each).
        let true_length: f64 = links.windows(2).map(|w| (w[1].0 - w[0].0).norm()).sum();
        let length_m = true_length * (1.0 + MODEL_THREAD_LENGTH_SHARE * normal());
        Ok(stitch_perception::ThreadTrace {
            sigma_m: vec![s * 3f64.sqrt(); points.len()],
            length_m,
            points,
            hidden,
            seen_share,
            matched: seen,
            left_path_px: vec![],
        })
    }
}

/// The thread tracer model's length error, as a share of the length (one standard deviation).
pub const MODEL_THREAD_LENGTH_SHARE: f64 = 0.02;

/// The thread tracer model's noise per axis (the stereo tracer's median error on rendered
/// pairs is about 0.1 mm, its 90th percentile a few millimetres: docs/perception.md), m.
pub const MODEL_THREAD_SIGMA_M: f64 = 0.0005;

/// Where the primitives work on the mock, from its scene.
pub fn mock_layout(scene: &SceneConfig, sensing: &SensingConfig) -> Layout {
    let p = |a: [f64; 3]| Point::new(a[0], a[1], a[2]);
    let wound = &scene.wound;
    Layout {
        correction_point: p(sensing.corner),
        left_ready: p(scene.left_home),
        right_ready: p(scene.right_home),
        // Above the wound's left side, in the middle of its length (modelling choice).
        handover_point: Point::new(
            wound.origin.x - 0.015,
            wound.origin.y + wound.spacing_m * (wound.count.saturating_sub(1)) as f64 / 2.0,
            wound.origin.z + 0.03,
        ),
    }
}

/// How the primitives on the mock see the needle.
#[derive(Clone, Debug, PartialEq)]
pub enum MockPerception {
    /// The mock's noise model: the truth plus noise and dropouts (fast; `--perception model`).
    Model(SensingConfig),
    /// The stereo pipeline on pairs the mock's camera renders (`--perception pipeline`),
    /// with this segmenter (`None`: the classical colour segmenter).
    Pipeline(Box<CameraConfig>, Option<SharedSegmenter>),
}

/// Simulated time one rendered frame costs the pipeline in the loop: a 30 Hz camera's frame
/// period (the pipeline itself runs in under 2 ms; `stitch bench perception`), s.
pub const PIPELINE_FRAME_TIME_S: f64 = 1.0 / 30.0;

/// The mock dVRK and the primitives over it, everything seeded by `seed`, the needle seen
/// through the mock's noise model.
pub fn mock_primitives(
    scene: &SceneConfig,
    sensing: SensingConfig,
    seed: u64,
    clock: SimClock,
) -> Result<(RobotPrimitives, MockDvrk), SimError> {
    mock_primitives_with(scene, MockPerception::Model(sensing), seed, clock)
}

/// The mock dVRK and the primitives over it, everything seeded by `seed`, with the given
/// perception.
pub fn mock_primitives_with(
    scene: &SceneConfig,
    perception: MockPerception,
    seed: u64,
    clock: SimClock,
) -> Result<(RobotPrimitives, MockDvrk), SimError> {
    mock_primitives_observed(scene, perception, seed, clock, None)
}

/// [`mock_primitives_with`], with every frame the mock's camera renders for the pipeline
/// shown to `frames` (a recorder's tap; nothing without the pipeline).
pub fn mock_primitives_observed(
    scene: &SceneConfig,
    perception: MockPerception,
    seed: u64,
    clock: SimClock,
    frames: Option<FrameObserver>,
) -> Result<(RobotPrimitives, MockDvrk), SimError> {
    let streams = Streams::new(seed);
    let world = MockDvrk::new(scene, streams, clock)?;
    let (estimator, corner): (Box<dyn NeedleEstimator>, SensingConfig) = match perception {
        MockPerception::Model(sensing) => (
            Box::new(ModelEstimator::new(world.clone(), sensing, streams)?),
            sensing,
        ),
        MockPerception::Pipeline(camera, segmenter) => {
            let renderer = StereoRenderer::new(*camera, world.phantom_view())?;
            let calibration = renderer.calibration().clone();
            let camera = ObservedCamera::new(
                MockCamera::new(
                    world.clone(),
                    renderer,
                    streams,
                    Duration::from_secs_f64(PIPELINE_FRAME_TIME_S),
                ),
                frames,
            );
            let mut pipeline =
                NeedlePipeline::classical(calibration, scene.needle).map_err(|e| {
                    SimError::Config {
                        what: "camera".into(),
                        why: e.to_string(),
                    }
                })?;
            if let Some(s) = segmenter {
                pipeline.segmenter = Box::new(s);
            }
            (
                Box::new(PipelineEstimator::new(camera, pipeline, seed)),
                SensingConfig::default(),
            )
        }
    };
    let sensing = corner;
    let rig = Rig {
        right: Arc::new(world.arm(Side::Right)),
        left: Arc::new(world.arm(Side::Left)),
        right_jaw: Arc::new(world.jaw(Side::Right)),
        left_jaw: Arc::new(world.jaw(Side::Left)),
        estimator,
        observer: Some(Box::new(MockObserver::new(world.clone()))),
        needle: scene.needle,
        layout: mock_layout(scene, &sensing),
        rng: streams.rng(Subsystem::Primitives),
    };
    Ok((RobotPrimitives::new(rig), world))
}
