"""``python -m gvbench_nb.speed``: the bench (``bench.py``)."""

import sys

from gvbench_nb.speed import bench

sys.exit(bench.main())
