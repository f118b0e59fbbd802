//! Criterion benchmarks of the stereo pipeline's stages on rendered 1280×960 pairs (the
//! tables over 500 frames come from `stitch bench perception`).

use criterion::{Criterion, criterion_group, criterion_main};
use rand_chacha::ChaCha8Rng;
use rand_chacha::rand_core::SeedableRng;
use std::hint::black_box;
use stitch_eval::own::{self as evaluate, jaw_hint};
use stitch_perception::disparity::StereoInput;
use stitch_perception::{MaskRowMatcher, NeedlePipeline, Rect, SemiGlobalMatcher, StereoMatcher};
use stitch_robot::{Needle, Pose, SimClock};
use stitch_sim::{CameraConfig, MockDvrk, SceneConfig, StereoRenderer, Streams};

fn benches(c: &mut Criterion) {
    let world =
        MockDvrk::new(&SceneConfig::default(), Streams::new(1), SimClock::new()).expect("world");
    let renderer =
        StereoRenderer::new(CameraConfig::default(), world.phantom_view()).expect("renderer");
    let samples = evaluate::dataset(8, 1, Needle::default(), &world.phantom_view());
    let mut rng = ChaCha8Rng::seed_from_u64(1);
    // A frame the pipeline estimates (the first of the set that succeeds).
    let pipeline =
        NeedlePipeline::classical(renderer.calibration().clone(), Needle::default()).expect("p");
    let (sample, pair) = samples
        .iter()
        .map(|s| (s, renderer.render(&s.scene, &Pose::identity(), &mut rng)))
        .find(|(_, p)| pipeline.estimate(&p.left, &p.right, None, 1).is_ok())
        .expect("a frame the pipeline sees");
    let hint = jaw_hint(sample);
    let (l, r) = (&pair.left, &pair.right);

    let mut g = c.benchmark_group("perception");
    g.bench_function("render stereo pair", |b| {
        let mut rng = ChaCha8Rng::seed_from_u64(2);
        b.iter(|| renderer.render(black_box(&sample.scene), &Pose::identity(), &mut rng))
    });
    let seg = &pipeline.segmenter;
    let full = Rect::full(l.width, l.height);
    g.bench_function("segment both views (full frame)", |b| {
        b.iter(|| {
            let lr = seg.locate(black_box(l), full).expect("left");
            let rr = seg.locate(black_box(r), full).expect("right");
            (
                seg.segment(l, lr).expect("masks"),
                seg.segment(r, rr).expect("masks"),
            )
        })
    });
    let lm = seg
        .segment(l, seg.locate(l, full).expect("left"))
        .expect("masks");
    let rm = seg
        .segment(r, seg.locate(r, full).expect("right"))
        .expect("masks");
    let input = StereoInput {
        left: l,
        right: r,
        left_masks: &lm,
        right_masks: &rm,
        min_disparity: 150,
        max_disparity: 350,
        segmenter: seg.as_ref(),
        parallel: false,
    };
    g.bench_function("disparity, mask rows", |b| {
        let rows = MaskRowMatcher::default();
        b.iter(|| rows.disparity(black_box(&input)).expect("map"))
    });
    g.bench_function(
        "disparity, semi-global around the mask (200 disparities)",
        |b| {
            let sgm = SemiGlobalMatcher::default();
            b.iter(|| sgm.disparity(black_box(&input)).expect("map"))
        },
    );
    g.bench_function("end to end, full frame", |b| {
        b.iter(|| {
            pipeline
                .estimate(black_box(l), black_box(r), None, 1)
                .expect("pose")
        })
    });
    g.bench_function("end to end, jaw known", |b| {
        b.iter(|| {
            pipeline
                .estimate(black_box(l), black_box(r), Some(&hint), 1)
                .expect("pose")
        })
    });
    g.sample_size(10);
    g.bench_function(
        "disparity, semi-global over the whole region (200 disparities)",
        |b| {
            let sgm = SemiGlobalMatcher {
                around_mask_px: None,
                ..SemiGlobalMatcher::default()
            };
            b.iter(|| sgm.disparity(black_box(&input)).expect("map"))
        },
    );
    g.finish();
}

criterion_group!(perception, benches);
criterion_main!(perception);
