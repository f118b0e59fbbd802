//! `stitch sweep`: every point a trials run on its own mock configuration, a table and a
//! plot per parameter; sharded and merged (by hand, and by a local Ray cluster) into the same
//! bytes; bad sweeps refused before anything runs.

mod support;

use std::path::{Path, PathBuf};
use support::{stitch_at_root as stitch, text};

fn dir(name: &str) -> PathBuf {
    support::test_dir("stitch-sweep").join(name)
}

/// Every file under `d`, by relative path, sorted.
fn tree(d: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    let mut stack = vec![d.to_path_buf()];
    while let Some(p) = stack.pop() {
        for e in std::fs::read_dir(&p).expect("dir") {
            let path = e.expect("entry").path();
            if path.is_dir() {
                stack.push(path);
            } else {
                let name = path.strip_prefix(d).expect("inside").display().to_string();
                out.push((name, std::fs::read(&path).expect("read")));
            }
        }
    }
    out.sort();
    out
}

fn assert_same(a: &Path, b: &Path) {
    let (x, y) = (tree(a), tree(b));
    assert_eq!(
        x.iter().map(|(n, _)| n).collect::<Vec<_>>(),
        y.iter().map(|(n, _)| n).collect::<Vec<_>>(),
        "the same files"
    );
    for ((name, p), (_, q)) in x.iter().zip(&y) {
        assert!(p == q, "{name} differs");
    }
}

/// A sweep of the needle estimate's noise away from the camera's sweet spot, from a base
/// configuration (the noise spec is a whole table: the sweep sets one of its keys).
fn spec(name: &str) -> PathBuf {
    let d = dir(name);
    std::fs::create_dir_all(&d).expect("dir");
    std::fs::write(
        d.join("base.toml"),
        "[sensing]\nelsewhere = { sigma_position_m = 0.0009, sigma_rotation_rad = 0.0611, p_dropout = 0.15 }\n",
    )
    .expect("base");
    let path = d.join("sweep.toml");
    std::fs::write(
        &path,
        r#"policies = ["stitch", "sensing_only"]
trials = 12
seed = 3
mock_config = "base.toml"
[grid]
"sensing.elsewhere.sigma_position_m" = [0.0002, 0.004]
"scene.thread.length_m" = [0.3, 0.4]
"#,
    )
    .expect("spec");
    path
}

fn sweep_ok(args: &[&str]) -> String {
    let o = stitch(args);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    text(&o.stdout)
}

