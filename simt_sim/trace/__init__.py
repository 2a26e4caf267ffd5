"""Recording: each ray's traversal as an op stream (OpTrace), path traces, trace files."""
