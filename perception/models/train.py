#!/usr/bin/env python3
"""Train the needle-and-thread U-Net that `--segmenter onnx` runs, and export it to ONNX.

A developer step, not a CI or user step (PyTorch on CPU: `pip install torch onnx pillow numpy scipy`).
The frames come from `stitch perceive dataset --set training` (the mock's renderer under
randomised cameras); this script randomises them further (tissue colour and texture, glare,
shadows, needle and thread colour, light, defocus, noise, scale, orientation) so the net
learns the needle's and the thread's shape rather than the mock's palette. Score it on frames
no training setting made: `stitch bench segmentation` (the independent ray tracer's set).

    stitch perceive dataset --set training --frames 700 --seed 7 --out /tmp/seg/train
    stitch perceive dataset --set training --frames 700 --seed 8 --out /tmp/seg/train8
    python perception/models/train.py --data /tmp/seg/train --steps 4000 --out perception/models
    python perception/models/train.py --data /tmp/seg/train,/tmp/seg/train8 --steps 7500 \
        --arch half-shuffle3 --threads 1 --scenes rods --ema 0.999 \
        --name needle_thread_unet_fast --out perception/models

`--scenes` adds what the mock does not draw: `rods` (an instrument's slender steel jaws, which
the committed fast model is trained with), and `shadows,streaks,vessels,dim` (scene_effects),
which did not lift the needle's IoU on the independent crops (nor did `dim` or `shadows,dim`
beside `rods`; docs/perception.md, "How the committed model was made").

writes NAME.onnx (one file, weights inside; needle_thread_unet by default), the reference the
Rust tests compare against (reference/input.png and reference/NAME-logits.bin: this script's
PyTorch output on that input) and, if it is not there, wrong_input.onnx (a model with a
one-channel input, for the error test).

The contract (docs/perception.md, "The model contract"): input `image`, float32
[1, 3, H, W], RGB in 0..1 as stored (sRGB, not linearised), H and W multiples of 8; output
`logits`, float32 [1, 2, H, W]: channel 0 the needle, channel 1 the thread, a pixel in a mask
where its logit is above 0.
"""

import argparse
import glob
import math
import os
import struct
import time

import numpy as np
import torch
import torch.nn as nn
import torch.nn.functional as F
from PIL import Image, ImageDraw
from scipy import ndimage as ndi
from torch.optim.swa_utils import AveragedModel, get_ema_multi_avg_fn

# The labels `stitch perceive dataset` writes (sim/src/render.rs, `Label`).
NEEDLE, THREAD, INSTRUMENT = 1, 2, 3
# What `--scenes` may add (scene_effects; `dim` and `rods` in augment).
SCENES = ("shadows", "streaks", "vessels", "dim", "rods")


def conv(cin, cout, stride=1):
    return nn.Sequential(nn.Conv2d(cin, cout, 3, stride, 1), nn.ReLU(inplace=True))


