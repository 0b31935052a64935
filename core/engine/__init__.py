"""Frame engine: what every sensor system shares to run a frame (memory planning; blocks, stage log and random
streams follow).  Imports the layers below it, never a sensor system."""
