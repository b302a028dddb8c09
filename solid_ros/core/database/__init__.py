"""What the detector remembers: the rolling descriptor store and its search (:mod:`.descriptors`),
the keyframe clouds kept for verification (:mod:`.clouds`), and saving and loading both
(:mod:`.persistence`; the file format and its checked reading, :mod:`.archive`; crash-safe
writes, :mod:`.atomic`).
"""
