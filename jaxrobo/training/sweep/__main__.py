"""``python -m jaxrobo.training.sweep``: the same as ``jaxrobo sweep``."""
import sys

from jaxrobo.training.sweep.cli import main

sys.exit(main())
