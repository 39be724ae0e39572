"""``python -m gnwarp``: the ``gnwarp`` command (``gnwarp.cli``), as ``python -m gnwarp.cli``."""
import sys

from gnwarp.cli import main

sys.exit(main())
