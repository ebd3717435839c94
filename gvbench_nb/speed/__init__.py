"""Speed: the bench against our per-pair loop (``python -m gvbench_nb.speed``). Nothing in the
package imports it; the peer benchmark against vismatch is ``benchmarks/peer_vismatch.py``."""
