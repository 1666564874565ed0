"""Synthetic data: the forward model (:func:`clsas.simulate`), scene files and the demo scenes, scans
that look measured, and seeded scene families for held-out evaluation."""
