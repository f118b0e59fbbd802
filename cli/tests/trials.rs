//! `stitch trials`: every file written, the same bytes whatever the number of threads or
//! shards (merged by hand or by a local Ray cluster), and bad arguments refused with the
//! reason.

mod support;

use std::path::{Path, PathBuf};
use support::{stitch_at_root as stitch, text};

fn dir(name: &str) -> PathBuf {
    support::test_dir("stitch-trials").join(name)
}

fn files(d: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = Vec::new();
    for sub in ["", "journals"] {
        let mut names: Vec<_> = std::fs::read_dir(d.join(sub))
            .expect("dir")
            .map(|e| e.expect("entry").path())
            .filter(|p| p.is_file())
            .collect();
        names.sort();
        for p in names {
            let name = p.strip_prefix(d).expect("inside").display().to_string();
            out.push((name, std::fs::read(&p).expect("read")));
        }
    }
    out
}

#[test]
fn trials_write_every_file_and_the_same_bytes_on_one_or_two_threads() {
    let (a, b) = (dir("a"), dir("b"));
    for (d, jobs) in [(&a, "1"), (&b, "2")] {
        let out = stitch(&[
            "trials",
            "--trials",
            "3",
            "--seed",
            "5",
            "--jobs",
            jobs,
            "--out",
            d.to_str().expect("utf-8"),
        ]);
        assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
        assert!(
            text(&out.stdout).contains("| *paper* | *2.93* |"),
            "{}",
            text(&out.stdout)
        );
    }
    let (fa, fb) = (files(&a), files(&b));
    let names: Vec<&str> = fa.iter().map(|(n, _)| n.as_str()).collect();
    for want in [
        "table.md",
        "trials.csv",
        "trials.json",
        "histogram.svg",
        "histogram.png",
    ] {
        assert!(names.contains(&want), "{want} missing: {names:?}");
    }
    // 5 policies × 3 trials, seeds 5, 6, 7.
    assert_eq!(
        names.iter().filter(|n| n.starts_with("journals")).count(),
        15
    );
    assert!(names.contains(&"journals/stitch_human-7.mcap"), "{names:?}");
    assert_eq!(fa, fb, "the files depend on --jobs");
    let csv = text(&fa.iter().find(|(n, _)| n == "trials.csv").expect("csv").1);
    assert_eq!(csv.lines().count(), 1 + 15);
    assert!(csv.starts_with("policy,seed,throws,sutures,outcome,failure,errors_I"));
    let png = &fa
        .iter()
        .find(|(n, _)| n == "histogram.png")
        .expect("png")
        .1;
    assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
    let json: serde_json::Value =
        serde_json::from_slice(&fa.iter().find(|(n, _)| n == "trials.json").expect("json").1)
            .expect("JSON");
    assert_eq!(json["trials"].as_array().expect("trials").len(), 15);
    assert_eq!(json["metrics"].as_array().expect("metrics").len(), 5);
    // The journals are the runs: the same seed with `stitch run` records the same file.
    let j = dir("run.mcap");
    let out = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--seed",
        "6",
        "--journal",
        j.to_str().expect("utf-8"),
    ]);
    assert!(
        matches!(out.status.code(), Some(0 | 4)),
        "{}",
        text(&out.stderr)
    );
    let journal = &fa
        .iter()
        .find(|(n, _)| n == "journals/stitch-6.mcap")
        .expect("j")
        .1;
    assert!(
        &std::fs::read(&j).expect("journal") == journal,
        "stitch trials and stitch run recorded seed 6 differently"
    );
}

