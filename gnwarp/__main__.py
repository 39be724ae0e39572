"""``python -m gnwarp``: the command line (``gnwarp.cli``)."""
import sys

from gnwarp.cli import main

sys.exit(main())
