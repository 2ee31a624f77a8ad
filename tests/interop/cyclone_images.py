"""Eclipse Cyclone DDS subscribes to the node's images and deformed meshes with
sensor-data QoS (best effort, the last 5), as a viewer does, and prints the stamps of what
it received, per topic, as one JSON object (as rclpy_images.py does).

Usage: cyclone_images.py SECONDS NAMESPACE; ROS_DOMAIN_ID picks the domain, CYCLONEDDS_URI
the interface.
"""

import json
import os
import sys
import time
from dataclasses import dataclass

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
import cyclonedds.idl.types as t
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic

from cyclone_peer import DeformedMesh, Header


@dataclass
class Image(IdlStruct, typename="sensor_msgs::msg::dds_::Image_"):
    header: Header
    height: t.uint32
    width: t.uint32
    encoding: str
    is_bigendian: t.uint8
    step: t.uint32
    data: t.sequence[t.uint8]


TOPICS = {"raycast/image": Image, "dpcm/height": Image, "dpcm/image": Image, "deformed_mesh": DeformedMesh}


def main():
    seconds, namespace = float(sys.argv[1]), sys.argv[2].strip("/")
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    sensor = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
    readers = {topic: DataReader(dp, Topic(dp, f"rt/{namespace}/{topic}", ty), qos=sensor) for topic, ty in TOPICS.items()}
    stamps = {topic: [] for topic in TOPICS}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        for topic, reader in readers.items():
            for sample in reader.take(N=100):
                if not hasattr(sample, "header"):
                    continue  # the writer's end (an InvalidSample), not a message
                stamps[topic].append(sample.header.stamp.sec * 1_000_000_000 + sample.header.stamp.nanosec)
        time.sleep(0.005)
    print(json.dumps(stamps))


if __name__ == "__main__":
    main()
