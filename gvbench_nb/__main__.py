import sys

from gvbench_nb.cli import main

sys.exit(main())
