"""ROS 2's own client library (rclpy on Fast DDS) names files to a running defvol node the
way `ros2 param set NODE scene_file PATH` does, while it listens to everything the node says
(its diagnostics, /rosout); prints each answer and every text heard as one JSON object.

Usage: rclpy_files.py NODE PATH...; ROS_DOMAIN_ID picks the domain.
"""

import json
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from rcl_interfaces.msg import Log
from rclpy.parameter import Parameter
from parameter_client import connect


def main():
    target, paths = sys.argv[1], sys.argv[2:]
    namespace = target.rsplit("/", 1)[0]
    rclpy.init()
    node = rclpy.create_node("rclpy_files")
    heard = []
    node.create_subscription(DiagnosticArray, f"{namespace}/diagnostics", lambda m: heard.append(str(m)), 100)
    node.create_subscription(Log, "/rosout", lambda m: heard.append(m.msg), 1000)
    client, wait = connect(node, target)

    answers = {}
    for path in paths:
        result = wait(client.set_parameters([Parameter("scene_file", value=path)])).results[0]
        answers[path] = {"successful": result.successful, "reason": result.reason}
    # What the node says after the last set (a reload, diagnostics) is heard too.
    end = time.monotonic() + 2.0
    while time.monotonic() < end:
        rclpy.spin_once(node, timeout_sec=0.1)
    print(json.dumps({"answers": answers, "heard": heard}))
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
