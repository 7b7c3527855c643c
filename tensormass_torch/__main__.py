"""``python -m tensormass_torch ...`` runs the ``tensormass`` command line."""
import sys

from .app.cli import main

sys.exit(main())
