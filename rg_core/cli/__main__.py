"""`python -m rg_core.cli`: the `rg` command."""
import sys

from . import main

sys.exit(main())
