"""Reporting: executing notebooks (a kernel pool), the HTML report, and ``compare`` across runs."""
