"""``python -m greybox``: the `greybox` command."""

import sys

from greybox.cli import main

sys.exit(main())
