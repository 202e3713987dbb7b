"""ReasonGrounder ROS 2 node (rclpy): converts messages and calls rg_core. The only package that
imports ROS; the node, message conversions and CLI tools land with the ROS node issue."""
