#!/usr/bin/env python3
"""Write the region scale a segmentation model wants into its ONNX file's metadata, which the
Rust runner reads when it loads the model (docs/perception.md, "The model contract"):

    python perception/models/set_region_scale.py MODEL.onnx --max-side 240 --max-upscale 1.5

`stitch.max_side`: a region whose longer side is above it is shrunk to it (pixels, 8 to
4096; 256 when absent); `stitch.max_upscale`: a region below it is enlarged towards it by at
most this factor (1 to 4; 1, never enlarged, when absent). Only the metadata changes, not a
weight. Choose them on labelled crops the model was not trained on with `score_crops.py
--scales`, as the committed models' were.
"""

import argparse

import onnx

KEYS = {"max_side": "stitch.max_side", "max_upscale": "stitch.max_upscale"}


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model")
    ap.add_argument("--max-side", type=int, required=True)
    ap.add_argument("--max-upscale", type=float, required=True)
    a = ap.parse_args()
    if not 8 <= a.max_side <= 4096:
        raise SystemExit(f"--max-side {a.max_side}: want 8 to 4096 pixels")
    if not 1.0 <= a.max_upscale <= 4.0:
        raise SystemExit(f"--max-upscale {a.max_upscale}: want 1 to 4")
    m = onnx.load(a.model)
    values = {KEYS["max_side"]: str(a.max_side), KEYS["max_upscale"]: f"{a.max_upscale:g}"}
    kept = [p for p in m.metadata_props if p.key not in values]
    del m.metadata_props[:]
    m.metadata_props.extend(kept)
    for k, v in values.items():
        m.metadata_props.add(key=k, value=v)
    onnx.save_model(m, a.model, save_as_external_data=False)
    print(f"{a.model}: {', '.join(f'{k} = {v}' for k, v in values.items())}")


if __name__ == "__main__":
    main()
