"""Launches defvol's node, always active or managed.

    ros2 launch defvol defvol.launch.py scene_file:=organ.yaml
    ros2 launch defvol defvol.launch.py managed:=true                  # configured, then activated
    ros2 launch defvol defvol.launch.py managed:=true autostart:=false # left to a lifecycle manager

Arguments: namespace (default /), scene_file (default: the embedded scene), record (an MCAP
file, default none), managed (default false), autostart (managed only, default true: this
launch file configures the node and activates it once inactive, as nav2's lifecycle manager
would; false leaves it unconfigured for `ros2 lifecycle set` or a manager).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, EmitEvent, RegisterEventHandler
from launch.conditions import IfCondition, UnlessCondition
from launch.events import matches_action
from launch.substitutions import AndSubstitution, LaunchConfiguration
from launch_ros.actions import LifecycleNode, Node
from launch_ros.event_handlers import OnStateTransition
from launch_ros.events.lifecycle import ChangeState
from lifecycle_msgs.msg import Transition


def generate_launch_description():
    managed = LaunchConfiguration("managed")
    autostart = AndSubstitution(managed, LaunchConfiguration("autostart"))
    parameters = [{"scene_file": LaunchConfiguration("scene_file"), "record": LaunchConfiguration("record")}]
    common = dict(
        package="defvol",
        executable="defvol_node",
        name="defvol",
        namespace=LaunchConfiguration("namespace"),
        parameters=parameters,
        output="screen",
    )
    always_active = Node(condition=UnlessCondition(managed), **common)
    lifecycle = LifecycleNode(condition=IfCondition(managed), arguments=["--managed"], **common)
    configure = EmitEvent(
        condition=IfCondition(autostart),
        event=ChangeState(
            lifecycle_node_matcher=matches_action(lifecycle), transition_id=Transition.TRANSITION_CONFIGURE
        ),
    )
    activate_when_inactive = RegisterEventHandler(
        condition=IfCondition(autostart),
        event_handler=OnStateTransition(
            target_lifecycle_node=lifecycle,
            start_state="configuring",
            goal_state="inactive",
            entities=[
                EmitEvent(
                    event=ChangeState(
                        lifecycle_node_matcher=matches_action(lifecycle), transition_id=Transition.TRANSITION_ACTIVATE
                    )
                )
            ],
        ),
    )
    return LaunchDescription(
        [
            DeclareLaunchArgument("namespace", default_value="/"),
            DeclareLaunchArgument("scene_file", default_value=""),
            DeclareLaunchArgument("record", default_value=""),
            DeclareLaunchArgument("managed", default_value="false"),
            DeclareLaunchArgument("autostart", default_value="true"),
            always_active,
            lifecycle,
            activate_when_inactive,
            configure,
        ]
    )
