"""Is a candidate the same place, and where: registration (:mod:`.registration`), the tests on it
(:mod:`.verifier`), the loop covariance (:mod:`.covariance`) and the mixed-pixel filter of
tight spaces (:mod:`.mixed_pixels`).
"""