class UNet(nn.Module):
    """Scales down by two, skips added (not concatenated) on the way up.

    `half=False` (the committed model's, channels 8, 16, 32, 48): from full resolution, a
    few hundred multiply-adds a pixel there, where a thin wire needs it. `half=True` (the
    fast one's, 16, 32, 48): the first convolution has stride 2 (it still sees every pixel),
    so the scales are 1/2, 1/4 and 1/8, and the logits are brought back to the input's size
    inside the model: bilinearly, or (`shuffle`, the committed fast model's: a 3x3 head) by a
    pixel shuffle. At full resolution the first net's 8-channel convolutions,
    its skip and its head took half its time (ONNX Runtime's profile, one thread, 256 x 256:
    3.6 of 7.8 ms); from half resolution it runs in about half the time with as many weights,
    and learns to place a two-pixel thread between its cells. Either way the input's sides
    must be multiples of 8 (three halvings)."""

    def __init__(self, c=(8, 16, 32, 48), half=False, refine=0, shuffle=0):
        super().__init__()
        self.half = half
        self.shuffle = shuffle
        n = len(c)
        self.e0 = conv(3, c[0], 2 if half else 1)
        self.down = nn.ModuleList(
            nn.Sequential(conv(c[i - 1], c[i], 2), conv(c[i], c[i])) for i in range(1, n))
        # Made in this order (lateral, then decoder, from the coarsest scale) so that a seed
        # gives the weights it gave when each layer had its own name.
        lat, dec = [], []
        for i in range(n - 1, 0, -1):
            lat.append(nn.Conv2d(c[i], c[i - 1], 1))
            dec.append(conv(c[i - 1], c[i - 1]))
        self.lat, self.dec = nn.ModuleList(lat), nn.ModuleList(dec)
        # From half resolution, `shuffle` (a kernel size, 1 or 3) gives each half-resolution
        # cell the logits of its 2 x 2 pixels (8 channels, then depth to space) in place of
        # the bilinear upsampling: the edges' places learned, not interpolated.
        self.head = (nn.Conv2d(c[0], 8, shuffle, 1, shuffle // 2) if half and shuffle
                     else nn.Conv2d(c[0], 2, 1))
        # From half resolution, `refine` > 0 adds a full-resolution step after the bilinear
        # upsampling: the image and the upsampled logits, one 3x3 convolution of `refine`
        # channels and a 1x1 to two, added to the logits (edges placed on the image's own
        # pixels rather than between half-resolution cells).
        self.refine = (
            nn.Sequential(conv(5, refine), nn.Conv2d(refine, 2, 1)) if half and refine else None)

    def forward(self, x):
        skips = [self.e0(x)]
        for d in self.down:
            skips.append(d(skips[-1]))
        up = lambda t: F.interpolate(t, scale_factor=2.0, mode="nearest")
        y = skips.pop()
        for lat, dec in zip(self.lat, self.dec):
            y = dec(up(lat(y)) + skips.pop())
        y = self.head(y)
        if self.half and self.shuffle:
            return F.pixel_shuffle(y, 2)
        if self.half:
            y = F.interpolate(y, scale_factor=2.0, mode="bilinear", align_corners=False)
            if self.refine is not None:
                y = y + self.refine(torch.cat([x, y], 1))
        return y


ARCHS = {"unet": UNet, "half": lambda c=(16, 32, 48): UNet(c, half=True),
         "half-refine": lambda c=(16, 32, 48): UNet(c, half=True, refine=8),
         "half-shuffle": lambda c=(16, 32, 48): UNet(c, half=True, shuffle=1),
         "half-shuffle3": lambda c=(16, 32, 48): UNet(c, half=True, shuffle=3)}


def load(folder):
    items = []
    for f in sorted(glob.glob(os.path.join(folder, "[0-9]*[0-9].png"))):
        img = np.asarray(Image.open(f).convert("RGB"), dtype=np.float32) / 255.0
        lab = np.asarray(Image.open(f[:-4] + "-labels.png"), dtype=np.uint8)
        items.append((img, lab))
    if not items:
        raise SystemExit(f"no crops in {folder} (stitch perceive dataset --out {folder})")
    return items


def fit_side(img, lab, max_side, max_upscale=1.0):
    """What the Rust runner does: shrink a region whose longer side exceeds max_side (PIL's
    box filter), and enlarge one below it towards it by at most max_upscale (bilinear with
    pixel centres aligned, on floats; the labels by nearest neighbour)."""
    h, w = lab.shape
    s = max(h, w)
    k = min(max_side / s, max(max_upscale, 1.0))
    size = (max(8, round(w * k)), max(8, round(h * k)))
    if k == 1.0 or size == (w, h):
        return img, lab
    if k > 1.0:
        x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
        x = F.interpolate(x, size=(size[1], size[0]), mode="bilinear", align_corners=False)
        lb = Image.fromarray(lab).resize(size, Image.NEAREST)
        return np.ascontiguousarray(x[0].numpy().transpose(1, 2, 0)), np.asarray(lb)
    im = Image.fromarray((img * 255).astype(np.uint8)).resize(size, Image.BOX)
    lb = Image.fromarray(lab).resize(size, Image.NEAREST)
    return np.asarray(im, np.float32) / 255.0, np.asarray(lb)


def smooth_noise(rng, h, w, cells):
    g = rng.random((cells + 1, cells + 1), dtype=np.float32)
    t = torch.from_numpy(g)[None, None]
    return F.interpolate(t, size=(h, w), mode="bicubic", align_corners=True)[0, 0].numpy()


def texture(rng, h, w):
    """A random tissue: a two-colour palette over multi-octave noise."""
    n = sum(smooth_noise(rng, h, w, int(rng.integers(2, 24))) * a for a in (0.5, 0.3, 0.2))
    n = (n - n.min()) / (np.ptp(n) + 1e-6)
    hue = rng.choice([rng.uniform(-0.05, 0.12), rng.uniform(0, 1)], p=[0.8, 0.2])
    def colour():
        v = rng.uniform(0.2, 0.95)
        s = rng.uniform(0.25, 0.9)
        import colorsys
        return np.array(colorsys.hsv_to_rgb(hue % 1.0 + rng.uniform(-0.04, 0.04), s, v), np.float32)
    a, b = colour(), colour()
    return a[None, None] * (1 - n[..., None]) + b[None, None] * n[..., None]


def scene_effects(rng, img, lab, scenes):
    """What the mock's renderer does not draw (`--scenes`): shadows cast by the needle, thread
    and instrument on the tissue (and by the instrument on the needle), highlights running
    along the instrument's round fingers, and thin dark vessels in the tissue (`dim`, a needle lit
    unevenly, is applied in `augment` with the needle's own colour change)."""
    h, w = lab.shape
    bg = lab == 0
    objects = lab != 0
    if "shadows" in scenes and objects.any() and rng.random() < 0.5:
        dy, dx = (int(v) for v in rng.integers(-25, 26, 2))
        shadow = np.zeros((h, w), np.float32)
        src = objects[max(0, -dy):h - max(0, dy), max(0, -dx):w - max(0, dx)]
        shadow[max(0, dy):max(0, dy) + src.shape[0], max(0, dx):max(0, dx) + src.shape[1]] = src
        shadow = ndi.gaussian_filter(shadow, rng.uniform(0.5, 4.0))
        dark = 1 - rng.uniform(0.25, 0.7) * shadow[..., None]
        onto = bg | ((lab == NEEDLE) & (rng.random() < 0.3))
        img[onto] = (img * dark)[onto]
    tool = lab == INSTRUMENT
    if "streaks" in scenes and tool.any() and rng.random() < 0.5:
        d = ndi.distance_transform_edt(tool)
        a, width = rng.uniform(1.0, 6.0), rng.uniform(0.8, 3.0)
        streak = np.exp(-((d - a) / width) ** 2) * tool
        gain = rng.uniform(0.4, 1.0) * (0.5 + 0.5 * smooth_noise(rng, h, w, int(rng.integers(2, 10))))
        img = np.clip(img + (streak * gain)[..., None], 0, 1)
    if "vessels" in scenes and bg.any() and rng.random() < 0.4:
        vessel = Image.new("L", (w, h), 0)
        draw = ImageDraw.Draw(vessel)
        for _ in range(int(rng.integers(1, 6))):
            p = rng.uniform(0, 1, (3, 2)) * (w, h)
            t = np.linspace(0, 1, 30)[:, None]
            curve = (1 - t) ** 2 * p[0] + 2 * t * (1 - t) * p[1] + t**2 * p[2]
            draw.line([tuple(q) for q in curve], fill=255, width=int(rng.integers(1, 4)))
        v = ndi.gaussian_filter(np.asarray(vessel, np.float32) / 255, 0.7)
        dark = 1 - rng.uniform(0.2, 0.6) * v[..., None]
        img[bg] = (img * dark)[bg]
    return img


def capsule_distance(h, w, a, b):
    """Each pixel centre's distance (px) from the segment a-b ((x, y) pairs)."""
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) + 0.5
    ab = np.subtract(b, a, dtype=np.float32)
    t = ((xx - a[0]) * ab[0] + (yy - a[1]) * ab[1]) / max(float(ab @ ab), 1e-6)
    t = np.clip(t, 0, 1)
    dx, dy = xx - (a[0] + t * ab[0]), yy - (a[1] + t * ab[1])
    # The offset across the axis, signed (for shading); returned after the distance.
    across = (dx * -ab[1] + dy * ab[0]) / max(float(np.hypot(*ab)), 1e-6)
    return np.hypot(dx, dy), across


