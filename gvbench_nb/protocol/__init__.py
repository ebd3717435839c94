"""The benchmark protocol: what the paper (the authors' hloc fork) and the GV-Bench repository
compute. It imports only its libraries and itself; ``runner`` stands around it."""
