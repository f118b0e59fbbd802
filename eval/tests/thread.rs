//! The thread tracer on rendered pairs against their truth: the mock's own renderer and its
//! chain thread, and a few pairs of the independent ray tracer (`stitch bench thread` runs
//! the full sets; docs/perception.md quotes them).

use stitch_eval::thread::{accuracy, independent_set, own_set, run_independent, run_own};
use stitch_perception::ColorSegmenter;
use stitch_perception::thread::ThreadParams;
use stitch_robot::{Needle, SimClock};
use stitch_sim::{CameraConfig, MockDvrk, SceneConfig, StereoRenderer, Streams};

#[test]
fn rendered_threads_are_traced_near_their_truth_or_refused_typed() {
    let world =
        MockDvrk::new(&SceneConfig::default(), Streams::new(1), SimClock::new()).expect("world");
    let renderer =
        StereoRenderer::new(CameraConfig::default(), world.phantom_view()).expect("renderer");
    let samples = own_set(60, 1, Needle::default(), &world.phantom());
    let params = ThreadParams::default();
    let seg = ColorSegmenter::default();
    let results = run_own(&params, &seg, &renderer, &samples, 1);
    let a = accuracy(&results);
    // On 200 pairs (`stitch bench thread`): 82 % traced, median error 0.08 mm. Sixty pairs
    // must show the same picture.
    assert!(a.traced >= 45, "{a:?}");
    assert!(a.median_error_m < 0.0005, "{a:?}");
    // A pair is traced or refused with a thread failure; nothing else.
    for r in &results {
        if let Some(f) = &r.failure {
            assert!(
                ["no_thread", "thread_hidden", "thread_untraced"].contains(&f.as_str()),
                "{f}"
            );
        }
    }
    // Refusals are for threads the view hides in good part (the renderer's labels).
    let refused: Vec<f64> = results
        .iter()
        .filter(|r| r.failure.is_some())
        .map(|r| r.visible)
        .collect();
    let mean_refused = refused.iter().sum::<f64>() / refused.len().max(1) as f64;
    let traced: Vec<f64> = results
        .iter()
        .filter(|r| r.failure.is_none())
        .map(|r| r.visible)
        .collect();
    let mean_traced = traced.iter().sum::<f64>() / traced.len().max(1) as f64;
    assert!(
        mean_refused < mean_traced,
        "{mean_refused} vs {mean_traced}"
    );
    // The same seed, the same traces.
    assert_eq!(
        run_own(&params, &seg, &renderer, &samples, 1)[..10]
            .iter()
            .map(|r| r.length_error.to_bits())
            .collect::<Vec<_>>(),
        results[..10]
            .iter()
            .map(|r| r.length_error.to_bits())
            .collect::<Vec<_>>()
    );

    // Pairs the tracer was never tuned on: other cameras, light, thread colours.
    let ind = independent_set(6, 1, Needle::default());
    let a = accuracy(&run_independent(&params, &seg, &ind, None));
    assert!(a.traced >= 4, "{a:?}");
    assert!(
        a.median_error_m < 0.0005 && a.median_length_error < 0.05,
        "{a:?}"
    );
}
