#!/usr/bin/env python3
"""The flight recorder's cost, as docs/journal.md quotes it: the same `stitch run` command
with and without `--journal FILE.mcap` (and `.jsonl`), interleaved, medians and ratios;
then a pipeline mission with and without frames; then `stitch trials` with MCAP and with
JSON Lines journals. Each recorded file is removed before its run (a fresh file, as a run
makes; truncating the last one costs ~1 ms on ext4).

    cargo build --release && python3 tests/bench/recorder.py [--binary target/release/stitch]
        [--runs 60] [--trials 1000] [--out-dir /dev/shm]
"""
import argparse
import os
import shutil
import statistics
import subprocess
import time


def timed(cmd, fresh=None):
    if fresh and os.path.exists(fresh):
        os.remove(fresh)
    start = time.perf_counter()
    r = subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    took = time.perf_counter() - start
    if r.returncode not in (0, 4):  # completed, or failed with an error class
        raise SystemExit(f"{' '.join(cmd)}: exit {r.returncode}")
    return took


def compare(title, cases, runs, unit):
    times = {name: [] for name in cases}
    for _ in range(runs):
        for name, (cmd, fresh) in cases.items():
            times[name].append(timed(cmd, fresh))
    base = statistics.median(next(iter(times.values())))
    print(f"{title} (median of {runs})")
    for name, t in times.items():
        m = statistics.median(t)
        print(f"  {name:<22} {m * unit:9.2f} {'ms' if unit == 1e3 else 's'}  ratio {m / base:.2f}")


def main():
    a = argparse.ArgumentParser()
    a.add_argument("--binary", default="target/release/stitch")
    a.add_argument("--runs", type=int, default=60)
    a.add_argument("--trials", type=int, default=1000)
    a.add_argument("--out-dir", default="/tmp")
    o = a.parse_args()
    s, d = o.binary, o.out_dir
    mission = [s, "run", "scripts/stitch_human.rhai", "--seed", "1"]
    f = {k: os.path.join(d, f"bench-{k}") for k in ("mcap", "jsonl", "p", "pf")}
    compare("kinematic mock mission", {
        "without": (mission, None),
        "--journal FILE.jsonl": (mission + ["--journal", f["jsonl"] + ".jsonl"], f["jsonl"] + ".jsonl"),
        "--journal FILE.mcap": (mission + ["--journal", f["mcap"] + ".mcap"], f["mcap"] + ".mcap"),
    }, o.runs, 1e3)
    print(f"  sizes: mcap {os.path.getsize(f['mcap'] + '.mcap')} B, jsonl {os.path.getsize(f['jsonl'] + '.jsonl')} B")
    pipeline = mission + ["--perception", "pipeline"]
    compare("pipeline mock mission", {
        "without": (pipeline, None),
        "--journal FILE.mcap": (pipeline + ["--journal", f["p"] + ".mcap"], f["p"] + ".mcap"),
        "... --record-frames 1": (pipeline + ["--journal", f["pf"] + ".mcap", "--record-frames", "1"], f["pf"] + ".mcap"),
    }, max(3, o.runs // 10), 1)
    print(f"  sizes: {os.path.getsize(f['p'] + '.mcap')} B, with frames {os.path.getsize(f['pf'] + '.mcap')} B")
    policies = "sensing_only,thread_handling,stitch,stitch_human"
    for fmt in ("jsonl", "mcap"):
        out = os.path.join(d, f"bench-trials-{fmt}")
        shutil.rmtree(out, ignore_errors=True)
        t = timed([s, "trials", "--trials", str(o.trials), "--policies", policies,
                   "--journal-format", fmt, "--out", out])
        size = sum(e.stat().st_size for e in os.scandir(os.path.join(out, "journals")))
        print(f"trials, 4 policies x {o.trials}, {fmt}: {t:.2f} s, journals {size / 1e6:.0f} MB")
        shutil.rmtree(out, ignore_errors=True)


if __name__ == "__main__":
    main()
