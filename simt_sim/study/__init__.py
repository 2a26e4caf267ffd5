"""Studies: a spec resolved once into a plan, launch batches recorded and replayed, the
table's rows, sampling, Dask, and the regression goldens."""
