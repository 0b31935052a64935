"""Ladar simulator core: NumPy/SciPy/embreex, never Blender.  See ../docs/ and the paper's Figure 4."""
__version__ = "0.1.0"
