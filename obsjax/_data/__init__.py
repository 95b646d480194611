"""Observers on recorded data: sampled measurements (``_measurements.py``), the estimation driver
(``_estimate.py``) and its reading of CSV files and data frames (``_io.py``).

``estimate`` is a driver of the integration core (``obsjax/_integrate/``): its "plant" is the held
measurement signal.  The sample times are event breakpoints of ``_schedule.build`` (merged with the
observer's resets), so every solve runs between two samples and sees one piece of the hold; the sample
index is carried through the segmented scan of ``_segments.integrate``.
"""
