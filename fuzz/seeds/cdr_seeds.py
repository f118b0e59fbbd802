#!/usr/bin/env python3
"""Seeds for the `cdr` and `camera_image` targets: plain little-endian CDR of the messages a
dVRK and a ROS 2 camera send, written by hand from the ROS 2 definitions (alignment counted
from the payload's start, after the 4-byte encapsulation header)."""
import os
import struct
import sys


class Cdr:
    def __init__(self):
        self.b = bytearray()

    def align(self, n):
        while len(self.b) % n:
            self.b.append(0)

    def u8(self, v):
        self.b += struct.pack("<B", v)

    def u32(self, v):
        self.align(4)
        self.b += struct.pack("<I", v)

    def i32(self, v):
        self.align(4)
        self.b += struct.pack("<i", v)

    def f64(self, v):
        self.align(8)
        self.b += struct.pack("<d", v)

    def string(self, s):
        raw = s.encode() + b"\0"
        self.u32(len(raw))
        self.b += raw

    def header(self, sec=1_700_000_000, nsec=5, frame=""):
        self.i32(sec)
        self.u32(nsec)
        self.string(frame)

    def out(self):
        return bytes([0, 1, 0, 0]) + bytes(self.b)


def pose_stamped():
    c = Cdr()
    c.header()
    for v in (0.01, -0.02, -0.1, 0.0, 0.0, 0.0, 1.0):
        c.f64(v)
    return c.out()


def joint_state():
    c = Cdr()
    c.header()
    c.u32(1)
    c.string("jaw")
    for vals in ([0.5], [0.0], []):
        c.u32(len(vals))
        for v in vals:
            c.f64(v)
    return c.out()


def operating_state():
    c = Cdr()
    c.header()
    c.string("ENABLED")
    c.u8(1)
    c.u8(0)
    return c.out()


def string(s):
    c = Cdr()
    c.string(s)
    return c.out()


def string_stamped():
    c = Cdr()
    c.header()
    c.string("enable")
    return c.out()


def image(enc="rgb8", w=4, h=3, bpp=3):
    c = Cdr()
    c.header(frame="left")
    c.u32(h)
    c.u32(w)
    c.string(enc)
    c.u8(0)
    c.u32(w * bpp)
    data = bytes((i * 37) % 256 for i in range(w * h * bpp))
    c.u32(len(data))
    c.b += data
    return c.out()


def camera_info(tx):
    c = Cdr()
    c.header(frame="left")
    c.u32(960)
    c.u32(1280)
    c.string("plumb_bob")
    c.u32(5)
    for _ in range(5):
        c.f64(0.0)
    for v in (1200, 0, 640, 0, 1200, 480, 0, 0, 1):
        c.f64(v)
    for v in (1, 0, 0, 0, 1, 0, 0, 0, 1):
        c.f64(v)
    for v in (1200, 0, 640, tx, 0, 1200, 480, 0, 0, 0, 1, 0):
        c.f64(v)
    c.u32(0)
    c.u32(0)
    for _ in range(4):
        c.u32(0)
    c.u8(0)
    return c.out()


def main(root):
    cdr = os.path.join(root, "cdr")
    img = os.path.join(root, "camera_image")
    os.makedirs(cdr, exist_ok=True)
    os.makedirs(img, exist_ok=True)
    seeds = {
        0: pose_stamped(),
        1: joint_state(),
        2: operating_state(),
        3: string("PSM1: joint limit"),
        4: string_stamped(),
        5: bytes([0, 1, 0, 0, 0]),
        6: bytes([0, 1, 0, 0]) + struct.pack("<d", 0.2),
        7: image(),
    }
    for which, body in seeds.items():
        with open(os.path.join(cdr, f"type{which}"), "wb") as f:
            f.write(bytes([which]) + body)
    left, right = camera_info(0.0), camera_info(-48.0)
    with open(os.path.join(cdr, "type8_infos"), "wb") as f:
        f.write(bytes([8]) + struct.pack("<H", len(left)) + left + right)
    # camera_image: encoding index, width, height, step (little-endian u32s), data.
    for name, enc, w, h, bpp in (("rgb", 0, 4, 3, 3), ("bgra", 3, 5, 2, 4)):
        data = bytes((i * 11) % 256 for i in range(w * h * bpp))
        with open(os.path.join(img, name), "wb") as f:
            f.write(bytes([enc]) + struct.pack("<III", w, h, w * bpp) + data)


if __name__ == "__main__":
    main(sys.argv[1] if len(sys.argv) > 1 else os.path.join(os.path.dirname(__file__), "..", "corpus"))