def rods(rng, img, lab):
    """An instrument's jaws (`--scenes rods`): one or two straight, round metal rods side by
    side, sometimes from a wider shaft, steel-bright or dark, lying over the needle and thread
    or under them, labelled instrument. The mock draws its instrument as a dark blob; a real
    needle driver's jaws are slender steel, a wire like the needle but straight and thicker."""
    img, lab = img.copy(), lab.copy()
    h, w = lab.shape
    side = max(h, w)
    ys, xs = np.nonzero(lab == NEEDLE)
    if len(xs) and rng.random() < 0.7:
        k = rng.integers(len(xs))
        tip = np.array([xs[k], ys[k]], np.float32) + rng.normal(0, 6, 2).astype(np.float32)
    else:
        tip = rng.uniform(0, 1, 2).astype(np.float32) * (w, h)
    ang = rng.uniform(0, 2 * np.pi)
    d = np.array([np.cos(ang), np.sin(ang)], np.float32)
    normal = np.array([-d[1], d[0]], np.float32)
    r = rng.uniform(1.5, 7.0)
    length = rng.uniform(0.4, 1.5) * side
    gap = 2 * r * rng.uniform(1.05, 2.2)
    n = 2 if rng.random() < 0.7 else 1
    parts = []
    for i in range(n):
        off = normal * gap * (i - (n - 1) / 2)
        back = rng.uniform(0, 0.15) * side
        parts.append((tip + off + d * back, tip + off + d * (back + length), r))
    if rng.random() < 0.4:
        start = tip + d * (rng.uniform(0.3, 0.8) * length)
        parts.append((start, start + d * side * 2, r * rng.uniform(2.0, 4.0)))
    base = rng.uniform(0.12, 0.8)
    tint = base * rng.uniform(0.9, 1.1, 3).astype(np.float32)
    spec = rng.uniform(0.0, 0.9) if rng.random() < 0.7 else 0.0
    lx, lz = rng.uniform(-0.8, 0.8), rng.uniform(0.4, 1.0)
    d0, sw = rng.uniform(-0.6, 0.6), rng.uniform(0.08, 0.3)
    over = rng.random() < 0.6
    allowed = np.ones((h, w), bool) if over else lab == 0
    if rng.random() < 0.5:
        # Its shadow on the tissue.
        dy, dx = (int(v) for v in rng.integers(-20, 21, 2))
        shade = np.zeros((h, w), np.float32)
        for a, b, rr in parts:
            dist, _ = capsule_distance(h, w, a + (dx, dy), b + (dx, dy))
            shade = np.maximum(shade, np.clip(rr - dist + 0.5, 0, 1))
        shade = ndi.gaussian_filter(shade, rng.uniform(0.5, 4.0))
        img[lab == 0] = (img * (1 - rng.uniform(0.2, 0.6) * shade[..., None]))[lab == 0]
    for a, b, rr in parts:
        dist, across = capsule_distance(h, w, a, b)
        alpha = np.clip(rr - dist + 0.5, 0, 1) * allowed
        if not alpha.any():
            continue
        u = np.clip(across / rr, -1, 1)
        nz = np.sqrt(np.clip(1 - u * u, 0, 1))
        lit = 0.35 + 0.65 * np.clip(lx * u + lz * nz, 0, 1)
        colour = tint[None, None] * lit[..., None] + (spec * np.exp(-((u - d0) / sw) ** 2))[..., None]
        img = img * (1 - alpha[..., None]) + np.clip(colour, 0, 1) * alpha[..., None]
        lab[alpha >= 0.5] = INSTRUMENT
    return img.astype(np.float32), lab


