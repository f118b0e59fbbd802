#!/usr/bin/env python3
"""Decode every message on every channel of MCAP files with readers this project did not
write: the `mcap` package with `mcap-ros2-support` (each message from the file's own
`ros2msg` schema), and `rosbags` (its own CDR reader, types registered from the same schemas).
Prints one JSON line per file: its messages per topic, per reader; exits 1 on any failure."""

import json
import sys
from pathlib import Path


def with_mcap(path):
    from mcap.reader import make_reader
    from mcap_ros2.decoder import DecoderFactory

    counts = {}
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            assert channel.message_encoding == "cdr", channel
            assert schema.encoding == "ros2msg", schema
            assert "offered_qos_profiles" in channel.metadata, channel
            if channel.topic == "/stitch/events":
                json.loads(decoded.record_json)  # the record inside is JSON
            if schema.name == "sensor_msgs/msg/CompressedImage":
                assert decoded.format == "jpeg", decoded.format
                assert bytes(decoded.data[:2]) == b"\xff\xd8", "a JPEG"
            if schema.name == "foxglove_msgs/msg/ImageAnnotations":
                assert decoded.points and decoded.points[0].type == 3, "a line strip"
                assert len(decoded.points[0].points) > 2, "the needle's arc or the thread"
            if schema.name == "stitch_msgs/msg/ThreadTrace":
                t = decoded
                assert len(t.sigma_m) == len(t.points), "a sigma per point"
                assert len(t.hidden_from_m) == len(t.hidden_to_m), "hidden stretches in pairs"
                if t.ok:
                    assert len(t.points) >= 2 and t.failure == "", t.failure
                    assert all(0 <= a <= b <= t.length_m + 1e-9
                               for a, b in zip(t.hidden_from_m, t.hidden_to_m)), "inside the curve"
                else:
                    assert not t.points and json.loads(t.failure)["kind"], t.failure
            if schema.name == "geometry_msgs/msg/PoseStamped":
                q = decoded.pose.orientation
                norm = q.x * q.x + q.y * q.y + q.z * q.z + q.w * q.w
                assert abs(norm - 1) < 1e-9, f"{channel.topic}: |q|² = {norm}"
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
        summary = reader.get_summary()
        names = [a.name for a in reader.iter_attachments()]
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return counts, names, meta, summary.statistics.message_count


def with_rosbags(path):
    from rosbags.highlevel import AnyReader

    counts = {}
    with AnyReader([Path(path)]) as reader:
        for connection, _, raw in reader.messages():
            msg = reader.deserialize(raw, connection.msgtype)
            if connection.topic == "/stitch/events":
                json.loads(msg.record_json)
            counts[connection.topic] = counts.get(connection.topic, 0) + 1
    return counts


def main():
    ok = True
    for path in sys.argv[1:]:
        try:
            counts, attachments, meta, total = with_mcap(path)
            rosbags = with_rosbags(path)
            same = counts == rosbags and sum(counts.values()) == total
            print(json.dumps({"file": path, "mcap": counts, "rosbags": rosbags,
                              "attachments": attachments, "metadata": meta,
                              "agree": same}))
            ok = ok and same
        except Exception as e:  # a reader that fails is the answer
            print(json.dumps({"file": path, "error": f"{type(e).__name__}: {e}"}))
            ok = False
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
