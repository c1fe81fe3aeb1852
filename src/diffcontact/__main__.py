"""``python -m diffcontact``: the same as the ``diffcontact`` command."""

import sys

from diffcontact.cli import main

sys.exit(main())
