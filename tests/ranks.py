"""Start several ranks of a command on the CPU as ``torchrun`` starts them (its environment
variables, gloo), for the tests of work spread over ranks."""
import os
import socket
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_ranks(args, world=2, timeout=30, env=None, wait=240):
    """Start ``world`` processes of ``args`` with torchrun's variables (``timeout``: the group's, in
    seconds); (returncodes, outputs). A rank still running after ``wait`` seconds fails the test
    (``subprocess.TimeoutExpired``): a hang, not a slow run."""
    port = free_port()
    procs = []
    for r in range(world):
        e = dict(os.environ, MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), WORLD_SIZE=str(world), RANK=str(r),
                 LOCAL_RANK=str(r), LOCAL_WORLD_SIZE=str(world), GNWARP_DIST_TIMEOUT=str(timeout),
                 OMP_NUM_THREADS="1", **(env or {}))
        # the checkout first, installed or not (the workers import gnwarp and the test helpers)
        e["PYTHONPATH"] = os.pathsep.join([str(ROOT), str(ROOT / "tests"), os.environ.get("PYTHONPATH", "")])
        procs.append(subprocess.Popen([sys.executable, *args], env=e, stdout=subprocess.PIPE,
                                      stderr=subprocess.STDOUT, text=True))
    try:
        outs = [p.communicate(timeout=wait)[0] for p in procs]
    finally:
        for p in procs:   # none left behind when one hangs
            p.kill()
    return [p.returncode for p in procs], outs
