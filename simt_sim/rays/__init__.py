"""Rays: the paper's primary, ambient-occlusion and diffuse rays in warp order, and Morton
orders."""
