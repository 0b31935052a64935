"""The simulator's version (written into every run's metadata and LAS header)."""
__version__ = "0.1.0"
