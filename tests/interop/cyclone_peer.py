"""A ROS 2 peer written with Eclipse Cyclone DDS (another DDS implementation, the same
wire format): it publishes tool poses and wrenches the way a tracker would, and reads the
node's outputs as ROS 2 types. Prints one JSON object with what it received.

usage: cyclone_peer.py SECONDS [NAMESPACE]
"""

import json
import os
import sys
import time
from dataclasses import dataclass, field

from cyclonedds.domain import DomainParticipant
from cyclonedds.idl import IdlStruct
import cyclonedds.idl.types as t
from cyclonedds.pub import DataWriter
from cyclonedds.qos import Policy, Qos
from cyclonedds.sub import DataReader
from cyclonedds.topic import Topic
from cyclonedds.util import duration


@dataclass
class Time(IdlStruct, typename="builtin_interfaces::msg::dds_::Time_"):
    sec: t.int32
    nanosec: t.uint32


@dataclass
class Header(IdlStruct, typename="std_msgs::msg::dds_::Header_"):
    stamp: Time
    frame_id: str


@dataclass
class Point(IdlStruct, typename="geometry_msgs::msg::dds_::Point_"):
    x: t.float64
    y: t.float64
    z: t.float64


@dataclass
class Vector3(IdlStruct, typename="geometry_msgs::msg::dds_::Vector3_"):
    x: t.float64
    y: t.float64
    z: t.float64


@dataclass
class Quaternion(IdlStruct, typename="geometry_msgs::msg::dds_::Quaternion_"):
    x: t.float64
    y: t.float64
    z: t.float64
    w: t.float64


@dataclass
class Pose(IdlStruct, typename="geometry_msgs::msg::dds_::Pose_"):
    position: Point
    orientation: Quaternion


@dataclass
class PoseStamped(IdlStruct, typename="geometry_msgs::msg::dds_::PoseStamped_"):
    header: Header
    pose: Pose


@dataclass
class Wrench(IdlStruct, typename="geometry_msgs::msg::dds_::Wrench_"):
    force: Vector3
    torque: Vector3


@dataclass
class WrenchStamped(IdlStruct, typename="geometry_msgs::msg::dds_::WrenchStamped_"):
    header: Header
    wrench: Wrench


@dataclass
class DeformedMesh(IdlStruct, typename="defvol_interfaces::msg::dds_::DeformedMesh_"):
    header: Header
    positions: t.sequence[t.float32]
    triangles: t.sequence[t.uint32]
    scalar_name: str
    scalars: t.sequence[t.float32]
    step: t.uint64


@dataclass
class KeyValue(IdlStruct, typename="diagnostic_msgs::msg::dds_::KeyValue_"):
    key: str
    value: str


@dataclass
class DiagnosticStatus(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticStatus_"):
    level: t.uint8
    name: str
    message: str
    hardware_id: str
    values: t.sequence[KeyValue]


@dataclass
class DiagnosticArray(IdlStruct, typename="diagnostic_msgs::msg::dds_::DiagnosticArray_"):
    header: Header
    status: t.sequence[DiagnosticStatus]


def main():
    seconds = float(sys.argv[1])
    ns = sys.argv[2].strip("/") if len(sys.argv) > 2 else ""
    prefix = f"rt/{ns}/" if ns else "rt/"
    dp = DomainParticipant(int(os.environ.get("ROS_DOMAIN_ID", "0")))
    sensor = Qos(Policy.Reliability.BestEffort, Policy.History.KeepLast(5))
    reliable = Qos(Policy.Reliability.Reliable(duration(seconds=1)), Policy.History.KeepLast(50))
    pose_writer = DataWriter(dp, Topic(dp, prefix + "tool_pose", PoseStamped), qos=reliable)
    wrench_writer = DataWriter(dp, Topic(dp, prefix + "tool_wrench", WrenchStamped), qos=sensor)
    feedback = DataReader(dp, Topic(dp, prefix + "tool_feedback", WrenchStamped), qos=sensor)
    meshes = DataReader(dp, Topic(dp, prefix + "deformed_mesh", DeformedMesh), qos=reliable)
    diagnostics = DataReader(dp, Topic(dp, prefix + "diagnostics", DiagnosticArray), qos=reliable)
    got = {"feedback": 0, "meshes": 0, "diagnostics": 0, "max_force_z": 0.0, "max_displacement": 0.0, "statuses": [], "rejected_nan": False}
    start = time.time()
    sent = 0
    while time.time() - start < seconds:
        now = time.time()
        # Down from 10 cm to 7 cm over the first second, then held.
        s = min((now - start) / 1.0, 1.0)
        z = 0.10 - 0.03 * s
        stamp = Time(int(now), int((now % 1) * 1e9))
        pose_writer.write(PoseStamped(Header(stamp, "world"), Pose(Point(0.0, 0.0, z), Quaternion(0.0, 0.0, 0.0, 1.0))))
        if sent % 100 == 50:
            # A broken sample: the node must refuse it and keep going.
            pose_writer.write(PoseStamped(Header(stamp, "world"), Pose(Point(float("nan"), 0.0, z), Quaternion(0.0, 0.0, 0.0, 1.0))))
        wrench_writer.write(WrenchStamped(Header(stamp, "world"), Wrench(Vector3(0.0, 0.0, 0.0), Vector3(0.0, 0.0, 0.0))))
        sent += 1
        for sample in feedback.take(N=100):
            got["feedback"] += 1
            got["max_force_z"] = max(got["max_force_z"], sample.wrench.force.z)
        for sample in meshes.take(N=100):
            got["meshes"] += 1
            got["nodes"] = len(sample.positions) // 3
            got["triangles"] = len(sample.triangles) // 3
            got["max_displacement"] = max(got["max_displacement"], max(sample.scalars, default=0.0))
        for sample in diagnostics.take(N=10):
            got["diagnostics"] += 1
            got["statuses"] = sorted({s.name for s in sample.status})
            for s in sample.status:
                if s.name == "defvol: inputs" and any(kv.key == "rejected_not_finite" for kv in s.values):
                    got["rejected_nan"] = True
        time.sleep(0.01)
    got["sent"] = sent
    print(json.dumps(got))


if __name__ == "__main__":
    main()
