"""The parameter client the rclpy scripts share: rclpy's own AsyncParameterClient on a
node, and a wait for one reply."""

import rclpy
from rclpy.parameter_client import AsyncParameterClient


def connect(node, target):
    """The parameter client of `target`, once its services are found (20 s at most), and a
    function that waits for a future's reply (10 s at most)."""
    client = AsyncParameterClient(node, target)
    if not client.wait_for_services(timeout_sec=20.0):
        raise SystemExit(f"{target}: parameter services not found")

    def wait(future):
        rclpy.spin_until_future_complete(node, future, timeout_sec=10.0)
        if future.result() is None:
            raise SystemExit("no reply")
        return future.result()

    return client, wait
