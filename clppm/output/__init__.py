"""What a render leaves: the film (radiance to XYZ, sRGB, exposure and the report: film),
checkpoints (checkpoint) and the output paths, sidecars and lock (paths).
"""
