"""The drive contract: Bus, Drive, DriveState, errors, the units and parameter rules every vendor
shares (no rclpy).
"""
