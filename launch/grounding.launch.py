"""ROS 2 launch file (needs a full ROS 2 install: launch, launch_ros, rviz2; not available as wheels).

    ros2 launch rg_ros grounding.launch.py [params_file:=...] [rviz:=false] [rviz_config:=...]

Starts rg-node with the parameters of config/grounding.yaml and RViz with config/grounding.rviz.
From a pip install the same is `rg-node --params config/grounding.yaml` (and rviz2 by hand).
"""
import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    share = get_package_share_directory("rg_ros")
    params = LaunchConfiguration("params_file")
    rviz_config = LaunchConfiguration("rviz_config")
    return LaunchDescription([
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "grounding.yaml"),
                              description="ros__parameters YAML of rg_node"),
        DeclareLaunchArgument("rviz_config", default_value=os.path.join(share, "config", "grounding.rviz"),
                              description="RViz configuration"),
        DeclareLaunchArgument("rviz", default_value="true", description="start RViz"),
        Node(package="rg_ros", executable="rg-node", name="rg_node", output="screen", emulate_tty=True,
             parameters=[params]),
        Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
             arguments=["-d", rviz_config], condition=IfCondition(LaunchConfiguration("rviz"))),
    ])
