#!/usr/bin/env python3
"""A dVRK 2.x console stand-in on Cyclone DDS (not RustDDS): two PSMs with jaws on the CRTK
topics, with the console's QoS and its arm state machine, for stitch's tests against a DDS
that is not its own.

QoS, as the dVRK 2.x console (cisst-ros on rclcpp) offers them:
  periodic state (measured_cp, setpoint_cp, jaw/measured_js): QoS(100), reliable, volatile
  events (operating_state, error, warning, status, goal_reached, trajectory_j/ratio):
      QoS(100).transient_local(): reliable, keep last 100, transient local
  command subscriptions (state_command, move_cp, servo_cp, hold, jaw/move_jp,
      trajectory_j/set_ratio): QoS(1), reliable, volatile

State machine, per arm: DISABLED -> (enable) ENABLED, not homed -> (home) busy while homing
-> homed, idle. A move_cp or jaw/move_jp is busy while its trajectory runs (speed scaled by
the trajectory ratio), then idle at the goal; hold stops it. Commands are refused (an
`error`) unless ENABLED and homed, as the console does.

Driven on standard input, one command a line; every answer is one line on standard output:
  status                  -> JSON: each arm's state, homed, busy, ratio, commands received
  reset disabled|homed    -> arms DISABLED and unhomed, ratio 1.0 (a fresh console), or
                             ENABLED, homed, idle, ratio 1.0 (left so by a previous run);
                             the counters cleared
  error ARM TEXT          -> publish TEXT on ARM's `error` and go to FAULT, now
  pose ARM x y z qx qy qz qw -> place ARM there (idle), as a surgeon's recovery would
  quit
It prints `ready` once every topic exists. `--lose-first` drops the first sample each command
topic of each arm takes after a reset, as a reader that did not know the writer yet does;
`--ignore TOPIC` (repeatable) drops every sample of that command topic (a console that never
answers it).
"""

import json
import math
import sys
import threading
import time
from dataclasses import dataclass, field

from cyclonedds.core import Policy, Qos
from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
from cyclonedds.idl.types import float64, int32, sequence, uint8, uint32
from cyclonedds.pub import DataWriter
from cyclonedds.sub import DataReader, InvalidSample
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: int32 = 0
    nanosec: uint32 = 0


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time = field(default_factory=Time)
    frame_id: str = ""


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: float64 = 0.0
    y: float64 = 0.0
    z: float64 = 0.0
    w: float64 = 1.0


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point = field(default_factory=Point)
    orientation: Quaternion = field(default_factory=Quaternion)


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header = field(default_factory=Header)
    pose: Pose = field(default_factory=Pose)


@dataclass
class JointState(IdlStruct, typename="sensor_msgs::msg::dds_::JointState_"):
    header: Header = field(default_factory=Header)
    name: sequence[str] = field(default_factory=list)
    position: sequence[float64] = field(default_factory=list)
    velocity: sequence[float64] = field(default_factory=list)
    effort: sequence[float64] = field(default_factory=list)


@dataclass
class OperatingState(IdlStruct, typename="crtk_msgs::msg::dds_::OperatingState_"):
    header: Header = field(default_factory=Header)
    state: str = ""
    is_homed: bool = False
    is_busy: bool = False


@dataclass
class StringStamped(IdlStruct, typename="crtk_msgs::msg::dds_::StringStamped_"):
    header: Header = field(default_factory=Header)
    string: str = ""


@dataclass
class String(IdlStruct, typename="std_msgs::msg::dds_::String_"):
    data: str = ""


@dataclass
class Empty(IdlStruct, typename="std_msgs::msg::dds_::Empty_"):
    structure_needs_at_least_one_member: uint8 = 0


@dataclass
class Float64(IdlStruct, typename="std_msgs::msg::dds_::Float64_"):
    data: float64 = 0.0


@dataclass
class Bool(IdlStruct, typename="std_msgs::msg::dds_::Bool_"):
    data: bool = False


# ROS 2 encodes as XCDR1 (CDR); Cyclone's Python writer would pick XCDR2 otherwise.
CDR = Policy.DataRepresentation(use_cdrv0_representation=True)
STATE_QOS = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)),
                Policy.History.KeepLast(100), Policy.Durability.Volatile, CDR)
EVENT_QOS = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)),
                Policy.History.KeepLast(100), Policy.Durability.TransientLocal, CDR)
COMMAND_QOS = Qos(Policy.Reliability.Reliable(duration(milliseconds=100)),
                  Policy.History.KeepLast(1), Policy.Durability.Volatile, CDR)

RATE_HZ = 100.0
# Cartesian speed of a move at ratio 1, m/s, and its least duration, s (a kinematic model).
TOP_SPEED_M_S = 0.5
MIN_MOVE_S = 0.05
HOMING_S = 0.3
JAW_SPEED_RAD_S = 10.0


def take(reader):
    """The samples waiting on `reader`; not the notices of a writer gone (invalid samples)."""
    return [s for s in reader.take(N=10) if not isinstance(s, InvalidSample)]


