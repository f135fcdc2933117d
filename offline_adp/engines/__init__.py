"""Execution engines for the heavy loops: local (the default, in-process) and Dask
(:mod:`offline_adp.engines.dask`: distributed ingestion, FQI/FQE and evaluation tasks).

The engine changes where work runs, never the results.
"""
