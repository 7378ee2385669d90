"""clppm: spectral progressive photon mapping of a layered voxel skin model in OpenCL."""
__version__ = "0.1.0"