def stamp(t=None):
    t = time.time() if t is None else t
    return Time(sec=int(t), nanosec=int((t - int(t)) * 1e9))


def nlerp(a, b, s):
    dot = sum(x * y for x, y in zip(a, b))
    if dot < 0:
        b = [-x for x in b]
    q = [x + (y - x) * s for x, y in zip(a, b)]
    n = math.sqrt(sum(x * x for x in q)) or 1.0
    return [x / n for x in q]


class Arm:
    def __init__(self, dp, name, pose, lose_first=False, ignore=()):
        self.name = name
        self.lose_first, self.ignore = lose_first, set(ignore)
        self.lock = threading.Lock()
        self.home_pose = list(pose)
        w = lambda topic, ty, qos: DataWriter(dp, Topic(dp, f"rt/{name}/{topic}", ty), qos=qos)
        r = lambda topic, ty: DataReader(dp, Topic(dp, f"rt/{name}/{topic}", ty), qos=COMMAND_QOS)
        self.measured_cp = w("measured_cp", PoseStamped, STATE_QOS)
        self.setpoint_cp = w("setpoint_cp", PoseStamped, STATE_QOS)
        self.measured_js = w("jaw/measured_js", JointState, STATE_QOS)
        self.operating_state = w("operating_state", OperatingState, EVENT_QOS)
        self.error = w("error", String, EVENT_QOS)
        self.warning = w("warning", String, EVENT_QOS)
        self.status = w("status", String, EVENT_QOS)
        self.goal_reached = w("goal_reached", Bool, EVENT_QOS)
        self.ratio_out = w("trajectory_j/ratio", Float64, EVENT_QOS)
        self.state_command = r("state_command", StringStamped)
        self.move_cp = r("move_cp", PoseStamped)
        self.servo_cp = r("servo_cp", PoseStamped)
        self.hold = r("hold", Empty)
        self.jaw_move_jp = r("jaw/move_jp", JointState)
        self.set_ratio = r("trajectory_j/set_ratio", Float64)
        self.reset(homed=False)

    def reset(self, homed):
        with self.lock:
            self.state = "ENABLED" if homed else "DISABLED"
            self.homed = homed
            self.busy = False
            self.pose = list(self.home_pose)  # x y z qx qy qz qw
            self.jaw = 0.0
            self.motion = None  # (kind, start, goal, t0, duration)
            self.homing_until = None
            self.ratio = 1.0
            self.counts = {k: 0 for k in ("enable", "disable", "home", "move_cp", "servo_cp",
                                          "hold", "jaw/move_jp", "set_ratio", "refused",
                                          "lost")}
            self.seen = set()  # command topics that took a sample since the reset
        self.publish_state()
        self.ratio_out.write(Float64(data=self.ratio))

    def publish_state(self):
        self.operating_state.write(OperatingState(
            header=Header(stamp=stamp()), state=self.state, is_homed=self.homed,
            is_busy=self.busy))

    def fault(self, text):
        with self.lock:
            self.state, self.busy, self.motion = "FAULT", False, None
        self.error.write(String(data=f"{self.name}: {text}"))
        self.publish_state()

    def refuse(self, what):
        self.counts["refused"] += 1
        self.error.write(String(data=f"{self.name}: {what} refused: arm is {self.state}, "
                                     f"homed {self.homed}"))

    def take(self, topic, reader):
        """`take`, less what this stand-in is told to lose."""
        got = []
        for s in take(reader):
            if topic in self.ignore or (self.lose_first and topic not in self.seen):
                self.seen.add(topic)
                self.counts["lost"] += 1
                continue
            got.append(s)
        return got

    def ready(self):
        return self.state == "ENABLED" and self.homed

    def step(self, now):
        changed = False
        with self.lock:
            for s in self.take("state_command", self.state_command):
                cmd = s.string
                if cmd == "enable":
                    self.counts["enable"] += 1
                    if self.state in ("DISABLED", "FAULT"):
                        self.state, changed = "ENABLED", True
                elif cmd == "disable":
                    self.counts["disable"] += 1
                    self.state, self.homed, self.busy, self.motion = "DISABLED", False, False, None
                    changed = True
                elif cmd == "home":
                    self.counts["home"] += 1
                    if self.state == "ENABLED" and self.homing_until is None:
                        self.busy, self.homing_until, changed = True, now + HOMING_S, True
            for s in self.take("trajectory_j/set_ratio", self.set_ratio):
                self.counts["set_ratio"] += 1
                if 0.0 < s.data <= 1.0:
                    self.ratio = s.data
                    self.ratio_out.write(Float64(data=self.ratio))
            for _ in self.take("hold", self.hold):
                self.counts["hold"] += 1
                if self.motion is not None:
                    self.motion, self.busy, changed = None, False, True
            for s in self.take("move_cp", self.move_cp):
                self.counts["move_cp"] += 1
                if not self.ready():
                    self.refuse("move_cp")
                    continue
                p, o = s.pose.position, s.pose.orientation
                goal = [p.x, p.y, p.z, o.x, o.y, o.z, o.w]
                d = math.dist(goal[:3], self.pose[:3])
                dur = max(MIN_MOVE_S, d / (TOP_SPEED_M_S * self.ratio))
                self.motion = ("cp", list(self.pose), goal, now, dur)
                self.busy, changed = True, True
            for s in self.take("servo_cp", self.servo_cp):
                self.counts["servo_cp"] += 1
                if self.ready() and self.motion is None:
                    p, o = s.pose.position, s.pose.orientation
                    self.pose = [p.x, p.y, p.z, o.x, o.y, o.z, o.w]
            for s in self.take("jaw/move_jp", self.jaw_move_jp):
                self.counts["jaw/move_jp"] += 1
                if not self.ready() or not s.position:
                    self.refuse("jaw/move_jp")
                    continue
                dur = max(MIN_MOVE_S, abs(s.position[0] - self.jaw) / JAW_SPEED_RAD_S)
                self.motion = ("jaw", self.jaw, s.position[0], now, dur)
                self.busy, changed = True, True
            if self.homing_until is not None and now >= self.homing_until:
                self.homing_until, self.homed, self.busy, changed = None, True, False, True
            if self.motion is not None:
                kind, a, b, t0, dur = self.motion
                s = min(1.0, (now - t0) / dur)
                if kind == "cp":
                    self.pose = [x + (y - x) * s for x, y in zip(a[:3], b[:3])] + nlerp(a[3:], b[3:], s)
                else:
                    self.jaw = a + (b - a) * s
                if s >= 1.0:
                    self.motion, self.busy, changed = None, False, True
            pose, jaw = list(self.pose), self.jaw
        if changed:
            self.publish_state()
        t = stamp()
        msg = PoseStamped(header=Header(stamp=t), pose=Pose(
            position=Point(*pose[:3]), orientation=Quaternion(*pose[3:])))
        self.measured_cp.write(msg)
        self.setpoint_cp.write(msg)
        self.measured_js.write(JointState(header=Header(stamp=t), name=["jaw"], position=[jaw],
                                          velocity=[0.0], effort=[0.0]))

    def describe(self):
        with self.lock:
            return {"state": self.state, "homed": self.homed, "busy": self.busy,
                    "ratio": self.ratio, "counts": dict(self.counts),
                    "pose": [round(x, 6) for x in self.pose], "jaw": self.jaw}


