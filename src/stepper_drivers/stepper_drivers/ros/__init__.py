"""The ROS layer: one generic node over any vendor, its services, publishing, trajectory
interface, lifecycle variant, process and executables.
"""