#[test]
fn a_sweep_runs_every_point_and_writes_a_table_and_a_plot_per_parameter() {
    let (s, out) = (spec("table"), dir("table-out"));
    let table = sweep_ok(&[
        "sweep",
        s.to_str().expect("utf-8"),
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    // 2 × 2 points × 2 policies.
    let rows: Vec<&str> = table.lines().filter(|l| l.starts_with("| 000")).collect();
    assert_eq!(rows.len(), 8, "{table}");
    // Each point ran on its own configuration...
    let mock = std::fs::read_to_string(out.join("points/0003/mock.toml")).expect("mock.toml");
    assert!(
        mock.contains("sigma_position_m = 0.004") && mock.contains("length_m = 0.4"),
        "{mock}"
    );
    assert!(
        mock.contains("p_dropout = 0.15"),
        "the base's other keys kept: {mock}"
    );
    // ...and it shows: STITCH with 4 mm of noise does worse than with 0.2 mm.
    let csv = std::fs::read_to_string(out.join("sweep.csv")).expect("csv");
    let mean = |point: &str, policy: &str| -> f64 {
        let line = csv
            .lines()
            .find(|l| l.starts_with(&format!("{point},")) && l.contains(&format!("\"{policy}\"")))
            .expect("a row");
        let cells: Vec<&str> = line.split(',').collect();
        cells[4].parse().expect("a number")
    };
    // Keys in alphabetical order, the first varying slowest: point 0 is (0.3 m, 0.2 mm),
    // point 1 (0.3 m, 4 mm).
    assert!(
        mean("0", "STITCH") > mean("1", "STITCH") + 1.0,
        "0.2 mm against 4 mm of noise: {csv}"
    );
    for key in [
        "sensing_elsewhere_sigma_position_m",
        "scene_thread_length_m",
    ] {
        let svg = std::fs::read_to_string(out.join(format!("sweep-{key}.svg"))).expect("svg");
        assert_eq!(
            svg.matches("<polyline").count(),
            2,
            "a line per policy: {svg}"
        );
        assert_eq!(
            svg.matches("<circle").count(),
            8,
            "a mark per point and policy"
        );
    }
    // A point's directory is the trials run on its configuration, byte for byte.
    let alone = dir("table-alone");
    let o = stitch(&[
        "trials",
        "--trials",
        "12",
        "--seed",
        "3",
        "--policies",
        "stitch,sensing_only",
        "--mock-config",
        out.join("points/0003/mock.toml").to_str().expect("utf-8"),
        "--out",
        alone.to_str().expect("utf-8"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    for f in ["table.md", "trials.csv", "trials.json"] {
        assert_eq!(
            std::fs::read(alone.join(f)).expect("file"),
            std::fs::read(out.join("points/0003").join(f)).expect("file"),
            "{f}"
        );
    }
}

#[test]
fn a_sharded_sweep_merges_into_the_one_machine_sweep_byte_for_byte() {
    let s = spec("shards");
    let one = dir("shards-one");
    sweep_ok(&[
        "sweep",
        s.to_str().expect("utf-8"),
        "--out",
        one.to_str().expect("utf-8"),
    ]);
    let parts: Vec<PathBuf> = (1..=3).map(|k| dir(&format!("shards-{k}"))).collect();
    for (k, d) in (1..=3).zip(&parts) {
        let o = stitch(&[
            "sweep",
            s.to_str().expect("utf-8"),
            "--shard",
            &format!("{k}/3"),
            "--out",
            d.to_str().expect("utf-8"),
        ]);
        assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
        assert!(!d.join("sweep.md").exists(), "a shard writes no summary");
    }
    let merged = dir("shards-merged");
    let mut args: Vec<String> = vec!["sweep".into(), "merge".into()];
    args.extend(parts.iter().rev().map(|d| d.display().to_string()));
    args.extend(["--out".into(), merged.display().to_string()]);
    let o = stitch(&args.iter().map(String::as_str).collect::<Vec<_>>());
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    assert_same(&one, &merged);
    // A shard missing is refused, naming the point.
    let o = stitch(&[
        "sweep",
        "merge",
        parts[0].to_str().expect("utf-8"),
        parts[1].to_str().expect("utf-8"),
        "--out",
        dir("shards-refused").to_str().expect("utf-8"),
    ]);
    assert_eq!(o.status.code(), Some(1));
    let said = text(&o.stderr);
    assert!(said.contains("point 0") && said.contains("3/3"), "{said}");
}

#[test]
fn bad_sweeps_are_refused_before_anything_runs() {
    let d = dir("bad");
    std::fs::create_dir_all(&d).expect("dir");
    for (body, why) in [
        (
            "trials = 2\n[grid]\n\"sensing.no_such_key\" = [1.0]\n",
            "point 0 (sensing.no_such_key = 1.0) is not a valid mock configuration",
        ),
        (
            "trials = 2\n[grid]\n\"sensing.p_dropout_thread\" = [0.1]\n[random]\nsamples = 2\nseed = 1\nranges = { \"sensing.p_dropout_thread\" = [0.0, 0.5] }\n",
            "not both",
        ),
        ("trials = 2\n", "no parameters"),
        (
            "trials = 2\nmetric = \"speed\"\n[grid]\n\"sensing.p_dropout_thread\" = [0.1]\n",
            "metric \"speed\"",
        ),
        (
            "trials = 2\n[random]\nsamples = 2\nseed = 1\nranges = { \"sensing.p_dropout_thread\" = [0.5, 0.1] }\n",
            "is not a range",
        ),
        ("trials = 2\nunknown = 1\n", "unknown field"),
    ] {
        let s = d.join("s.toml");
        std::fs::write(&s, body).expect("spec");
        refused_before_running(&s, &d.join("out"), why);
    }
}

/// `stitch sweep SPEC` exits 1 saying `why`, and runs no point.
fn refused_before_running(spec: &Path, out: &Path, why: &str) {
    let o = stitch(&[
        "sweep",
        spec.to_str().expect("utf-8"),
        "--out",
        out.to_str().expect("utf-8"),
    ]);
    let said = text(&o.stderr);
    let body = std::fs::read_to_string(spec).unwrap_or_default();
    assert_eq!(o.status.code(), Some(1), "{body}: {said}");
    assert!(said.contains(why), "{body}: expected {why:?} in {said}");
    assert!(!out.join("points").exists(), "nothing ran: {body}");
}

#[test]
fn a_random_sweep_is_decided_by_its_seed() {
    let d = dir("random");
    std::fs::create_dir_all(&d).expect("dir");
    let s = d.join("s.toml");
    std::fs::write(
        &s,
        "trials = 2\n[random]\nsamples = 3\nseed = 5\nranges = { \"sensing.p_dropout_thread\" = [0.0, 0.5] }\n",
    )
    .expect("spec");
    let (a, b) = (d.join("a"), d.join("b"));
    for o in [&a, &b] {
        sweep_ok(&[
            "sweep",
            s.to_str().expect("utf-8"),
            "--out",
            o.to_str().expect("utf-8"),
        ]);
    }
    assert_same(&a, &b);
    let plan = std::fs::read_to_string(a.join("sweep.json")).expect("sweep.json");
    let v: serde_json::Value = serde_json::from_str(&plan).expect("JSON");
    let xs: Vec<f64> = v["points"]
        .as_array()
        .expect("points")
        .iter()
        .map(|p| p[0].as_f64().expect("a number"))
        .collect();
    assert_eq!(xs.len(), 3);
    assert!(xs.iter().all(|x| (0.0..=0.5).contains(x)), "{xs:?}");
    assert!(
        (xs[0] - xs[1]).abs() > 1e-9 && (xs[1] - xs[2]).abs() > 1e-9,
        "{xs:?}"
    );
}

#[test]
fn a_local_ray_cluster_runs_a_sharded_sweep_and_merges_the_same_bytes() {
    let s = spec("ray");
    let one = dir("ray-one");
    sweep_ok(&[
        "sweep",
        s.to_str().expect("utf-8"),
        "--out",
        one.to_str().expect("utf-8"),
    ]);
    let (work, merged) = (dir("ray-work"), dir("ray-merged"));
    let (code, out, err) = support::ray_driver(
        2,
        &work,
        &merged,
        &["--sweep", s.to_str().expect("utf-8"), "--chaos", "1"],
    );
    assert_eq!(code, Some(0), "{out}\n{err}");
    assert!(
        work.join("chaos-1").exists(),
        "shard 1 failed once: {out}\n{err}"
    );
    assert_same(&one, &merged);
}

/// A sweep over the thread-aware policy's parameters beside STITCH, which has none.
fn params_spec(name: &str, grid: &str) -> PathBuf {
    let d = dir(name);
    std::fs::create_dir_all(&d).expect("dir");
    let path = d.join("sweep.toml");
    std::fs::write(
        &path,
        format!("policies = [\"stitch_thread\", \"stitch\"]\ntrials = 5\nseed = 2\n[grid]\n{grid}"),
    )
    .expect("spec");
    path
}

#[test]
fn a_sweep_over_plan_parameters_gives_each_point_its_values_and_merges_the_same_bytes() {
    let s = params_spec(
        "params",
        "\"param.clearance_mm\" = [1.0, 12.0]\n\"param.max_sweeps\" = [1, 3]\n",
    );
    let one = dir("params-one");
    let table = sweep_ok(&[
        "sweep",
        s.to_str().expect("utf-8"),
        "--out",
        one.to_str().expect("utf-8"),
    ]);
    assert!(
        table.contains("| 0003 | 12.0 | 3 | STITCH, thread-aware |"),
        "{table}"
    );
    let trials = |k: usize| -> serde_json::Value {
        let p = one.join(format!("points/{k:04}/trials.json"));
        serde_json::from_str(&std::fs::read_to_string(p).expect("trials.json")).expect("JSON")
    };
    for (k, clearance, sweeps) in [(0, 1.0, 1), (1, 1.0, 3), (2, 12.0, 1), (3, 12.0, 3)] {
        assert_eq!(
            trials(k)["params"],
            serde_json::json!([
                { "policy": "STITCH, thread-aware", "params": { "clearance_mm": clearance, "max_sweeps": sweeps } },
                { "policy": "STITCH", "params": {} },
            ]),
            "point {k}"
        );
    }
    // The values decide the thread-aware runs (a 12 mm clearance sweeps more than 1 mm: more
    // steps in its trials), and STITCH, which has no parameters, runs the same at every point.
    let of = |k: usize, policy: &str| -> Vec<serde_json::Value> {
        trials(k)["trials"]
            .as_array()
            .expect("trials")
            .iter()
            .filter(|t| t["policy"] == policy)
            .cloned()
            .collect()
    };
    assert!(of(0, "STITCH") == of(3, "STITCH"));
    assert!(of(0, "STITCH, thread-aware") != of(3, "STITCH, thread-aware"));
    let mock = std::fs::read_to_string(one.join("points/0003/mock.toml")).expect("mock.toml");
    assert!(
        !mock.contains("param"),
        "parameters are not mock keys: {mock}"
    );

    // Sharded and merged: the same bytes.
    let parts: Vec<PathBuf> = (1..=2).map(|k| dir(&format!("params-{k}"))).collect();
    for (k, d) in (1..=2).zip(&parts) {
        sweep_ok(&[
            "sweep",
            s.to_str().expect("utf-8"),
            "--shard",
            &format!("{k}/2"),
            "--out",
            d.to_str().expect("utf-8"),
        ]);
    }
    let merged = dir("params-merged");
    sweep_ok(&[
        "sweep",
        "merge",
        parts[0].to_str().expect("utf-8"),
        parts[1].to_str().expect("utf-8"),
        "--out",
        merged.to_str().expect("utf-8"),
    ]);
    assert_same(&one, &merged);
}

#[test]
fn bad_plan_parameters_in_a_sweep_are_refused_before_anything_runs() {
    for (name, grid, why) in [
        (
            "params-undeclared",
            "\"param.sweeps\" = [1]\n",
            "--param sweeps: no policy declares it (stitch_thread: its parameters: clearance_mm, max_sweeps; stitch: it has no param(\"name\", default) calls)",
        ),
        (
            "params-type",
            "\"param.max_sweeps\" = [2, \"many\"]\n",
            "point 1 (param.max_sweeps = many): a policy's plan is invalid with these parameters",
        ),
        (
            "params-name",
            "\"param.a.b\" = [1]\n",
            "\"param.a.b\": a parameter's name is ASCII letters",
        ),
        (
            "params-value",
            "\"param.max_sweeps\" = [[1, 2]]\n",
            "a parameter's value is an integer, number, boolean or string",
        ),
    ] {
        refused_before_running(&params_spec(name, grid), &dir(&format!("{name}-out")), why);
    }
}
