"""CiA 402 (IEC 61800-7-201): the state machine tables and walker, the modes of operation and the
drive base of the CiA 402 vendors (no rclpy).
"""
