import sys

from evcap.app.cli import main

sys.exit(main())
