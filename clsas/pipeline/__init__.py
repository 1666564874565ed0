"""The pipeline floor: :func:`clsas.reconstruct` (one checked request through named stages) and its
tiles (out of core, on a Dask cluster)."""
