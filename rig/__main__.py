"""`python -m rig` is the `hdrig` command."""

import sys

from rig.cli import main

sys.exit(main())
