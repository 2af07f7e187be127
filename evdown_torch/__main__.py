"""``python -m evdown_torch`` runs the ``evdown`` command line."""

import sys

from evdown_torch.cli import main

sys.exit(main())
