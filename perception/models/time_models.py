#!/usr/bin/env python3
"""Where a segmentation model's time goes, and what other shapes of it would cost: a
developer step (PyTorch, ONNX Runtime; `pip install torch onnx onnxruntime numpy`).

    python perception/models/time_models.py --profile perception/models/needle_thread_unet.onnx
    python perception/models/time_models.py --shapes

`--profile FILE`: ONNX Runtime's own profile of FILE on one thread at 256 x 256 (30 runs),
the nodes by their median time. `--shapes`: `train.py`'s U-Net in several widths, with
random weights, exported as train.py exports and timed on one thread (median of 21 runs) at
256 x 256, 200 x 256 and 184 x 184. docs/perception.md ("How the committed model was made")
quotes both.
"""

import argparse
import collections
import json
import os
import sys
import tempfile
import time

import numpy as np
import onnxruntime as ort

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def session(path, profile=False):
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    so.enable_profiling = profile
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def profile(path):
    s = session(path, profile=True)
    x = np.random.rand(1, 3, 256, 256).astype(np.float32)
    for _ in range(30):
        s.run(None, {"image": x})
    trace = s.end_profiling()
    with open(trace) as fh:
        events = json.load(fh)
    os.remove(trace)
    times = collections.defaultdict(list)
    for e in events:
        if e.get("cat") == "Node" and e["name"].endswith("_kernel_time"):
            times[e["name"][: -len("_kernel_time")]].append(e["dur"])
    rows = sorted(((np.median(v) / 1e3, k) for k, v in times.items()), reverse=True)
    for ms, name in rows[:20]:
        print(f"{ms:7.3f} ms  {name}")
    print(f"{sum(ms for ms, _ in rows):7.3f} ms  all nodes")


def shapes():
    import torch
    import train

    torch.manual_seed(0)
    variants = [("unet", c) for c in [(8, 16, 32, 48), (8, 12, 24, 48), (6, 12, 24, 48),
                                      (8, 16, 24, 32), (4, 16, 32, 48)]]
    variants += [("half", c) for c in [(16, 32, 48), (16, 32, 64), (24, 32, 48)]]
    variants += [(a, (16, 32, 48)) for a in ["half-refine", "half-shuffle", "half-shuffle3"]]
    with tempfile.TemporaryDirectory() as d:
        for arch, c in variants:
            model = train.ARCHS[arch](c)
            path = os.path.join(d, "m.onnx")
            train.export(model, path)
            s = session(path)
            cols = []
            for h, w in [(256, 256), (200, 256), (184, 184)]:
                x = np.random.rand(1, 3, h, w).astype(np.float32)
                for _ in range(3):
                    s.run(None, {"image": x})
                t = []
                for _ in range(21):
                    t0 = time.perf_counter()
                    s.run(None, {"image": x})
                    t.append(time.perf_counter() - t0)
                cols.append(f"{h}x{w} {np.median(t) * 1e3:5.2f} ms")
            n = sum(p.numel() for p in model.parameters())
            print(f"{arch} {'/'.join(map(str, c)):12} {n:7} parameters  " + "  ".join(cols), flush=True)


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--profile", metavar="FILE", help="profile this model by node")
    ap.add_argument("--shapes", action="store_true", help="time train.py's U-Net in several widths")
    a = ap.parse_args()
    if not (a.profile or a.shapes):
        ap.error("give --profile FILE, --shapes or both")
    if a.profile:
        profile(a.profile)
    if a.shapes:
        shapes()


if __name__ == "__main__":
    main()
