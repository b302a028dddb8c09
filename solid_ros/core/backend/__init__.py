"""The pose graph that closes the loop: keyframes, odometry and loops in gtsam iSAM2
(:mod:`.posegraph`, :mod:`.solver`), their noise (:mod:`.noise`), the loop gate (:mod:`.gate`),
segments after odometry jumps (:mod:`.segments`) and the map of keyframe clouds
(:mod:`.mapping`).
"""
