//! `stitch perceive …` as a lab uses it: on a rendered pair written to PNG, with the
//! calibration file it documents.

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
    let d = std::env::temp_dir().join(format!("stitch-perceive-{}-{name}", std::process::id()));
    std::fs::create_dir_all(&d).expect("temp dir");
    d
}

fn text(b: &[u8]) -> String {
    String::from_utf8_lossy(b).into_owned()
}

fn s(p: &Path) -> &str {
    p.to_str().expect("utf-8 path")
}

fn vec3(v: &serde_json::Value) -> [f64; 3] {
    let a = v.as_array().expect("array");
    [0, 1, 2].map(|i| a[i].as_f64().expect("number"))
}

fn dist(a: [f64; 3], b: [f64; 3]) -> f64 {
    ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt()
}

#[test]
fn a_rendered_pair_on_disk_gives_the_needle_pose_within_a_millimetre() {
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
    let calib = d.join("calib.toml");
    let out = stitch(&[
        "perceive",
        "needle",
        s(&d.join("left.png")),
        s(&d.join("right.png")),
        "--calib",
        s(&calib),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let est: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let truth: serde_json::Value =
        serde_json::from_slice(&std::fs::read(d.join("truth.json")).expect("truth")).expect("JSON");
    for key in ["center_m", "tip_m", "swage_m"] {
        let e = dist(vec3(&est[key]), vec3(&truth[key]));
        assert!(e < 0.001, "{key} off by {e} m: {}", text(&out.stdout));
    }
    let confidence = est["confidence"].as_f64().expect("confidence");
    assert!((0.5..=1.0).contains(&confidence), "{confidence}");
    // Knowing the holding jaw (as the robot does) gives the same pose.
    let jaw = vec3(&truth["jaw_m"]).map(|v| v.to_string()).join(",");
    let holds = truth["jaw_holds"].as_str().expect("holds");
    let out = stitch(&[
        "perceive",
        "needle",
        s(&d.join("left.png")),
        s(&d.join("right.png")),
        "--calib",
        s(&calib),
        "--jaw",
        &jaw,
        "--holds",
        holds,
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let held: serde_json::Value = serde_json::from_slice(&out.stdout).expect("JSON");
    let e = dist(vec3(&held["tip_m"]), vec3(&truth["tip_m"]));
    assert!(e < 0.001, "tip off by {e} m with the jaw known");
    // A jaw without which end it holds is a command-line error.
    let out = stitch(&[
        "perceive",
        "needle",
        s(&d.join("left.png")),
        s(&d.join("right.png")),
        "--calib",
        s(&calib),
        "--jaw",
        "-0.01,0.02,-0.09",
    ]);
    assert_eq!(out.status.code(), Some(2), "{}", text(&out.stderr));
}

#[test]
fn the_disparity_map_is_written_as_pfm_with_the_needle_at_its_depth() {
    let d = dir("disparity");
    let out = stitch(&["perceive", "render", "--sample", "0", "--out", s(&d)]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let pfm = d.join("disp.pfm");
    for matcher in ["mask-row", "sgm"] {
        let out = stitch(&[
            "perceive",
            "disparity",
            s(&d.join("left.png")),
            s(&d.join("right.png")),
            "--calib",
            s(&d.join("calib.toml")),
            "--out",
            s(&pfm),
            "--matcher",
            matcher,
        ]);
        assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
        let bytes = std::fs::read(&pfm).expect("pfm");
        let header = b"Pf\n1280 960\n-1.0\n";
        assert_eq!(&bytes[..header.len()], header);
        assert_eq!(bytes.len(), header.len() + 1280 * 960 * 4);
        let values: Vec<f32> = bytes[header.len()..]
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        let valid: Vec<f32> = values.iter().copied().filter(|v| v.is_finite()).collect();
        assert!(valid.len() > 200, "{matcher}: {} valid", valid.len());
        // The needle lies 14 to 24 cm from this camera (f·B/Z = 1200 × 0.04 / Z); the
        // mask-row matcher gives disparities on the needle only, semi-global matching over
        // the whole region (tissue 20 to 30 cm away, too).
        let (lo, hi) = if matcher == "mask-row" {
            (200.0, 343.0)
        } else {
            (160.0, 343.0)
        };
        let near = valid.iter().filter(|&&v| (lo..hi).contains(&v)).count();
        assert!(
            near * 10 > valid.len() * 9,
            "{matcher}: {near} of {} in {lo}..{hi}",
            valid.len()
        );
    }
}

#[test]
fn bad_calibrations_and_images_are_refused_with_the_reason() {
    let d = dir("bad");
    let out = stitch(&["perceive", "render", "--out", s(&d)]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let good = std::fs::read_to_string(d.join("calib.toml")).expect("calib");
    let bad = d.join("bad.toml");
    let run = |calib: &Path| {
        stitch(&[
            "perceive",
            "needle",
            s(&d.join("left.png")),
            s(&d.join("right.png")),
            "--calib",
            s(calib),
        ])
    };
    // Not a rotation.
    let rotated = good.replace("[[-1.0, 0.0, 0.0]", "[[-2.0, 0.0, 0.0]");
    assert_ne!(rotated, good, "the calibration's layout changed");
    std::fs::write(&bad, rotated).expect("write");
    let out = run(&bad);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("not a rotation matrix"),
        "{}",
        text(&out.stderr)
    );
    // An unknown key says where.
    std::fs::write(&bad, format!("focal = 3\n{good}")).expect("write");
    let out = run(&bad);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("focal"), "{}", text(&out.stderr));
    // Images of another size than the calibration's: a typed failure, exit 6.
    std::fs::write(&bad, good.replace("width = 1280", "width = 1000")).expect("write");
    let out = run(&bad);
    assert_eq!(out.status.code(), Some(6), "{}", text(&out.stderr));
    assert!(
        text(&out.stdout).contains("\"camera\""),
        "{}",
        text(&out.stdout)
    );
    // A region past the image's edge.
    let out = stitch(&[
        "perceive",
        "disparity",
        s(&d.join("left.png")),
        s(&d.join("right.png")),
        "--calib",
        s(&d.join("calib.toml")),
        "--out",
        s(&d.join("x.pfm")),
        "--roi",
        "0,0,5000,5000",
    ]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out.stderr));
    assert!(
        text(&out.stderr).contains("not inside the 1280×960 image"),
        "{}",
        text(&out.stderr)
    );
    // A missing image.
    let out = stitch(&[
        "perceive",
        "needle",
        "nope.png",
        "nope.png",
        "--calib",
        s(&d.join("calib.toml")),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("nope.png"),
        "{}",
        text(&out.stderr)
    );
}