#[test]
fn trials_can_write_json_lines_journals_instead() {
    let d = dir("jsonl");
    let out = stitch(&[
        "trials",
        "--trials",
        "2",
        "--policies",
        "stitch",
        "--journal-format",
        "jsonl",
        "--out",
        d.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let j = dir("jsonl-run.jsonl");
    let run = stitch(&[
        "run",
        "scripts/stitch.rhai",
        "--seed",
        "2",
        "--journal",
        j.to_str().expect("utf-8"),
    ]);
    assert!(
        matches!(run.status.code(), Some(0 | 4)),
        "{}",
        text(&run.stderr)
    );
    assert_eq!(
        std::fs::read(d.join("journals/stitch-2.jsonl")).expect("trial journal"),
        std::fs::read(&j).expect("run journal")
    );
}

#[test]
fn bad_trial_arguments_are_refused_with_the_reason() {
    let d = dir("bad");
    let d = d.to_str().expect("utf-8");
    let out = stitch(&["trials", "--policies", "stitch,nope", "--out", d]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("unknown policy \"nope\""),
        "{}",
        text(&out.stderr)
    );
    let out = stitch(&["trials", "--trials", "0", "--out", d]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("--trials"),
        "{}",
        text(&out.stderr)
    );
    let out = stitch(&["trials", "--trials", "1000000000", "--out", d]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("expected 1 to 100000"),
        "{}",
        text(&out.stderr)
    );
    let out = stitch(&["trials", "--seed", "18446744073709551615", "--out", d]);
    assert_eq!(out.status.code(), Some(1));
    assert!(text(&out.stderr).contains("2^64"), "{}", text(&out.stderr));
    // A plan parameter no policy declares changes nothing: refused, naming what they declare.
    let out = stitch(&[
        "trials",
        "--policies",
        "stitch,stitch_thread",
        "--param",
        "clearance=3",
        "--out",
        d,
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("--param clearance: no policy declares it (stitch: it has no param(\"name\", default) calls; stitch_thread: its parameters: clearance_mm, max_sweeps)"),
        "{}",
        text(&out.stderr)
    );
    assert!(!Path::new(d).join("journals").exists(), "nothing ran");
    // An output "directory" that is a file.
    let file = dir("file");
    std::fs::write(&file, "x").expect("write");
    let out = stitch(&[
        "trials",
        "--trials",
        "1",
        "--out",
        file.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        text(&out.stderr).contains("cannot create"),
        "{}",
        text(&out.stderr)
    );
}

#[test]
fn the_results_in_docs_are_what_the_documented_command_writes() {
    let d = dir("docs");
    let out = stitch(&[
        "trials",
        "--trials",
        "15",
        "--seed",
        "1",
        "--out",
        d.to_str().expect("utf-8"),
    ]);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out.stderr));
    let docs = Path::new(env!("CARGO_MANIFEST_DIR")).join("../docs");
    for f in ["table.md", "histogram.svg", "histogram.png"] {
        let fresh = std::fs::read(d.join(f)).expect("fresh");
        let kept = std::fs::read(docs.join("experiments").join(f)).expect("kept");
        assert!(
            fresh == kept,
            "docs/experiments/{f} is stale: rerun `stitch trials --trials 15 --seed 1 --out DIR` and copy it"
        );
    }
    // docs/experiments.md shows the same rows.
    let page = std::fs::read_to_string(docs.join("experiments.md")).expect("page");
    let table = std::fs::read_to_string(d.join("table.md")).expect("table");
    for row in table.lines().filter(|l| l.starts_with("| ")) {
        assert!(page.contains(row), "docs/experiments.md lacks {row}");
    }
}

/// `stitch trials ARGS --out DIR`, which must succeed; its stderr.
fn run_ok(args: &[&str], out: &Path) -> String {
    let o = stitch(&[args, &["--out", out.to_str().expect("utf-8")]].concat());
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    text(&o.stderr)
}

#[test]
fn merged_shards_are_the_one_machine_run_byte_for_byte() {
    // Nine trials of two policies: with seven shards some hold one trial, some two.
    let args = [
        "trials",
        "--trials",
        "9",
        "--seed",
        "3",
        "--policies",
        "stitch,sensing_only",
    ];
    let one = dir("one");
    run_ok(&args, &one);
    let whole = files(&one);
    assert_eq!(
        whole
            .iter()
            .filter(|(n, _)| n.starts_with("journals"))
            .count(),
        18
    );
    for n in [1u32, 2, 7] {
        let shards: Vec<PathBuf> = (1..=n).map(|k| dir(&format!("shard-{k}-of-{n}"))).collect();
        for (k, d) in (1..=n).zip(&shards) {
            let said = run_ok(&[&args[..], &["--shard", &format!("{k}/{n}")]].concat(), d);
            assert!(said.contains(&format!("shard {k}/{n}")), "{said}");
            assert!(
                !d.join("table.md").exists(),
                "a shard writes no table of its own"
            );
        }
        // In any order.
        let merged = dir(&format!("merged-{n}"));
        let mut cmd: Vec<String> = vec!["trials".into(), "merge".into()];
        cmd.extend(shards.iter().rev().map(|d| d.display().to_string()));
        cmd.extend(["--out".into(), merged.display().to_string()]);
        let o = stitch(&cmd.iter().map(String::as_str).collect::<Vec<_>>());
        assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
        assert!(
            text(&o.stderr).contains(&format!("shards done: {n} of {n}")),
            "{}",
            text(&o.stderr)
        );
        let got = files(&merged);
        assert_eq!(
            got.iter().map(|(n, _)| n).collect::<Vec<_>>(),
            whole.iter().map(|(n, _)| n).collect::<Vec<_>>(),
            "the same files"
        );
        for ((name, a), (_, b)) in whole.iter().zip(&got) {
            assert!(a == b, "{name} differs after merging {n} shards");
        }
    }
}

#[test]
fn missing_duplicated_or_foreign_shards_are_refused_with_the_reason() {
    let args = [
        "trials",
        "--trials",
        "4",
        "--seed",
        "1",
        "--policies",
        "stitch",
    ];
    let s: Vec<PathBuf> = (1..=3).map(|k| dir(&format!("refuse-{k}"))).collect();
    for (k, d) in (1..=3).zip(&s) {
        run_ok(&[&args[..], &["--shard", &format!("{k}/3")]].concat(), d);
    }
    // Another run's shard 3: other seeds.
    let other = dir("refuse-other");
    run_ok(
        &[
            "trials",
            "--trials",
            "4",
            "--seed",
            "2",
            "--policies",
            "stitch",
            "--shard",
            "3/3",
        ],
        &other,
    );
    // Another split's shard: 2 of 2.
    let split = dir("refuse-split");
    run_ok(&[&args[..], &["--shard", "2/2"]].concat(), &split);
    let merge = |dirs: &[&PathBuf]| -> (Option<i32>, String) {
        let mut cmd: Vec<String> = vec!["trials".into(), "merge".into()];
        cmd.extend(dirs.iter().map(|d| d.display().to_string()));
        cmd.extend(["--out".into(), dir("refused").display().to_string()]);
        let o = stitch(&cmd.iter().map(String::as_str).collect::<Vec<_>>());
        (o.status.code(), text(&o.stderr))
    };
    for (dirs, why) in [
        (vec![&s[0], &s[1]], "shard 3/3 of the run is not here"),
        (vec![&s[0], &s[1], &s[1], &s[2]], "shard 2/3 twice"),
        (
            vec![&s[0], &s[1], &other],
            "not shards of one run: seed: 1 against 2",
        ),
        (vec![&s[0], &split], "not one split"),
    ] {
        let (code, said) = merge(&dirs);
        assert_eq!(code, Some(1), "{said}");
        assert!(said.contains(why), "expected {why:?}: {said}");
    }
    let (code, said) = merge(&[&dir("refuse-nowhere")]);
    assert_eq!(code, Some(1), "{said}");
    assert!(said.contains("not a shard directory"), "{said}");
    // A shard from another plan text is another run too.
    let edited = dir("refuse-plan");
    let plan = dir("refuse-plan.rhai");
    let text_of = std::fs::read_to_string(
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/stitch.rhai"),
    )
    .expect("plan");
    std::fs::write(&plan, text_of + "\n// edited\n").expect("write");
    let o = stitch(&[
        "trials",
        "--trials",
        "4",
        "--seed",
        "1",
        "--policies",
        plan.to_str().expect("utf-8"),
        "--shard",
        "3/3",
        "--out",
        edited.to_str().expect("utf-8"),
    ]);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o.stderr));
    let (code, said) = merge(&[&s[0], &s[1], &edited]);
    assert_eq!(code, Some(1), "{said}");
    assert!(said.contains("policies"), "{said}");
    // A hand-edited shard file is refused, not a panic.
    let file = s[2].join("shard.json");
    let saved = std::fs::read_to_string(&file).expect("shard.json");
    let k0 = dir("refuse-k0");
    std::fs::create_dir_all(&k0).expect("dir");
    std::fs::write(
        k0.join("shard.json"),
        saved.replace(r#""shard":{"k":3,"n":3}"#, r#""shard":{"k":0,"n":3}"#),
    )
    .expect("write");
    let (code, said) = merge(&[&s[0], &s[1], &k0]);
    assert_eq!(code, Some(1), "{said}");
    assert!(said.contains("expected K/N"), "{said}");
    for bad in ["0/3", "4/3", "3", "a/b", "1/9999999"] {
        let o = stitch(&[&args[..], &["--shard", bad, "--out", "/tmp/x"]].concat());
        assert_eq!(o.status.code(), Some(2), "{bad}");
        assert!(text(&o.stderr).contains("expected K/N"), "{bad}");
    }
}

#[test]
fn a_local_ray_cluster_runs_the_shards_retries_a_failed_one_and_merges_the_same_bytes() {
    let args = [
        "--trials",
        "5",
        "--seed",
        "2",
        "--policies",
        "stitch,sensing_only",
    ];
    let one = dir("ray-one");
    run_ok(&[&["trials"][..], &args].concat(), &one);
    let (work, merged) = (dir("ray-work"), dir("ray-merged"));
    // Shard 2's first try fails: Ray runs it again.
    let (code, out, err) = support::ray_driver(
        3,
        &work,
        &merged,
        &[&["--chaos", "2", "--"][..], &args].concat(),
    );
    assert_eq!(code, Some(0), "{out}\n{err}");
    assert!(
        work.join("chaos-2").exists(),
        "shard 2 failed once: {out}\n{err}"
    );
    for k in 1..=3 {
        assert!(out.contains(&format!("shard {k}/3 done")), "{out}\n{err}");
    }
    let (whole, got) = (files(&one), files(&merged));
    assert_eq!(
        got.iter().map(|(n, _)| n).collect::<Vec<_>>(),
        whole.iter().map(|(n, _)| n).collect::<Vec<_>>()
    );
    for ((name, a), (_, b)) in whole.iter().zip(&got) {
        assert!(a == b, "{name} differs after the Ray run");
    }
}
