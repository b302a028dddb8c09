"""The SOLiD descriptor of one scan: preprocessing and description (:mod:`.solid`), comparison and
heading (:mod:`.matching`), the sensor mounting that levels a scan first (:mod:`.mount`), and
what the first clouds say about the sensor and whether the settings fit it (:mod:`.sensor`,
:mod:`.sensor_check`).
"""
