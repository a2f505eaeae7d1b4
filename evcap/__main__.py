import sys

from evcap.cli import main

sys.exit(main())
