"""The simulator node (rclpy) and what only it needs: stepping policy, display topics, run bag, timing."""
