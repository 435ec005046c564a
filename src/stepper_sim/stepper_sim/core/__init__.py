"""What every simulator shares: the axis and its motion model, homing, line timing, the pty line,
link faults, the CAN broker and the ROS node around a simulator.
"""
