"""Which stored keyframes a query is verified against besides the descriptor's: the proposal
record (:mod:`.proposal`), keyframes by position in the pose graph (:mod:`.position`), by
shared structure (:mod:`.covisibility`), and the hit list the detector verifies (:mod:`.hits`).
"""
