"""The robot's ROS-free vocabulary: topic and service names, the parameter core and the pitch
conversions. Every part imports it, the ROS shells (krang_ros and the node modules) included; it
imports nothing of ROS, so offline tools and tests use it without rclpy."""
