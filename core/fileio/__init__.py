"""File output: the run folder (EXR, PLY, NPZ, metadata; staged then renamed into place), LAS point clouds and
PNG previews/plots."""
