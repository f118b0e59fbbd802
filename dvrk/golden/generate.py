#!/usr/bin/env python3
"""Golden CDR bytes of every ROS 2 message type the dVRK backend uses, from the real ROS 2
definitions as the `rosbags` package ships them (Jazzy), plus crtk_msgs from its .msg text.

A developer step, not a build step: `pip install rosbags==0.10.9`, then
`python3 dvrk/golden/generate.py` rewrites dvrk/golden/*.hex. The samples here must match
the ones in dvrk/tests/golden.rs field for field.
"""
from pathlib import Path

import numpy as np

from rosbags.typesys import Stores, get_typestore, get_types_from_msg

ts = get_typestore(Stores.ROS2_JAZZY)
CRTK = {
    "crtk_msgs/msg/OperatingState": "std_msgs/Header header\nstring state\nbool is_homed\nbool is_busy\n",
    "crtk_msgs/msg/StringStamped": "std_msgs/Header header\nstring string\n",
}
for name, text in CRTK.items():
    ts.register(get_types_from_msg(text, name))

T = ts.types
Time = T["builtin_interfaces/msg/Time"]
Header = T["std_msgs/msg/Header"]


def header(frame):
    return Header(stamp=Time(sec=1700000000, nanosec=123456789), frame_id=frame)


samples = {
    "std_msgs/msg/String": T["std_msgs/msg/String"](data="PSM1: joint limit"),
    "std_msgs/msg/Empty": T["std_msgs/msg/Empty"](),
    "std_msgs/msg/Float64": T["std_msgs/msg/Float64"](data=0.2),
    "geometry_msgs/msg/PoseStamped": T["geometry_msgs/msg/PoseStamped"](
        header=header("PSM1_base"),
        pose=T["geometry_msgs/msg/Pose"](
            position=T["geometry_msgs/msg/Point"](x=0.01, y=-0.02, z=-0.09),
            orientation=T["geometry_msgs/msg/Quaternion"](x=0.0, y=0.7071067811865476, z=0.0, w=0.7071067811865476),
        ),
    ),
    "sensor_msgs/msg/JointState": T["sensor_msgs/msg/JointState"](
        header=header(""),
        name=["jaw"],
        position=np.array([0.5], dtype="float64"),
        velocity=np.array([], dtype="float64"),
        effort=np.array([], dtype="float64"),
    ),
    "crtk_msgs/msg/OperatingState": T["crtk_msgs/msg/OperatingState"](
        header=header(""), state="ENABLED", is_homed=True, is_busy=False
    ),
    "crtk_msgs/msg/StringStamped": T["crtk_msgs/msg/StringStamped"](header=header(""), string="enable"),
    "sensor_msgs/msg/Image": T["sensor_msgs/msg/Image"](
        header=header("left"),
        height=2,
        width=3,
        encoding="rgb8",
        is_bigendian=0,
        step=9,
        data=np.array(list(range(18)), dtype="uint8"),
    ),
    "sensor_msgs/msg/CameraInfo": T["sensor_msgs/msg/CameraInfo"](
        header=header("left"),
        height=960,
        width=1280,
        distortion_model="plumb_bob",
        d=np.array([0.0] * 5, dtype="float64"),
        k=np.array([1200.0, 0, 640, 0, 1200, 480, 0, 0, 1], dtype="float64"),
        r=np.array([1.0, 0, 0, 0, 1, 0, 0, 0, 1], dtype="float64"),
        p=np.array([1200.0, 0, 640, -48.0, 0, 1200, 480, 0, 0, 0, 1, 0], dtype="float64"),
        binning_x=0,
        binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False),
    ),
}

out = Path(__file__).parent
for name, msg in samples.items():
    data = bytes(ts.serialize_cdr(msg, name))
    (out / (name.replace("/msg/", "__").replace("/", "_") + ".hex")).write_text(data.hex() + "\n")
    print(f"{name}: {len(data)} bytes")
