#!/usr/bin/env python3
"""Score ONNX segmentation models on labelled crops with ONNX Runtime, as the Rust runner
sees them: a developer step (`pip install torch onnxruntime pillow numpy scipy`).

    stitch perceive dataset --set independent --frames 100 --seed 1 --out /tmp/seg/ind-dev
    python perception/models/score_crops.py --data /tmp/seg/ind-dev \
        perception/models/needle_thread_unet.onnx perception/models/needle_thread_unet_fast.onnx

For each model: needle and thread IoU pooled over the crops at each logit threshold of
`--thresholds` (the contract's is 0), and the needle's errors split by distance from the
truth's edge (false positives and false negatives within 1.5 px of it, and farther; the
farther false positives by what the truth has there: tissue, thread, instrument). The
crops are brought to the model's scale and the logits back as the Rust runner does (the
contract, docs/perception.md): shrunk to at most `stitch.max_side` pixels, enlarged by at
most `stitch.max_upscale`, the model's metadata (256 and 1 where it has none); `--scales
SIDExUP,...` scores each model at other scales too (e.g. `256x1,240x1.5`).
docs/perception.md quotes its figures.
"""

import argparse
import os
import sys

import numpy as np
import onnxruntime as ort
import torch
import torch.nn.functional as F
from scipy import ndimage as ndi

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import train  # noqa: E402


def logits(session, img, lab, max_side, max_upscale=1.0):
    """The model's logits for one crop at the crop's own size, as the runner gives them."""
    h, w = lab.shape
    im, _ = train.fit_side(img, lab, max_side, max_upscale)
    x = torch.from_numpy(np.ascontiguousarray(im.transpose(2, 0, 1)))[None]
    hh, ww = x.shape[-2:]
    x = F.pad(x, (0, (-ww) % 8, 0, (-hh) % 8), mode="replicate")
    out = session.run(None, {session.get_inputs()[0].name: x.numpy()})[0]
    out = torch.from_numpy(out)[:, :, :hh, :ww]
    return F.interpolate(out, size=(h, w), mode="bilinear", align_corners=False)[0].numpy()


def model_scale(session):
    """The model's region scale from its metadata, as the runner reads it: (max_side,
    max_upscale), 256 and 1 where a key is absent."""
    meta = session.get_modelmeta().custom_metadata_map
    return int(meta.get("stitch.max_side", 256)), float(meta.get("stitch.max_upscale", 1))


def session_of(path):
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    return ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])


def score(path, items, thresholds, scale):
    session = session_of(path)
    max_side, max_upscale = scale or model_scale(session)
    acc = np.zeros((len(thresholds), 2, 2))
    split = np.zeros(5, np.int64)
    # The far false positives by what the truth has there: background, thread, instrument.
    far_on = np.zeros(3, np.int64)
    for img, lab in items:
        y = logits(session, img, lab, max_side, max_upscale)
        truths = [lab == train.NEEDLE, lab == train.THREAD]
        for k, th in enumerate(thresholds):
            for c, t in enumerate(truths):
                m = y[c] > th
                acc[k, c] += [(m & t).sum(), (m | t).sum()]
        m, t = y[0] > 0, truths[0]
        edge = np.where(t, ndi.distance_transform_edt(t), ndi.distance_transform_edt(~t)) <= 1.5
        fp, fn = m & ~t, ~m & t
        split += [(fp & edge).sum(), (fp & ~edge).sum(), (fn & edge).sum(), (fn & ~edge).sum(), t.sum()]
        far_on += [(fp & ~edge & (lab == v)).sum() for v in (0, train.THREAD, train.INSTRUMENT)]
    print(f"{path} (regions at most {max_side} px, enlarged at most {max_upscale:g} times)")
    for k, th in enumerate(thresholds):
        n, t = acc[k, :, 0] / np.maximum(acc[k, :, 1], 1)
        print(f"  logit > {th:+.2f}: needle IoU {n:.3f}, thread IoU {t:.3f}")
    print("  needle at logit 0: false positives within 1.5 px of the truth's edge {}, farther {}; "
          "false negatives within {}, farther {}; of {} true needle pixels".format(*split))
    print("  the farther false positives on tissue {}, thread {}, instrument {}".format(*far_on))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("models", nargs="+", help="ONNX files keeping the contract")
    ap.add_argument("--data", required=True, help="crops from `stitch perceive dataset`")
    ap.add_argument("--thresholds", default="0", help="logit thresholds, comma-separated (default 0)")
    ap.add_argument("--scales", default="",
                    help="SIDExUP,...: score at these region scales (the model's own metadata's by default)")
    a = ap.parse_args()
    thresholds = [float(v) for v in a.thresholds.split(",")]
    items = train.load(a.data)
    if not items:
        raise SystemExit(f"--data {a.data}: no labelled crops there")
    scales = [None]
    if a.scales:
        try:
            scales = [(int(v.split("x")[0]), float(v.split("x")[1])) for v in a.scales.split(",")]
        except (ValueError, IndexError):
            raise SystemExit(f"--scales {a.scales}: want SIDExUP pairs, e.g. 256x1,240x1.5")
    for path in a.models:
        for scale in scales:
            score(path, items, thresholds, scale)


if __name__ == "__main__":
    main()
