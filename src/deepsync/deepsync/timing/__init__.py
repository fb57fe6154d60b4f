"""Sub-sample timing of detected cells: classical estimators with an honest 1-sigma, the Cramer-Rao bound, the timing stage."""
