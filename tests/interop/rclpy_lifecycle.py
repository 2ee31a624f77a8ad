"""ROS 2's own client library (rclpy on Fast DDS) drives a managed defvol node and, side by
side, rclpy's own LifecycleNode (the reference: the rcl_lifecycle state machine rclcpp runs
too) through the same transitions, and prints what each answered as one JSON object.

Usage: rclpy_lifecycle.py NODE (e.g. /robot/defvol). The node starts on a scene whose
volume file does not exist, so its first configure fails (the reference's first configure
fails too); the `volume` parameter set to the phantom mends it. ROS_DOMAIN_ID picks the
domain.
"""

import json
import sys
import time

import rclpy
from diagnostic_msgs.msg import DiagnosticArray
from lifecycle_msgs.msg import Transition, TransitionEvent
from lifecycle_msgs.srv import ChangeState, GetAvailableStates, GetAvailableTransitions, GetState
from rclpy.executors import SingleThreadedExecutor
from rclpy.lifecycle import LifecycleNode, TransitionCallbackReturn
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

REFERENCE = "/reference"


class Reference(LifecycleNode):
    """rclpy's LifecycleNode, whose first configure fails as defvol's does on its bad scene."""

    def __init__(self):
        super().__init__("reference")
        self.configures = 0

    def on_configure(self, state):
        self.configures += 1
        return TransitionCallbackReturn.FAILURE if self.configures == 1 else TransitionCallbackReturn.SUCCESS


def state(s):
    return [s.id, s.label]


def description(t):
    return [t.transition.id, t.transition.label, state(t.start_state), state(t.goal_state)]


def main():
    target = sys.argv[1]
    namespace = target.rsplit("/", 1)[0]
    rclpy.init()
    reference = Reference()
    driver = rclpy.create_node("driver")
    executor = SingleThreadedExecutor()
    executor.add_node(reference)
    executor.add_node(driver)

    events = {REFERENCE: [], target: []}
    for name, seen in events.items():
        driver.create_subscription(
            TransitionEvent,
            f"{name}/transition_event",
            lambda m, seen=seen: seen.append(
                {
                    "transition": [m.transition.id, m.transition.label],
                    "start": state(m.start_state),
                    "goal": state(m.goal_state),
                    "stamped": m.timestamp > 0,
                }
            ),
            10,
        )
    diagnostics = []
    driver.create_subscription(DiagnosticArray, f"{namespace}/diagnostics", diagnostics.append, 10)

    clients = {}

    def call(node, srv, service, request):
        key = (node, service)
        if key not in clients:
            clients[key] = driver.create_client(srv, f"{node}/{service}")
            if not clients[key].wait_for_service(timeout_sec=20.0):
                raise SystemExit(f"{node}/{service} not found")
        future = clients[key].call_async(request)
        executor.spin_until_future_complete(future, timeout_sec=10.0)
        if future.result() is None:
            raise SystemExit(f"{node}/{service}: no reply")
        return future.result()

    def spin_for(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            executor.spin_once(timeout_sec=0.02)

    def outputs_for(seconds):
        spin_for(0.5)  # what was on its way before
        diagnostics.clear()
        spin_for(seconds)
        return len(diagnostics)

    def looked_at(node):
        return {
            "state": state(call(node, GetState, "get_state", GetState.Request()).current_state),
            "available": [
                description(t)
                for t in call(
                    node, GetAvailableTransitions, "get_available_transitions", GetAvailableTransitions.Request()
                ).available_transitions
            ],
        }

    def step(transition_id, label=""):
        answers = {}
        for node in (REFERENCE, target):
            request = ChangeState.Request(transition=Transition(id=transition_id, label=label))
            success = call(node, ChangeState, "change_state", request).success
            spin_for(0.3)
            answers[node] = {"success": success, **looked_at(node)}
            answers[node]["events"], events[node][:] = list(events[node]), []
        return answers

    def both(fn):
        return {node: fn(node) for node in (REFERENCE, target)}

    report = {
        "states": both(
            lambda n: [
                state(s)
                for s in call(n, GetAvailableStates, "get_available_states", GetAvailableStates.Request()).available_states
            ]
        ),
        "graph": both(
            lambda n: [
                description(t)
                for t in call(
                    n, GetAvailableTransitions, "get_transition_graph", GetAvailableTransitions.Request()
                ).available_transitions
            ]
        ),
        "initial": both(looked_at),
        "outputs": {"unconfigured": outputs_for(1.5)},
        "steps": [],
    }
    steps = report["steps"]
    steps.append(["activate while unconfigured", step(Transition.TRANSITION_ACTIVATE)])
    steps.append(["configure a scene that does not load", step(Transition.TRANSITION_CONFIGURE)])
    parameters = AsyncParameterClient(driver, target)
    parameters.wait_for_services(timeout_sec=10.0)
    future = parameters.set_parameters([Parameter("volume", value="phantom")])
    executor.spin_until_future_complete(future, timeout_sec=10.0)
    report["volume_set"] = future.result().results[0].successful
    steps.append(["configure", step(Transition.TRANSITION_CONFIGURE)])
    report["outputs"]["inactive"] = outputs_for(1.5)
    steps.append(["activate by its label", step(0, "activate")])
    report["outputs"]["active"] = outputs_for(3.0)
    steps.append(["an unknown id", step(99)])
    steps.append(["an unknown label", step(0, "explode")])
    steps.append(["deactivate", step(Transition.TRANSITION_DEACTIVATE)])
    report["outputs"]["deactivated"] = outputs_for(1.5)
    steps.append(["activate again", step(Transition.TRANSITION_ACTIVATE)])
    report["outputs"]["active_again"] = outputs_for(1.5)
    steps.append(["deactivate again", step(Transition.TRANSITION_DEACTIVATE)])
    steps.append(["cleanup", step(Transition.TRANSITION_CLEANUP)])
    report["outputs"]["cleaned_up"] = outputs_for(1.5)
    steps.append(["shutdown by its label", step(0, "shutdown")])
    steps.append(["configure when finalized", step(Transition.TRANSITION_CONFIGURE)])
    print(json.dumps(report))
    executor.shutdown()
    rclpy.shutdown()


if __name__ == "__main__":
    main()
