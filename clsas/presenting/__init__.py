"""Presenting results: export to other programs, a dataset's inspection, image quality."""
