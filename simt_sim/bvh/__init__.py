"""Bounding volume hierarchies: the binned-SAH builder and the Aila-Laine GPU layout."""
