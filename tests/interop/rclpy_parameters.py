"""ROS 2's own client library (rclpy on Fast DDS) asks a running defvol node about its
parameters the way `ros2 param` does, and prints what it was told as one JSON object.

Usage: rclpy_parameters.py NODE (e.g. /robot/defvol); ROS_DOMAIN_ID picks the domain.
"""

import json
import math
import sys

import rclpy
from rcl_interfaces.msg import ParameterType
from rclpy.parameter import Parameter
from parameter_client import connect


def main():
    target = sys.argv[1]
    rclpy.init()
    node = rclpy.create_node("rclpy_parameters")
    client, wait = connect(node, target)

    def set_one(name, value):
        result = wait(client.set_parameters([Parameter(name, value=value)])).results[0]
        return {"successful": result.successful, "reason": result.reason}

    def describe(name):
        d = wait(client.describe_parameters([name])).descriptors[0]
        return {
            "type": d.type,
            "description": d.description,
            "additional_constraints": d.additional_constraints,
            "read_only": d.read_only,
            "floating_point_range": [[r.from_value, r.to_value, r.step] for r in d.floating_point_range],
            "integer_range": [[r.from_value, r.to_value, r.step] for r in d.integer_range],
        }

    def value(name):
        v = wait(client.get_parameters([name])).values[0]
        return {ParameterType.PARAMETER_DOUBLE: v.double_value, ParameterType.PARAMETER_INTEGER: v.integer_value}.get(
            v.type, v.string_value
        )

    report = {
        "names": list(wait(client.list_parameters([], 0)).result.names),
        "solver.dt": describe("solver.dt"),
        "camera.width": describe("camera.width"),
        "backend": describe("backend"),
        "unknown": len(wait(client.describe_parameters(["solver.dtt"])).descriptors),
        "set": {
            "huge": set_one("solver.dt", 1e9),
            "nan": set_one("solver.dt", math.nan),
            "negative": set_one("solver.dt", -0.01),
            "string": set_one("solver.dt", "fast"),
            "backend": set_one("backend", "gpu"),
            "good": set_one("solver.dt", 0.005),
        },
        "dt_after": value("solver.dt"),
    }
    atomically = wait(
        client.set_parameters_atomically(
            [Parameter("camera.height", value=100), Parameter("camera.width", value=0)]
        )
    )
    report["atomically"] = {"successful": atomically.result.successful, "reason": atomically.result.reason}
    report["height_after"] = value("camera.height")
    print(json.dumps(report))
    node.destroy_node()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