def main():
    import argparse
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--domain-id", type=int, required=True)
    ap.add_argument("--arms", default="PSM1,PSM2")
    ap.add_argument("--lose-first", action="store_true",
                    help="drop the first sample of each command topic after each reset")
    ap.add_argument("--ignore", action="append", default=[],
                    help="a command topic (e.g. trajectory_j/set_ratio) whose samples are dropped")
    ap.add_argument("--pose", action="append", default=[],
                    help="ARM=x,y,z,qx,qy,qz,qw: where ARM starts (m, unit quaternion)")
    args = ap.parse_args()
    dp = DomainParticipant(args.domain_id)
    starts = {}
    for p in args.pose:
        name, values = p.split("=")
        starts[name] = [float(v) for v in values.split(",")]
    arms = {n: Arm(dp, n, starts.get(n, [0.0, 0.0, -0.1, 0.0, 0.0, 0.0, 1.0]),
                   lose_first=args.lose_first, ignore=args.ignore)
            for n in args.arms.split(",")}
    quit_flag = threading.Event()

    def loop():
        period = 1.0 / RATE_HZ
        nxt = time.monotonic()
        while not quit_flag.is_set():
            now = time.monotonic()
            try:
                for a in arms.values():
                    a.step(now)
            except Exception:  # a stand-in that stops serving must not look alive
                import os
                import traceback
                traceback.print_exc()
                os._exit(3)
            nxt += period
            time.sleep(max(0.0, nxt - time.monotonic()))

    thread = threading.Thread(target=loop, daemon=True)
    thread.start()
    print("ready", flush=True)
    for line in sys.stdin:
        words = line.split()
        if not words:
            continue
        try:
            if words[0] == "status":
                print(json.dumps({n: a.describe() for n, a in arms.items()}), flush=True)
            elif words[0] == "reset":
                for a in arms.values():
                    a.reset(homed=words[1] == "homed")
                print("ok", flush=True)
            elif words[0] == "error":
                arms[words[1]].fault(" ".join(words[2:]))
                print("ok", flush=True)
            elif words[0] == "pose":
                a = arms[words[1]]
                with a.lock:
                    a.pose, a.motion, a.busy = [float(v) for v in words[2:9]], None, False
                print("ok", flush=True)
            elif words[0] == "quit":
                break
            else:
                print(f"unknown command {words[0]!r}", flush=True)
        except (KeyError, IndexError, ValueError) as e:
            print(f"bad command {line.strip()!r}: {e}", flush=True)
    quit_flag.set()
    thread.join()


if __name__ == "__main__":
    main()
