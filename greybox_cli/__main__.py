"""``python -m greybox_cli``: the command line, Ctrl-C safe from the first instant."""

import sys

from . import main

sys.exit(main())
