"""Bounding volume hierarchies: the SAH builder (binned, swept or with spatial splits) and
the Aila-Laine GPU layout."""
