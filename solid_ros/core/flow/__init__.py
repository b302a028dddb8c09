"""The per-scan flow over the rooms below: the loop detector (:mod:`.detector`) and the loop
closure that adds odometry and the pose graph (:mod:`.closure`).
"""
