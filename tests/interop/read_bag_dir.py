"""Reads a rosbag2 bag directory with the field's readers: rosbags (which opens it as one bag
through its metadata.yaml) and Foxglove's mcap + mcap-ros2-support (each split on its own,
decoding CDR from the split's ros2msg schemas). Prints one JSON object: what rosbags sees
(message count, messages per topic, each message decoded), and per split what
mcap_ros2 decodes.

usage: read_bag_dir.py DIR
"""

import json
import sys
from pathlib import Path

from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rosbags.rosbag2 import Reader
from rosbags.typesys import Stores, get_typestore, get_types_from_msg


def main():
    path = Path(sys.argv[1])
    out = {"rosbags": {"topics": {}, "decoded": 0}, "splits": {}}
    typestore = get_typestore(Stores.ROS2_JAZZY)
    with Reader(path) as reader:
        for connection in reader.connections:
            typestore.register(get_types_from_msg(connection.msgdef.data, connection.msgtype))
        out["rosbags"]["message_count"] = reader.message_count
        for connection, _, raw in reader.messages():
            topics = out["rosbags"]["topics"]
            topics[connection.topic] = topics.get(connection.topic, 0) + 1
            typestore.deserialize_cdr(raw, connection.msgtype)
            out["rosbags"]["decoded"] += 1
    for split in sorted(path.glob("*.mcap")):
        with open(split, "rb") as f:
            reader = make_reader(f, decoder_factories=[DecoderFactory()])
            out["splits"][split.name] = sum(1 for _ in reader.iter_decoded_messages())
    print(json.dumps(out))


if __name__ == "__main__":
    main()
