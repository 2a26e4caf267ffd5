"""The warp-level SIMT model: replay op traces under ideal scheduling, one scheme a module."""
