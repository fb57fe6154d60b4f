"""Fusion: per-site arrivals to a position with an honest covariance.

``anchors`` turns cell arrivals into per-site ranges through the tower database, ``snapshot``
solves one stack on its own, ``tracker`` follows position, velocity and receiver clock with
every heard site as it comes, ``calibration`` estimates site clocks from a recording at known
positions, ``rssi`` is the power-based baseline we compare against, ``stage`` runs them for the
pipeline.
"""
