#!/usr/bin/env python3
"""The references for a region larger than the model's side and for one it enlarges: what
the committed model gives through ONNX Runtime when the region is shrunk as `train.py`
shrinks crops (PIL's box filter, here on float planes so nothing is rounded to 8 bits), or
enlarged by its `stitch.max_upscale` (bilinear, pixel centres aligned), and the logits are
brought back by bilinear interpolation with pixel centres aligned (PyTorch's
`align_corners=False`). `perception/tests/onnx.rs` checks that the Rust runner gives the same.

    pip install onnxruntime==1.31.1 pillow numpy
    python perception/models/shrunk_reference.py

writes reference/shrunk_logits.bin (a 300 x 41 region, shrunk) and
reference/enlarged_logits.bin (100 x 40, enlarged 1.5 times): three little-endian u32
(channels, rows, columns), then the logits of every third row and column of the region,
float32.
"""

import os
import struct

import numpy as np
import onnxruntime as ort
from PIL import Image

SHRUNK, ENLARGED, STEP = (300, 41), (100, 40), 3


def pattern(w, h):
    """The test image, as `shrunk_pattern` in perception/tests/onnx.rs draws it."""
    y, x = np.mgrid[0:h, 0:w].astype(np.int64)
    r = (37 * x + 11 * y) % 251
    g = (17 * x + 29 * y) % 241
    b = (x * y + 3 * x) % 239
    return np.stack([r, g, b], -1).astype(np.float32)


def bilinear(c, h, w):
    """PyTorch's F.interpolate(..., mode="bilinear", align_corners=False) of one plane."""
    mh, mw = c.shape
    ys = np.maximum((np.arange(h) + 0.5) * mh / h - 0.5, 0)
    xs = np.maximum((np.arange(w) + 0.5) * mw / w - 0.5, 0)
    y0, x0 = np.floor(ys).astype(int), np.floor(xs).astype(int)
    y1, x1 = np.minimum(y0 + 1, mh - 1), np.minimum(x0 + 1, mw - 1)
    ty, tx = (ys - y0)[:, None], (xs - x0)[None, :]
    a = c[y0][:, x0] * (1 - tx) + c[y0][:, x1] * tx
    b = c[y1][:, x0] * (1 - tx) + c[y1][:, x1] * tx
    return a * (1 - ty) + b * ty


def reference(session, w, h, name):
    meta = session.get_modelmeta().custom_metadata_map
    side, up = int(meta.get("stitch.max_side", 256)), float(meta.get("stitch.max_upscale", 1))
    img = pattern(w, h)
    k = min(side / max(w, h), up)
    mw, mh = round(w * k), round(h * k)
    if k < 1:
        planes = [np.asarray(Image.fromarray(img[..., c], mode="F").resize((mw, mh), Image.BOX)) for c in range(3)]
    else:
        planes = [bilinear(img[..., c].astype(np.float64), mh, mw) for c in range(3)]
    small = np.stack(planes, -1) / 255.0
    pw, ph = -(-mw // 8) * 8, -(-mh // 8) * 8
    x = np.pad(small, ((0, ph - mh), (0, pw - mw), (0, 0)), mode="edge").astype(np.float32)
    out = session.run(None, {session.get_inputs()[0].name: x.transpose(2, 0, 1)[None]})[0][0][:, :mh, :mw]
    full = np.stack([bilinear(out[c].astype(np.float64), h, w) for c in range(2)])
    kept = full[:, ::STEP, ::STEP].astype("<f4")
    here = os.path.dirname(os.path.abspath(__file__))
    path = os.path.join(here, "reference", name)
    with open(path, "wb") as fh:
        fh.write(struct.pack("<3I", *kept.shape))
        fh.write(kept.tobytes())
    print(f"wrote {path}: {w} x {h} at {mw} x {mh}, {kept.shape}, "
          f"{(full > 0).sum((1, 2))} pixels above 0 of {h * w}")


def main():
    here = os.path.dirname(os.path.abspath(__file__))
    s = ort.InferenceSession(os.path.join(here, "needle_thread_unet.onnx"))
    reference(s, *SHRUNK, "shrunk_logits.bin")
    reference(s, *ENLARGED, "enlarged_logits.bin")


if __name__ == "__main__":
    main()
