"""Device profiles shared by several vendors (no rclpy)."""
