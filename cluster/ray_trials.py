#!/usr/bin/env python3
"""`stitch trials` (or `stitch sweep`) sharded over a Ray cluster: one Ray task per shard, retried by Ray when
it fails or its worker dies (a shard is idempotent: run again, it writes the same files),
then the driver merges the shards into what one machine would have written, byte for byte
(docs/experiments.md, "Running on several machines").

    python3 cluster/ray_trials.py --stitch target/release/stitch --shards 8 \\
        --work /shared/run1/shards --out /shared/run1/results -- \\
        --trials 1000 --perception pipeline

Everything after `--` goes to `stitch trials` (not --shard or --out); `--sweep SPEC.toml`
runs a sweep's shards instead (`stitch sweep SPEC.toml --shard K/N`, then `stitch sweep
merge`). With no --address and
no RAY_ADDRESS, Ray starts a local instance (this machine's cores); on a cluster, run it as
a Ray job (`ray job submit --working-dir . -- python3 cluster/ray_trials.py …`) or with
--address auto on a node of the cluster. The binary, the plans and --work must be reachable
at the same paths from every node (a shared file system).
"""
import argparse
import os
import subprocess
import sys
import time

os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
os.environ.setdefault("RAY_ACCEL_ENV_VAR_OVERRIDE_ON_ZERO", "0")
import ray  # noqa: E402  (after the environment it reads)


@ray.remote(max_retries=3, retry_exceptions=True)
def run_shard(stitch, cwd, command, k, n, out, jobs, chaos_marker):
    """Shard k of n of `stitch COMMAND…` into `out`; raises (and Ray retries it) when the
    shard fails."""
    if chaos_marker and not os.path.exists(chaos_marker):
        open(chaos_marker, "w").close()
        raise RuntimeError(f"shard {k}/{n}: failed on purpose (--chaos), once")
    cmd = [stitch, *command, "--shard", f"{k}/{n}", "--jobs", str(jobs), "--out", out]
    r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True)
    if r.returncode != 0:
        raise RuntimeError(f"shard {k}/{n}: exit {r.returncode}: {r.stderr[-2000:]}")
    last = r.stderr.strip().splitlines()[-1] if r.stderr.strip() else ""
    return k, last


def main():
    argv = sys.argv[1:]
    trials_args = []
    if "--" in argv:
        i = argv.index("--")
        argv, trials_args = argv[:i], argv[i + 1:]
    a = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    a.add_argument("--stitch", required=True, help="the stitch binary (same path on every node)")
    a.add_argument("--shards", type=int, required=True, help="how many shards (N)")
    a.add_argument("--work", required=True, help="directory for the shard directories")
    a.add_argument("--out", required=True, help="directory for the merged results")
    a.add_argument("--cpus-per-shard", type=int, default=1,
                   help="cores each shard asks Ray for and runs trials on (--jobs)")
    a.add_argument("--address", default=None,
                   help="Ray cluster to join (`auto`, ray://…); default RAY_ADDRESS or a local instance")
    a.add_argument("--chaos", type=int, default=0, metavar="K",
                   help="make shard K's first try fail, to see Ray retry it (tests)")
    a.add_argument("--sweep", metavar="SPEC.toml",
                   help="run `stitch sweep SPEC.toml` sharded instead of `stitch trials`")
    o = a.parse_args(argv)
    if o.sweep and trials_args:
        sys.exit("ray_trials.py: with --sweep, the sweep file says everything; nothing after --")
    command = ["sweep", os.path.abspath(o.sweep)] if o.sweep else ["trials", *trials_args]
    for bad in ("--shard", "--out"):
        if any(t == bad or t.startswith(bad + "=") for t in trials_args):
            sys.exit(f"ray_trials.py: {bad} is set by the driver; drop it after --")
    if o.shards < 1:
        sys.exit("ray_trials.py: --shards must be at least 1")
    stitch = os.path.abspath(o.stitch)
    cwd = os.getcwd()
    os.makedirs(o.work, exist_ok=True)
    started = time.monotonic()
    ray.init(address=o.address or os.environ.get("RAY_ADDRESS"), include_dashboard=False,
             log_to_driver=False)
    dirs = [os.path.abspath(os.path.join(o.work, f"shard-{k}-of-{o.shards}"))
            for k in range(1, o.shards + 1)]
    pending = {
        run_shard.options(num_cpus=o.cpus_per_shard).remote(
            stitch, cwd, command, k, o.shards, dirs[k - 1], o.cpus_per_shard,
            os.path.join(o.work, f"chaos-{k}") if k == o.chaos else None): k
        for k in range(1, o.shards + 1)
    }
    failed = []
    while pending:
        ready, _ = ray.wait(list(pending), num_returns=1)
        for ref in ready:
            k = pending.pop(ref)
            try:
                _, last = ray.get(ref)
                print(f"shard {k}/{o.shards} done ({o.shards - len(pending)} of {o.shards}), "
                      f"{time.monotonic() - started:.1f} s: {last}", flush=True)
            except Exception as e:  # the shard failed every retry
                failed.append(k)
                print(f"shard {k}/{o.shards} FAILED after Ray's retries: {e}", flush=True)
    ray.shutdown()
    if failed:
        sys.exit(f"ray_trials.py: shards {failed} failed; rerun them with "
                 f"`stitch trials … --shard K/{o.shards}` and merge")
    r = subprocess.run([stitch, command[0], "merge", *dirs, "--out", o.out], cwd=cwd)
    print(f"ray_trials.py: {o.shards} shards and the merge in {time.monotonic() - started:.1f} s",
          flush=True)
    sys.exit(r.returncode)


if __name__ == "__main__":
    main()
