"""Comparing and measuring renders: image metrics (metrics), converged references (reference),
method comparisons (compare), spectral reflectance (reflectance), fits of the skin parameters to
measured spectra (fit, nist).
"""
