"""``python -m jaxrobo.sweep``: the same as ``jaxrobo sweep``."""
import sys

from jaxrobo.sweep.cli import main

sys.exit(main())