def augment(rng, img, lab, size, scenes=()):
    img = img.copy()
    h, w = lab.shape
    bg = lab == 0
    # Tissue: another colour and texture, keeping some of the rendered shading.
    if rng.random() < 0.75:
        t = texture(rng, h, w)
        keep = rng.uniform(0.0, 0.5)
        img[bg] = (keep * img + (1 - keep) * t)[bg]
    # Glare on wet tissue: a bright wash, and specks from blobs down to single pixels.
    if rng.random() < 0.3:
        wash = smooth_noise(rng, h, w, int(rng.integers(1, 4)))[..., None]
        img[bg] = np.clip(img + wash * rng.uniform(0.2, 0.8), 0, 1)[bg]
    if rng.random() < 0.6:
        n = smooth_noise(rng, h, w, int(rng.integers(8, 40)))
        fine = rng.random((h, w), dtype=np.float32) if rng.random() < 0.5 else n
        n = 0.5 * n + 0.5 * fine
        spots = (n > rng.uniform(0.6, 0.85)) & bg
        img[spots] = np.clip(img[spots] + rng.uniform(0.4, 1.0), 0, 1)
    # The instrument: sometimes bright steel, like the needle but not the needle.
    tool = lab == INSTRUMENT
    if tool.any() and rng.random() < 0.4:
        img[tool] = np.clip(img[tool] * rng.uniform(1.5, 4.0) + rng.uniform(0.1, 0.4), 0, 1)
    # Shadows: dark curved bands on the tissue.
    if rng.random() < 0.5:
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        cx, cy = rng.uniform(-0.5, 1.5) * w, rng.uniform(-0.5, 1.5) * h
        r = rng.uniform(0.3, 1.2) * max(h, w)
        band = np.abs(np.hypot(xx - cx, yy - cy) - r) < rng.uniform(1.5, 6)
        img[band & bg] *= rng.uniform(0.2, 0.6)
    if scenes:
        img = scene_effects(rng, img, lab, scenes)
    if "rods" in scenes and rng.random() < 0.5:
        img, lab = rods(rng, img, lab)
        bg = lab == 0
    # The needle: brighter or duller, tinted by what it reflects.
    nd = lab == NEEDLE
    if nd.any():
        tint = img[bg].mean(0) if bg.any() else np.ones(3, np.float32)
        m = rng.uniform(0.0, 0.35)
        img[nd] = np.clip(img[nd] * rng.uniform(0.65, 1.3) * (1 - m) + tint * m * 1.2, 0, 1)
        if "dim" in scenes and rng.random() < 0.5:
            # Lit unevenly along its length: dimmer stretches that mirror the tissue.
            f = smooth_noise(rng, h, w, int(rng.integers(2, 8)))[..., None]
            dim = rng.uniform(0.3, 0.8)
            mix = f * rng.uniform(0.3, 0.7)
            lit = img * (dim + (1 - dim) * f)
            img[nd] = np.clip(lit * (1 - mix) + tint[None, None] * mix, 0, 1)[nd]
    # The thread: another violet.
    th = lab == THREAD
    if th.any():
        img[th] = np.clip(img[th] * rng.uniform(0.7, 1.3, 3).astype(np.float32), 0, 1)
    # Light, white balance, gamma.
    img = img * rng.uniform(0.6, 1.4) * rng.uniform(0.85, 1.15, 3).astype(np.float32)
    img = np.clip(img, 0, 1) ** rng.uniform(0.75, 1.3)
    # Scale (as a region of another size would be), then the runner's fit.
    k = rng.uniform(0.6, 1.5)
    nh, nw = max(8, round(h * k)), max(8, round(w * k))
    img = np.asarray(Image.fromarray((img * 255).astype(np.uint8)).resize((nw, nh), Image.BILINEAR), np.float32) / 255
    lab = np.asarray(Image.fromarray(lab).resize((nw, nh), Image.NEAREST))
    img, lab = fit_side(img, lab, 256)
    # Defocus and noise.
    x = torch.from_numpy(np.ascontiguousarray(img.transpose(2, 0, 1)))[None]
    sigma = rng.uniform(0.0, 1.5)
    if sigma > 0.3:
        r = int(math.ceil(2.5 * sigma))
        k1 = torch.exp(-torch.arange(-r, r + 1, dtype=torch.float32) ** 2 / (2 * sigma**2))
        k1 = (k1 / k1.sum()).view(1, 1, 1, -1).repeat(3, 1, 1, 1)
        x = F.conv2d(F.pad(x, (r, r, 0, 0), mode="replicate"), k1, groups=3)
        x = F.conv2d(F.pad(x, (0, 0, r, r), mode="replicate"), k1.transpose(2, 3), groups=3)
    x = x + torch.randn_like(x) * rng.uniform(0, 0.03)
    x = x.clamp(0, 1)[0]
    y = torch.from_numpy(lab.astype(np.int64))
    # Orientation.
    if rng.random() < 0.5:
        x, y = x.flip(-1), y.flip(-1)
    if rng.random() < 0.5:
        x, y = x.flip(-2), y.flip(-2)
    if rng.random() < 0.5:
        x, y = x.transpose(-1, -2), y.transpose(-1, -2)
    # A window of `size` (padded by the edge if smaller), favouring ones with needle in.
    _, h, w = x.shape
    ph, pw = max(0, size - h), max(0, size - w)
    if ph or pw:
        x = F.pad(x[None], (0, pw, 0, ph), mode="replicate")[0]
        y = F.pad(y[None, None].float(), (0, pw, 0, ph), mode="replicate")[0, 0].long()
        _, h, w = x.shape
    for _ in range(5):
        y0, x0 = rng.integers(0, h - size + 1), rng.integers(0, w - size + 1)
        win = y[y0:y0 + size, x0:x0 + size]
        if (win == NEEDLE).sum() > 30:
            break
    return x[:, y0:y0 + size, x0:x0 + size], win


