"""Poses for the scans: odometry samples, tracks and the path driven (:mod:`.track`), and KISS-ICP
over the clouds when there is no odometry (:mod:`.kiss`).
"""
