"""Reporting: figures, the analysis notebooks and the HTML report."""