def targets(y):
    return torch.stack([(y == NEEDLE), (y == THREAD)], 1).float()


def loss_fn(logits, t):
    # Thin structures: weighted cross-entropy plus a soft Dice term per class.
    bce = F.binary_cross_entropy_with_logits(logits, t, pos_weight=torch.tensor([4.0, 6.0]).view(1, 2, 1, 1))
    p = torch.sigmoid(logits)
    inter = (p * t).sum((0, 2, 3))
    dice = 1 - (2 * inter + 1) / (p.sum((0, 2, 3)) + t.sum((0, 2, 3)) + 1)
    return bce + dice.mean()


def iou(model, items, max_side):
    model.eval()
    acc = np.zeros((2, 2))
    with torch.no_grad():
        for img, lab in items:
            h, w = lab.shape
            im, _ = fit_side(img, lab, max_side)
            x = torch.from_numpy(np.ascontiguousarray(im.transpose(2, 0, 1)))[None]
            hh, ww = x.shape[-2:]
            x = F.pad(x, (0, (-ww) % 8, 0, (-hh) % 8), mode="replicate")
            out = model(x)[:, :, :hh, :ww]
            out = F.interpolate(out, size=(h, w), mode="bilinear", align_corners=False)[0] > 0
            for c, l in enumerate((NEEDLE, THREAD)):
                t = torch.from_numpy(lab == l)
                acc[c] += [(out[c] & t).sum().item(), (out[c] | t).sum().item()]
    model.train()
    return acc[:, 0] / np.maximum(acc[:, 1], 1)


