"""A Python ROS 2 node built against defvol_interfaces (the package generated from
defvol_interfaces/ by rosidl) subscribes to a running defvol node's `deformed_mesh` and
`warped_volume/info` and calls its `load_scene`, and prints what it got as one JSON object.
It streams tool poses above the organ as a device would, so that the solver, which sleeps
at rest, is stepping (and publishing meshes) however late this peer joins.

Usage: rclpy_interfaces.py NAMESPACE (e.g. /robot); ROS_DOMAIN_ID picks the domain, and
PYTHONPATH / AMENT_PREFIX_PATH must reach the built defvol_interfaces.
"""

import json
import math
import sys
import time

import rclpy
from defvol_interfaces.msg import DeformedMesh, WarpedVolumeInfo
from defvol_interfaces.srv import LoadScene
from geometry_msgs.msg import PoseStamped
from rclpy.qos import DurabilityPolicy, QoSProfile, ReliabilityPolicy


def main():
    namespace = sys.argv[1]
    rclpy.init()
    node = rclpy.create_node("interfaces_peer")
    meshes, infos = [], []
    node.create_subscription(DeformedMesh, f"{namespace}/deformed_mesh", meshes.append, 10)
    latched = QoSProfile(
        depth=1, reliability=ReliabilityPolicy.RELIABLE, durability=DurabilityPolicy.TRANSIENT_LOCAL
    )
    node.create_subscription(WarpedVolumeInfo, f"{namespace}/warped_volume/info", infos.append, latched)
    client = node.create_client(LoadScene, f"{namespace}/load_scene")
    if not client.wait_for_service(timeout_sec=20.0):
        raise SystemExit("load_scene not found")
    poses = node.create_publisher(PoseStamped, f"{namespace}/tool_pose", 10)
    end = time.monotonic() + 20.0
    while time.monotonic() < end and (len(meshes) < 3 or not infos):
        pose = PoseStamped()
        pose.header.frame_id = "world"
        pose.header.stamp = node.get_clock().now().to_msg()
        pose.pose.position.z = 0.15 + 0.005 * math.sin(4.0 * time.monotonic())
        pose.pose.orientation.w = 1.0
        poses.publish(pose)
        rclpy.spin_once(node, timeout_sec=0.02)
    future = client.call_async(LoadScene.Request(scene="volume: [phantom\nmesh: {}"))
    rclpy.spin_until_future_complete(node, future, timeout_sec=10.0)
    reply = future.result()
    mesh = meshes[-1]
    info = infos[-1]
    print(
        json.dumps(
            {
                "meshes": len(meshes),
                "mesh": {
                    "frame_id": mesh.header.frame_id,
                    "stamp": [mesh.header.stamp.sec, mesh.header.stamp.nanosec],
                    "step": mesh.step,
                    "positions": [float(p) for p in mesh.positions],
                    "triangles": [int(t) for t in mesh.triangles],
                    "scalar_name": mesh.scalar_name,
                },
                "info": {
                    "service_name": info.service_name,
                    "dims": [int(d) for d in info.dims],
                    "spacing": [float(s) for s in info.spacing],
                    "direction": [float(d) for d in info.direction],
                },
                "load_scene": {"success": reply.success, "message": reply.message},
            }
        )
    )
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
