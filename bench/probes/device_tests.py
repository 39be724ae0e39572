"""Run tests of this repository on the lent GPU machine as a sweep's probe
(``bench/rl_sweep.py``: a probe is a script of the repository, run on its GPU before the runs).

The arguments are pytest's; the exit code is pytest's (non-zero: the sweep reports the probe as
failed with its log). The tests that need CUDA are skipped on a machine without it, so run the
ones that are not: ``-k cuda`` or a test's id.

    python bench/probes/device_tests.py -q tests/test_rl_graphed.py -k cuda
"""
from __future__ import annotations

import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def main(argv=None) -> int:
    import pytest
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    return int(pytest.main(list(sys.argv[1:] if argv is None else argv)))


if __name__ == "__main__":
    sys.exit(main())
