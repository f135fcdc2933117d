"""``python -m offline_adp.cli`` (the same as ``python -m offline_adp``)."""

import sys

from offline_adp.cli import main

sys.exit(main())
