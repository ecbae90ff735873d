"""`python -m tissue` is the `tissue` command."""

import sys

from .cli import main

sys.exit(main())
