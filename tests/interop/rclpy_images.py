"""ROS 2's own client library (rclpy on Fast DDS, Jazzy's default middleware, as RViz and
rqt_image_view are) subscribes to the node's images with sensor-data QoS, as an image
viewer does, and prints the stamps of what it received, per topic, as one JSON object.

Usage: rclpy_images.py SECONDS NAMESPACE; ROS_DOMAIN_ID picks the domain, and
FASTDDS_DEFAULT_PROFILES_FILE a Fast DDS profile (its receive buffers) as for any rclpy node.
"""

import json
import sys
import time

import rclpy
from rclpy.qos import qos_profile_sensor_data
from sensor_msgs.msg import Image

TOPICS = ["raycast/image", "dpcm/height", "dpcm/image"]


def main():
    seconds, namespace = float(sys.argv[1]), sys.argv[2]
    rclpy.init()
    node = rclpy.create_node("rclpy_images")
    stamps = {topic: [] for topic in TOPICS}

    def keep(topic):
        return lambda m: stamps[topic].append(m.header.stamp.sec * 1_000_000_000 + m.header.stamp.nanosec)

    for topic in TOPICS:
        node.create_subscription(Image, f"{namespace}/{topic}", keep(topic), qos_profile_sensor_data)
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.05)
    print(json.dumps(stamps))
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
