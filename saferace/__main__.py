"""``python -m saferace`` runs the command line."""

import sys

from saferace.cli import main

sys.exit(main())
