"""Speed: the benchmark against our per-pair loop and the peer, and scale-out runs."""
