"""Readers and writers of data formats: bags, PointCloud2, point files, poses, candidate rows.

No rclpy: messages are duck-typed, so rclpy and rosbags messages both work.
"""
