"""`python -m warpsense` (also what torchrun launches: torchrun --nproc_per_node N -m warpsense train ...)."""

import sys

from warpsense.cli import main

sys.exit(main())
