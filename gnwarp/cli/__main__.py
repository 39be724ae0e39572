"""``python -m gnwarp.cli``: the ``gnwarp`` command."""
import sys

from gnwarp.cli import main

sys.exit(main())
