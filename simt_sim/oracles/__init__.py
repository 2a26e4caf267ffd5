"""Oracles: the exact lockstep executor and the plain-Python reference replay.

They may see the BVH and the rays (the replay may not): the yardsticks the SIMT model's
replay is checked against.
"""
