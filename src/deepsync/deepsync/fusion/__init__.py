"""Position fusion: geodesy, TDOA solving, covariance and tracking."""
