"""The scene a config describes, on the host: spectra and colour matching (spectra, colorimetry),
the skin layers (skin), the wavelength bands (bands), the light and camera (light, camera), the
voxel volume (volume) and whether the scene can give a meaningful image (scene).
"""
