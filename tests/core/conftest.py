"""Core tests: no Blender.  The folders mirror core/'s layers; ``scenes.py`` (shared test scenes) sits here."""
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
