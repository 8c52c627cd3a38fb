import sys

from afmctl.cli import main

sys.exit(main())
