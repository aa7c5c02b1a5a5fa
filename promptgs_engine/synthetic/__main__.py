"""``python -m promptgs_engine.synthetic dataset mountain ...`` (same as ``promptgs dataset``)."""

import sys

from .cli import main

sys.exit(main())
