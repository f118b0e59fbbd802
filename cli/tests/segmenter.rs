//! `--segmenter` as a lab uses it, and `perceive dataset`. The learned segmenter's tests need
//! a stitch built with `--features onnx` and ORT_DYLIB_PATH naming libonnxruntime.so 1.31
//! (`.ci/run` sets it from the tests' Python venv); without the feature, the error it gives.

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

fn stitch(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_stitch"))
        .args(args)
        .current_dir(Path::new(env!("CARGO_MANIFEST_DIR")).join(".."))
        .output()
        .expect("the stitch binary runs")
}

fn dir(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("stitch-segmenter-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

#[test]
fn dataset_writes_crops_with_labels_of_the_same_size() {
    let d = dir("dataset");
    let out = stitch(&[
        "perceive",
        "dataset",
        "--set",
        "training",
        "--frames",
        "3",
        "--seed",
        "4",
        "--out",
        s(&d),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("wrote 6 labelled crops"),
        "{}",
        text(&out.stderr)
    );
    for k in 0..6 {
        let img = image::open(d.join(format!("{k:05}.png")))
            .expect("crop")
            .to_rgb8();
        let lab = image::open(d.join(format!("{k:05}-labels.png")))
            .expect("labels")
            .to_luma8();
        assert_eq!(img.dimensions(), lab.dimensions());
        let needle = lab.pixels().filter(|p| p.0[0] == 1).count();
        assert!(needle > 30, "crop {k}: {needle} needle pixels");
        assert!(lab.pixels().all(|p| p.0[0] <= 3));
    }
    std::fs::remove_dir_all(&d).ok();
}

#[test]
fn the_segmenter_is_only_for_the_pipeline() {
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--perception",
        "model",
        "--segmenter",
        "onnx",
    ]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("--perception pipeline"),
        "{}",
        text(&out.stderr)
    );
    let out = stitch(&["bench", "segmentation", "--segmenters", "unet"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(
        text(&out.stderr).contains("classical, onnx"),
        "{}",
        text(&out.stderr)
    );
}

#[cfg(not(feature = "onnx"))]
#[test]
fn without_the_onnx_feature_the_learned_segmenter_says_how_to_get_it() {
    let out = stitch(&[
        "bench",
        "segmentation",
        "--frames",
        "1",
        "--independent-frames",
        "0",
        "--segmenters",
        "onnx",
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("--features onnx"),
        "{}",
        text(&out.stderr)
    );
}

#[cfg(feature = "onnx")]
mod onnx {
    use super::*;

    fn vec3(v: &serde_json::Value) -> [f64; 3] {
        let a = v.as_array().expect("array");
        [0, 1, 2].map(|i| a[i].as_f64().expect("number"))
    }

    #[test]
    fn the_built_in_model_finds_the_needle_in_a_rendered_pair() {
        let d = dir("needle");
        let out = stitch(&[
            "perceive",
            "render",
            "--sample",
            "0",
            "--seed",
            "1",
            "--out",
            s(&d),
        ]);
        assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
        let out = stitch(&[
            "perceive",
            "needle",
            s(&d.join("left.png")),
            s(&d.join("right.png")),
            "--calib",
            s(&d.join("calib.toml")),
            "--segmenter",
            "onnx",
        ]);
        assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
        let est: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
        let truth: serde_json::Value =
            serde_json::from_slice(&std::fs::read(d.join("truth.json")).expect("truth"))
                .expect("JSON");
        let (a, b) = (vec3(&est["center_m"]), vec3(&truth["center_m"]));
        let e = ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt();
        assert!(e < 0.002, "centre off by {e} m: {}", text(&out.stdout));
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn a_model_file_that_is_not_a_model_is_refused_before_anything_runs() {
        let d = dir("bad-model");
        let bad = d.join("mine.onnx");
        std::fs::write(&bad, b"\x08\x07garbage").expect("write");
        let seg = format!("onnx:{}", s(&bad));
        let out = stitch(&[
            "run",
            "scripts/stitch.rhai",
            "--perception",
            "pipeline",
            "--segmenter",
            &seg,
        ]);
        assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
        let err = text(&out.stderr);
        assert!(
            err.contains("mine.onnx") && err.contains("not a model"),
            "{err}"
        );
        assert!(
            out.stdout.is_empty(),
            "something ran: {}",
            text(&out.stdout)
        );
        let wrong =
            Path::new(env!("CARGO_MANIFEST_DIR")).join("../perception/models/wrong_input.onnx");
        let seg = format!("onnx:{}", s(&wrong));
        let out = stitch(&[
            "bench",
            "segmentation",
            "--frames",
            "1",
            "--segmenters",
            &seg,
        ]);
        assert_eq!(out.status.code(), Some(1));
        assert!(
            text(&out.stderr).contains("[1, 3, H, W]"),
            "{}",
            text(&out.stderr)
        );
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn a_mission_runs_on_the_learned_segmenter_and_its_recording_replays() {
        let d = dir("run");
        let journal = d.join("run.mcap");
        let out = stitch(&[
            "run",
            "scripts/stitch.rhai",
            "--perception",
            "pipeline",
            "--segmenter",
            "onnx",
            "--seed",
            "3",
            "--journal",
            s(&journal),
        ]);
        assert!(
            matches!(out.status.code(), Some(0 | 4)),
            "{}",
            text(&out.stderr)
        );
        let out = stitch(&["replay", s(&journal)]);
        assert_eq!(
            out.status.code(),
            Some(0),
            "{}{}",
            text(&out.stdout),
            text(&out.stderr)
        );
        assert!(
            text(&out.stdout).contains("identical"),
            "{}",
            text(&out.stdout)
        );
        std::fs::remove_dir_all(&d).ok();
    }
}
