"""The SOLiD descriptor of one scan: preprocessing and description (:mod:`.solid`), comparison and
heading (:mod:`.matching`), and the sensor mounting that levels a scan first (:mod:`.mount`).
"""
