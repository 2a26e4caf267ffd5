"""Real tracers that measure the rays the SIMT model simulates: numba CPU, Embree, CUDA."""
