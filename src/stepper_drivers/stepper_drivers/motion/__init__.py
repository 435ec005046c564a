"""Motion planning over the drive contract: trajectories and their follower (no rclpy)."""
