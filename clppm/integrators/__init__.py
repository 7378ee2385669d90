"""The integrators: the photon pass, eye pass, photon grid and density estimators of progressive
photon mapping (photonpass, eyepass, hashgrid, estimators, beam, ppm), the unbiased path tracer
(pathtracer) and the one render loop both run in (driver).
"""
