"""Verifiers beyond the protocol's RANSAC, compared after a run (``studies/alternative_verifiers.py``): the
Doppelgangers classifier and SUE. The protocol's own verification is ``protocol/ransac.py``."""
