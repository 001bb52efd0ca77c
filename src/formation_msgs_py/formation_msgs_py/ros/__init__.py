"""The messages' rclpy side: QoS profiles (:mod:`qos`) and conversions to and from ROS message objects
(:mod:`conversions`)."""