def write_reference(model, folder, out, name):
    """The contract's reference: PyTorch's logits on one crop (reference/NAME-logits.bin),
    for the Rust tests."""
    os.makedirs(os.path.join(out, "reference"), exist_ok=True)
    f = sorted(glob.glob(os.path.join(folder, "[0-9]*[0-9].png")))[0]
    im = Image.open(f).convert("RGB")
    w, h = im.size
    im = im.crop((0, 0, min(w, 64), min(h, 48)))
    im.save(os.path.join(out, "reference", "input.png"))
    x = torch.from_numpy(np.asarray(im, np.float32).transpose(2, 0, 1) / 255.0)[None]
    with torch.no_grad():
        y = model(x)[0].numpy().astype("<f4")
    with open(os.path.join(out, "reference", f"{name}-logits.bin"), "wb") as fh:
        fh.write(struct.pack("<3I", *y.shape))
        fh.write(y.tobytes())


def export(model, path, channels=3):
    model.eval()
    x = torch.rand(1, channels, 64, 64)
    torch.onnx.export(
        model, x, path, input_names=["image"], output_names=["logits"],
        dynamic_axes={"image": {2: "height", 3: "width"}, "logits": {2: "height", 3: "width"}},
        opset_version=17, dynamo=False,
    )


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True,
                    help="crops from `stitch perceive dataset --set training` (several folders: comma-separated)")
    ap.add_argument("--val", help="crops to report IoU on while training (not used to choose anything)")
    ap.add_argument("--out", default=os.path.dirname(os.path.abspath(__file__)))
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--batch", type=int, default=12)
    ap.add_argument("--size", type=int, default=128)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--ema", type=float, default=0.0,
                    help="export (and report) an exponential moving average of the weights with this decay "
                         "per step, e.g. 0.999 (0: the last step's weights)")
    ap.add_argument("--arch", choices=sorted(ARCHS), default="unet",
                    help="unet: the first committed model's; half-shuffle3: the fast one's (from half "
                         "resolution, a pixel shuffle from a 3x3 head); half, half-shuffle, half-refine: "
                         "the other heads tried (docs/perception.md)")
    ap.add_argument("--name", default="needle_thread_unet",
                    help="the model's file name, without .onnx (needle_thread_unet_fast: the fast one)")
    ap.add_argument("--channels", help="channels per scale, e.g. 16,32,48 (the architecture's own by default)")
    ap.add_argument("--scenes", default="",
                    help=f"comma-separated extra effects: {', '.join(SCENES)} (scene_effects)")
    a = ap.parse_args()
    scenes = tuple(filter(None, a.scenes.split(",")))
    unknown = set(scenes) - set(SCENES)
    if unknown:
        raise SystemExit(f"--scenes: unknown effect(s) {', '.join(sorted(unknown))} ({', '.join(SCENES)})")
    torch.manual_seed(a.seed)
    torch.set_num_threads(a.threads)
    rng = np.random.default_rng(a.seed)
    items = [it for folder in a.data.split(",") for it in load(folder)]
    val = load(a.val) if a.val else []
    model = ARCHS[a.arch](*([tuple(int(c) for c in a.channels.split(","))] if a.channels else []))
    print(f"{len(items)} crops, {sum(p.numel() for p in model.parameters())} parameters")
    opt = torch.optim.AdamW(model.parameters(), lr=3e-3, weight_decay=1e-4)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=3e-3, total_steps=a.steps, pct_start=0.1)
    # The nets have no normalisation layers, so the average is of the parameters alone.
    ema = AveragedModel(model, multi_avg_fn=get_ema_multi_avg_fn(a.ema)) if a.ema > 0 else None
    t0 = time.time()
    for step in range(1, a.steps + 1):
        batch = [augment(rng, *items[rng.integers(len(items))], a.size, scenes) for _ in range(a.batch)]
        x = torch.stack([b[0] for b in batch])
        y = torch.stack([b[1] for b in batch])
        loss = loss_fn(model(x), targets(y))
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
        if ema is not None:
            ema.update_parameters(model)
        if step % 250 == 0 or step == a.steps:
            msg = f"step {step} loss {loss.item():.3f} {time.time() - t0:.0f} s"
            if val:
                n, t = iou(model, val, 256)
                msg += f" val IoU needle {n:.3f} thread {t:.3f}"
                if ema is not None:
                    n, t = iou(ema.module, val, 256)
                    msg += f" (average: {n:.3f} {t:.3f})"
            print(msg, flush=True)
    if ema is not None:
        model = ema.module
    os.makedirs(a.out, exist_ok=True)
    path = os.path.join(a.out, f"{a.name}.onnx")
    export(model, path)
    # One file: fold any external weights back in.
    import onnx
    m = onnx.load(path, load_external_data=True)
    onnx.save_model(m, path, save_as_external_data=False)
    for extra in glob.glob(path + ".data"):
        os.remove(extra)
    write_reference(model, a.data.split(",")[0], a.out, a.name)
    wrong = os.path.join(a.out, "wrong_input.onnx")
    if not os.path.exists(wrong):
        export(UNet_one_channel(), wrong, channels=1)
    print(f"wrote {path} ({os.path.getsize(path)} bytes)")


class UNet_one_channel(nn.Module):
    """A model that breaks the contract (one input channel), for the error test."""

    def __init__(self):
        super().__init__()
        self.c = nn.Conv2d(1, 2, 1)

    def forward(self, x):
        return self.c(x)


if __name__ == "__main__":
    main()
