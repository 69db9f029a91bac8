"""The ROS 2 node, `rangeret ros2`: labels every `sensor_msgs/PointCloud2` of a topic and
publishes it again with a `label` and a `confidence` per point.

Beside `workers` and `service`, it imports only `rangeret` and ROS 2's own modules (the `ros2`
extra); `ros2node.commands` is the entry point and imports neither rclpy nor torch.
"""
