"""rg_node (mapping + grounding) and RViz.

    ros2 launch rg_ros grounding.launch.py [camera:=/camera] [params_file:=...] [rviz:=false]

rg_node subscribes to relative names (rgb/image, depth/image, rgb/camera_info, pose, odom) and
serves `ground`; this file remaps the inputs to a camera driver's topics under `camera`
(realsense2_camera 4.x: camera:=/camera/camera) or to single topics (color_topic:=...), and the
service becomes /ground. Parameters: config/grounding.yaml (params_file:=...).
"""
import os

from ament_index_python.packages import PackageNotFoundError, get_package_prefix, get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, LogInfo, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

# node input -> (launch argument, default under `camera`); rg_ros.params.INPUTS holds the same defaults
REMAPS = {
    "rgb/image": ("color_topic", "/color/image_raw"),
    "depth/image": ("depth_topic", "/aligned_depth_to_color/image_raw"),
    "rgb/camera_info": ("camera_info_topic", "/color/camera_info"),
    "pose": ("pose_topic", "/pose"),
}


def rviz(context):
    """RViz when rviz:=true and rviz2 is installed; without rviz2 (the PyPI wheels have none) say so
    and run the node alone."""
    if LaunchConfiguration("rviz").perform(context).lower() not in ("true", "1", "yes"):
        return []
    config = LaunchConfiguration("rviz_config").perform(context)
    try:
        get_package_prefix("rviz2")
    except PackageNotFoundError:
        return [LogInfo(msg=f"rviz2 is not installed: RViz not started (open {config} in it elsewhere; "
                            "rviz:=false hides this)")]
    return [Node(package="rviz2", executable="rviz2", name="rviz2", output="screen", arguments=["-d", config])]


def generate_launch_description():
    share = get_package_share_directory("rg_ros")
    camera = LaunchConfiguration("camera")
    args = [
        DeclareLaunchArgument("camera", default_value="/camera", description="namespace of the RGB-D driver"),
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "grounding.yaml"),
                              description="ros__parameters YAML of rg_node"),
        DeclareLaunchArgument("rviz_config", default_value=os.path.join(share, "config", "grounding.rviz"),
                              description="RViz configuration"),
        DeclareLaunchArgument("rviz", default_value="true", description="start RViz"),
        DeclareLaunchArgument("odom_topic", default_value="/odom", description="nav_msgs/Odometry (pose_source odometry)"),
    ]
    args += [DeclareLaunchArgument(arg, default_value=[camera, suffix], description=f"remapped to rg_node's {name}")
             for name, (arg, suffix) in REMAPS.items()]
    remappings = [(name, LaunchConfiguration(arg)) for name, (arg, _) in REMAPS.items()]
    remappings.append(("odom", LaunchConfiguration("odom_topic")))
    return LaunchDescription(args + [
        # sigterm_timeout: the node saves the map on shutdown when save_on_shutdown is set
        Node(package="rg_ros", executable="rg-node", name="rg_node", output="screen", emulate_tty=True,
             parameters=[LaunchConfiguration("params_file")], remappings=remappings, sigterm_timeout="30"),
        OpaqueFunction(function=rviz),
    ])
