//! `STITCH_BUILD`: the commit the binary was built from (`git rev-parse --short=12 HEAD`),
//! or "unknown" outside a git checkout. Shards of one trials run must come from one build
//! (`stitch trials merge` compares it).

fn main() {
    let git = std::path::Path::new("../.git");
    if git.is_dir() {
        println!("cargo:rerun-if-changed=../.git/HEAD");
        // The branch HEAD names, where it moves on a commit.
        let head = std::fs::read_to_string(git.join("HEAD")).unwrap_or_default();
        if let Some(r) = head.trim().strip_prefix("ref: ") {
            println!("cargo:rerun-if-changed=../.git/{r}");
        }
    }
    let build = std::process::Command::new("git")
        .args(["rev-parse", "--short=12", "HEAD"])
        .output()
        .ok()
        .filter(|o| o.status.success())
        .and_then(|o| String::from_utf8(o.stdout).ok())
        .map(|s| s.trim().to_string())
        .filter(|s| !s.is_empty())
        .unwrap_or_else(|| "unknown".into());
    println!("cargo:rustc-env=STITCH_BUILD={build}");
}
