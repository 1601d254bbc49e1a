"""Reproducible numerical studies behind `python -m studies`."""
