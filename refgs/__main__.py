"""``python -m refgs ...`` = the ``refgs`` command (refgs.cli.main)."""
import sys

from .cli import main

sys.exit(main())
