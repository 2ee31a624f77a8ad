"""Reads a bag with Foxglove's rosbag2-compatible reader (mcap + mcap-ros2-support), which
decodes CDR from the ros2msg schemas in the file. Prints one JSON object: messages per
topic, the profile, each channel's QoS metadata presence, and decoded values to compare.

usage: read_bag.py FILE.mcap
"""

import json
import sys

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory


def main():
    out = {"topics": {}, "schemas": {}, "qos": {}, "meshes": [], "feedback_z": [], "poses_z": [], "images": {}}
    with open(sys.argv[1], "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        out["profile"] = reader.get_header().profile
        summary = reader.get_summary()
        for channel in summary.channels.values():
            out["qos"][channel.topic] = "offered_qos_profiles" in channel.metadata
            out["schemas"][channel.topic] = summary.schemas[channel.schema_id].name
        for schema, channel, message, decoded in reader.iter_decoded_messages():
            out["topics"][channel.topic] = out["topics"].get(channel.topic, 0) + 1
            if channel.topic.endswith("deformed_mesh"):
                out["meshes"].append({"step": decoded.step, "nodes": len(decoded.positions) // 3, "first": [float(v) for v in decoded.positions[:3]], "peak": float(max(decoded.scalars))})
            elif channel.topic.endswith("tool_feedback"):
                out["feedback_z"].append(decoded.wrench.force.z)
            elif channel.topic.endswith("tool_pose"):
                out["poses_z"].append(decoded.pose.position.z)
            elif schema.name == "sensor_msgs/msg/Image":
                out["images"][channel.topic] = [decoded.width, decoded.height, decoded.encoding, len(decoded.data)]
    print(json.dumps(out))


if __name__ == "__main__":
    main()
