"""The front end: per-scan pose tracking from the walls (the paper's method, made robust).

Steps, one module each: `heading` (projection histograms, paper §II), `rotation` (direction
spectra), `translation` and `gated` (1-D histogram correlation, paper §III), `refine` (the joint
2-D check), `profile` (turns from the range profile), `covariance` (what the match says about its
own uncertainty). `estimator.ManhattanEstimator` composes them; `params.EstimatorParams` holds the
paper's parameters as named defaults.
"""
