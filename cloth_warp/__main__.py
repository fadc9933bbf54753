"""`python -m cloth_warp` is the cloth-warp command."""

import sys

from .cli import main

sys.exit(main())
