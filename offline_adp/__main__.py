import sys

from offline_adp.cli import main

sys.exit(main())
