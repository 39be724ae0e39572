"""Helpers shared by the benchmark scripts."""
from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path


def device_name() -> str:
    """The GPU's name, or the CPU's core count where there is no GPU."""
    try:
        import torch
        if torch.cuda.is_available():
            return torch.cuda.get_device_name(0)
    except Exception:  # noqa: BLE001 - no usable torch CUDA means a CPU run
        pass
    return f"CPU ({os.cpu_count()} cores, {platform.processor() or platform.machine()})"


def run_side_by_side(commands: dict[str, list[str]], log_dir: Path, threads: int = 2,
                     deadline: float | None = None) -> dict[str, int]:
    """Start every command at once (one process each, sharing the device), wait for all; each
    one's output goes to ``log_dir/<name>.log``. Commands still running ``deadline`` seconds after
    the start are killed (exit code -9 in the result). Returns the exit codes."""
    import time
    end = None if deadline is None else time.monotonic() + deadline
    procs = {}
    for name, cmd in commands.items():
        log = open(Path(log_dir) / f"{name}.log", "w")
        procs[name] = (subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT,
                                        env={**os.environ, "OMP_NUM_THREADS": str(threads)}), log)
    codes = {}
    for name, (p, log) in procs.items():
        try:
            codes[name] = p.wait(None if end is None else max(0.0, end - time.monotonic()))
        except subprocess.TimeoutExpired:
            p.kill()
            codes[name] = p.wait()
        log.close()
    return codes


def median_ms(fn, device, reps: int, warmup: int) -> float:
    """Median milliseconds of ``fn()`` over ``reps`` calls after ``warmup``: CUDA events around
    each call on a CUDA ``device`` (a torch.device), perf_counter elsewhere."""
    import statistics
    import time

    import torch
    for _ in range(warmup):
        fn()
    ts = []
    if device.type == "cuda":
        torch.cuda.synchronize()
        for _ in range(reps):
            a, b = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            a.record()
            fn()
            b.record()
            b.synchronize()
            ts.append(a.elapsed_time(b))
    else:
        for _ in range(reps):
            t0 = time.perf_counter()
            fn()
            ts.append((time.perf_counter() - t0) * 1e3)
    return statistics.median(ts)
