"""A sweep of RL runs over the GPUs of one machine, one call at a time: what a lent machine that
keeps nothing between sessions and stops every command after 10 minutes needs.

A spec (TOML) names, per GPU, the probes to run first (scripts of this repository with their
arguments, run one after the other on that GPU, on the first call only: ``--probes``) and the
runs to train there (each a ``bench/rl_seeds.py`` process with its seeds, side by side on that
GPU). Every run gets the call's budget (``call_seconds - margin_seconds``, less what its GPU's
probes took) and is resumed by the next call from its checkpoint; a run already done returns at
once. Every process runs in a process group of its own; one still running ``PACK_SECONDS`` before
the call's end is killed with its children, so the archives are always written. The run folders are ``<work>/<task>/<run name>/s<seed>`` (``--work`` runs/rl: the
``"out"`` that ``bench/results/rl/`` records), the records copied to ``<work>/_results/<task>/...``
(the layout of ``bench/results/rl/``) at the call's end, a killed run's evaluations so far
included, each agent exported to ``<work>/_export/<task>/...``.
``--pack DIR`` then writes ``results.tar.xz`` (records), ``logs.tar.xz`` (each process's log, the
probes' output and ``<work>/_probes``, where a probe's own ``--out`` can point) and ``export.tar``
(the agents; over 15 MiB, in parts ``export.tar.part-NNN``: ``cat export.tar.part-* > export.tar``)
into DIR: what comes back from the machine. With ``--slim``, also ``slim.tar`` (parts likewise):
each unfinished run's slim copy (``gnwarp.rl.slim``; ~20 MB a 1M-step swimmer6 run), which a
later machine's call takes up with ``--restore slim.tar`` (its runs go on, their replay buffers
rebuilt first). One call brings back at most 64 MiB (~3 runs at 1M): ``--slim-only GLOB`` then
runs nothing and packs only the matching runs' copies, one short call for each share of the runs.

    PYTHONPATH=. python3 bench/rl_sweep.py SPEC.toml --call-seconds 590 --probes --mps --pack "$OUT"
    PYTHONPATH=. python3 bench/rl_sweep.py SPEC.toml --dry-run     # the commands, nothing run
    PYTHONPATH=. python3 bench/rl_sweep.py SPEC.toml --slim-only 'swimmer6/*/s2[0-2]' --pack "$OUT"

A spec::

    margin_seconds = 75            # of each call, left for starting, stopping and packing

    [[gpu]]
    index = 0
    runs = [{agent = "svg1", task = "cheetah-run", seeds = "1", env_steps = 500000}]

    [[gpu]]
    index = 3
    probes = [["bench/rl_loop.py", "--task", "swimmer6"]]
    probe_seconds = 240
    runs = [{agent = "svg1", task = "swimmer6", seeds = "0-1", env_steps = 1000000,
             set = ["act_ahead=true"]}]

A GPU's ``probe_seconds`` caps its probes (together, from the call's start): one still running
then is killed with its children and the runs start.
A run's keys: ``agent``, ``task``, ``seeds`` (``"0-5"``, ``"0,2"``), and optionally ``env_steps``,
``preset``, ``networks``, ``threads`` (CPU threads a seed, default 1), ``set`` (``RLConfig``
keys as ``KEY=VALUE``), ``quick`` (``bench/rl_seeds.py --quick``: CPU-sized). ``index`` is a
GPU's index (``CUDA_VISIBLE_DEVICES``) or ``"cpu"`` (no GPU visible). Each run's ``RLConfig`` and
task are checked before anything starts, and two runs training one seed (the task however spelt)
are refused.
"""
from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import subprocess
import sys
import tarfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from bench.rl_seeds import COPIED, file_seed, run_name, seed_config, seeds_of  # noqa: E402
from gnwarp.rl.config import RLConfig  # noqa: E402
from gnwarp.rl.run import check_task  # noqa: E402
from gnwarp.rl.run_log import CHECKPOINT  # noqa: E402
from gnwarp.validation import ConfigError, read_config_file  # noqa: E402

__all__ = ["read_spec", "commands", "main", "collect", "pack", "start_mps"]

RUN_KEYS = {"agent", "task", "seeds", "env_steps", "preset", "networks", "threads", "set", "quick"}
GPU_KEYS = {"index", "probes", "probe_seconds", "runs"}
SPEC_KEYS = {"margin_seconds", "gpu"}
PACK_SECONDS = 25   # of each call, kept for packing: a process still running then is killed


def _fail(where: str, why: str):
    raise ConfigError(where, why)


def read_spec(path) -> dict:
    """The spec at ``path``, checked (``ConfigError`` naming the key and what is wrong)."""
    d = read_config_file(path, "sweep keys")
    for k in set(d) - SPEC_KEYS:
        _fail(k, f"unknown sweep key (known: {', '.join(sorted(SPEC_KEYS))})")
    margin = d.get("margin_seconds", 75)
    if isinstance(margin, bool) or not isinstance(margin, (int, float)) or not margin >= 0 or margin == float("inf"):
        _fail("margin_seconds", f"finite seconds >= 0, got {margin!r}")
    gpus = d.get("gpu")
    if not isinstance(gpus, list) or not gpus:
        _fail("gpu", "one [[gpu]] table or more, each with its index and runs")
    seen, names = set(), set()
    for i, g in enumerate(gpus):
        where = f"gpu[{i}]"
        if not isinstance(g, dict):
            _fail(where, f"a table, got {type(g).__name__}")
        for k in set(g) - GPU_KEYS:
            _fail(f"{where}.{k}", f"unknown key (known: {', '.join(sorted(GPU_KEYS))})")
        idx = g.get("index")
        if not (idx == "cpu" or (isinstance(idx, int) and not isinstance(idx, bool) and idx >= 0)):
            _fail(f"{where}.index", f"a GPU index >= 0 or \"cpu\", got {idx!r}")
        if idx in seen:
            _fail(f"{where}.index", f"GPU {idx} appears twice: put its runs in one [[gpu]] table")
        seen.add(idx)
        probes = g.setdefault("probes", [])
        if not isinstance(probes, list) or not all(isinstance(p, list) and p and all(isinstance(a, str) for a in p)
                                                   for p in probes):
            _fail(f"{where}.probes", "a list of commands, each a list of strings: a script of this repository "
                                     "and its arguments")
        for p in probes:
            if not (ROOT / p[0]).is_file():
                _fail(f"{where}.probes", f"no script {p[0]!r} in this repository")
        cap = g.get("probe_seconds")
        if cap is not None and (isinstance(cap, bool) or not isinstance(cap, (int, float)) or not 0 < cap < float("inf")):
            _fail(f"{where}.probe_seconds", f"finite seconds > 0, got {cap!r}")
        runs = g.setdefault("runs", [])
        if not isinstance(runs, list) or not all(isinstance(r, dict) for r in runs):
            _fail(f"{where}.runs", "a list of tables")
        for j, r in enumerate(runs):
            rw = f"{where}.runs[{j}]"
            for k in set(r) - RUN_KEYS:
                _fail(f"{rw}.{k}", f"unknown key (known: {', '.join(sorted(RUN_KEYS))})")
            for k in ("agent", "task", "seeds"):
                if not isinstance(r.get(k), str) or not r[k]:
                    _fail(f"{rw}.{k}", f"required, a string; got {r.get(k)!r}")
            try:
                seeds = seeds_of(r["seeds"])
            except ValueError as e:
                _fail(f"{rw}.seeds", str(e))
            if "env_steps" in r and (isinstance(r["env_steps"], bool) or not isinstance(r["env_steps"], int)
                                     or r["env_steps"] < 1):
                _fail(f"{rw}.env_steps", f"an integer >= 1, got {r['env_steps']!r}")
            sets = r.setdefault("set", [])
            if not isinstance(sets, list) or not all(isinstance(s, str) and "=" in s for s in sets):
                _fail(f"{rw}.set", "a list of KEY=VALUE strings")
            if not isinstance(r.get("quick", False), bool):
                _fail(f"{rw}.quick", f"true or false, got {r['quick']!r}")
            threads = r.get("threads", 1)
            if isinstance(threads, bool) or not isinstance(threads, int) or threads < 1:
                _fail(f"{rw}.threads", f"an integer >= 1, got {threads!r}")
            base = effective_run(r)
            try:
                name = run_name(base)
                cfg = RLConfig.from_dict({**base, "seed": seeds[0], "out": "unused"})
                task = check_task(cfg).name
            except ConfigError as e:   # (a ValueError too: first)
                _fail(f"{rw}.{e.path}", e.reason)
            except ValueError as e:
                _fail(f"{rw}.set", str(e))
            for s in seeds:   # two processes must never train one run, nor one seed twice under two names
                key = (task, name, s)
                if key in names:
                    _fail(f"{rw}.seeds", f"{task} {name} seed {s} is already in the sweep")
                names.add(key)
    return {"margin_seconds": float(margin), "gpu": gpus}


def effective_run(r: dict) -> dict:
    """The run's settings as ``bench/rl_seeds.py`` builds them (``seed_config``)."""
    return seed_config(bool(r.get("quick")), r["task"], r["agent"], r.get("preset", "spinningup"),
                       r.get("networks", "mlp"), r.get("threads", 1), r.get("env_steps"), r["set"])


def commands(spec: dict, work, budget: float) -> list[dict]:
    """Per GPU: its environment, its probes' and runs' command lines (``budget`` seconds a run,
    before the probes' time is taken off)."""
    work = Path(work)
    out = []
    for g in spec["gpu"]:
        env = {"CUDA_VISIBLE_DEVICES": "" if g["index"] == "cpu" else str(g["index"])}
        probes = [[sys.executable, str(ROOT / p[0]), *p[1:]] for p in g["probes"]]
        runs = []
        for r in g["runs"]:
            cmd = [sys.executable, str(ROOT / "bench" / "rl_seeds.py"), "--agent", r["agent"], "--task", r["task"],
                   "--seeds", r["seeds"], "--threads", str(r.get("threads", 1)),
                   "--runs", str(work / r["task"]), "--results", str(work / "_results"),
                   "--export", str(work / "_export" / r["task"]), "--budget-seconds", f"{budget:.0f}"]
            for k in ("preset", "networks"):
                if k in r:
                    cmd += [f"--{k}", r[k]]
            if "env_steps" in r:
                cmd += ["--env-steps", str(r["env_steps"])]
            for s in r["set"]:
                cmd += ["--set", s]
            if r.get("quick"):
                cmd += ["--quick"]
            base = effective_run(r)
            log = f"{base['task']}-{run_name(base)}-s{r['seeds'].replace(',', '_')}.log"
            runs.append({"cmd": cmd, "log": log})
        out.append({"index": g["index"], "env": env, "probes": probes, "probe_seconds": g.get("probe_seconds"),
                    "runs": runs})
    return out


def _wait(p: subprocess.Popen, deadline: float, why: str = "the call's deadline"):
    """``p``'s exit code, or, past ``deadline`` (monotonic), its whole process group killed (``why``:
    what the deadline is, for the report)."""
    try:
        return p.wait(timeout=max(0.0, deadline - time.monotonic()))
    except subprocess.TimeoutExpired:
        try:
            os.killpg(p.pid, signal.SIGKILL)   # its own children too (a probe's measuring process, the seeds)
        except ProcessLookupError:
            pass
        p.wait()
        return f"killed at {why}"


def _gpu_job(job: dict, work: Path, started: float, budget: float, deadline: float, probes: bool,
             lines: list) -> None:
    """One GPU's share: its probes (when asked), then its runs side by side with what is left;
    every process in a process group of its own, killed with its children at ``deadline``."""
    env = dict(os.environ, **job["env"], PYTHONUNBUFFERED="1")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    logs = work / "_logs"
    gpu = f"GPU {job['index']}"
    if probes:
        stop, why = min(deadline, started + budget), "the call's deadline"   # the probes' end, or their cap
        if job.get("probe_seconds") is not None and started + job["probe_seconds"] < stop:
            stop, why = started + job["probe_seconds"], f"the GPU's probe_seconds ({job['probe_seconds']:g} s)"
        for k, cmd in enumerate(job["probes"]):
            name = f"probe-{job['index']}-{k}-{Path(cmd[1]).stem}.txt"
            with open(logs / name, "w") as f:
                p = subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT,
                                     start_new_session=True)
                rc = _wait(p, stop, why)
            lines.append((rc != 0, f"{gpu}: probe {shlex.join(cmd[1:])}: exit {rc}, "
                                   f"{time.monotonic() - started:.0f} s into the call"))
    left = budget - (time.monotonic() - started)
    if left < 30 and job["runs"]:
        lines.append((False, f"{gpu}: {left:.0f} s left after the probes: its runs wait for the next call"))
        return
    procs = []
    for r in job["runs"]:
        cmd = list(r["cmd"])
        cmd[cmd.index("--budget-seconds") + 1] = f"{left:.0f}"
        f = open(logs / r["log"], "a")
        start = f.tell()
        procs.append((subprocess.Popen(cmd, env=env, stdout=f, stderr=subprocess.STDOUT, cwd=ROOT,
                                       start_new_session=True), f, r["log"], start))
    for p, f, log, start in procs:
        rc = _wait(p, deadline)
        f.close()
        with open(logs / log, errors="replace") as g:   # this call's lines only: the log is appended
            g.seek(start)
            mine = [ln.rstrip("\n") for ln in g]
        tail = [ln for ln in mine if ln.startswith("seed ")][-8:] if rc == 0 else mine[-8:]
        lines.append((rc != 0, f"{gpu}: {log[:-4]}: exit {rc}" + "".join(f"\n  {t}" for t in tail)))


def _guarded(job: dict, *args) -> None:
    """``_gpu_job``, an error in it reported among the lines (the other GPUs go on)."""
    lines = args[-1]
    try:
        _gpu_job(job, *args)
    except Exception as e:   # reported, and the call still packs what exists
        lines.append((True, f"GPU {job['index']}: failed: {type(e).__name__}: {e}"))


def start_mps() -> str:
    """Start the CUDA MPS control daemon (``nvidia-cuda-mps-control -d``) unless one runs; what
    happened, as a line."""
    import shutil
    exe = shutil.which("nvidia-cuda-mps-control")
    if exe is None:
        return "MPS: nvidia-cuda-mps-control not found; processes sharing a GPU take turns on it"
    if subprocess.run(["pgrep", "-x", "nvidia-cuda-mps"], capture_output=True).returncode == 0:
        return "MPS: the daemon runs already"
    rc = subprocess.run([exe, "-d"], capture_output=True, text=True)
    return "MPS: daemon started" if rc.returncode == 0 else f"MPS: could not start the daemon ({rc.stderr.strip()})"


def _run_folders(work: Path, holding: str) -> list[Path]:
    """The run folders ``<work>/<task>/<name>/s<seed>`` (not the sweep's own ``_*`` folders) that
    hold a file matching ``holding``, each once."""
    found = {f.parent for f in work.glob(f"*/*/s*/{holding}") if not f.relative_to(work).parts[0].startswith("_")}
    return sorted(found)


def collect(work) -> int:
    """Copy every run folder's records (``COPIED``) to ``<work>/_results`` as ``bench/rl_seeds.py``
    files them when a seed's process ends (``file_seed``): also for a process killed at the
    deadline, whose evaluations up to then are kept. The number of seeds copied."""
    import json
    work, n = Path(work), 0
    for seed_dir in _run_folders(work, "records.jsonl"):
        rel = seed_dir.relative_to(work)
        try:   # under the task its config names, as rl_seeds files it (a quick run's differs from the spec's)
            task = json.loads((seed_dir / "config.json").read_text())["task"]
        except (OSError, ValueError, KeyError, TypeError):
            task = rel.parts[0]
        files = {f: (seed_dir / f).read_bytes() for f in COPIED if (seed_dir / f).is_file()}
        file_seed(work / "_results", task, rel.parts[1], rel.parts[2][1:], files)
        n += 1
    return n


PART_BYTES = 15 * 2**20   # a file the lent machine sends back holds at most 16 MiB


def split_file(path: Path, part_bytes: int = PART_BYTES) -> list[Path]:
    """``path`` itself where it fits in ``part_bytes``, else its parts ``<name>.part-000``,
    ``.part-001``, ... (each written to a temporary name, then renamed; ``path`` removed):
    ``cat <name>.part-* > <name>`` joins them."""
    size = path.stat().st_size
    if size <= part_bytes:
        return [path]
    parts = []
    with open(path, "rb") as f:
        for i in range(-(-size // part_bytes)):
            part = path.with_name(f"{path.name}.part-{i:03d}")
            tmp = part.with_name(part.name + ".tmp")
            tmp.write_bytes(f.read(part_bytes))
            tmp.replace(part)
            parts.append(part)
    path.unlink()
    return parts


def make_slim(work, only: str = "*") -> list[str]:
    """Each unfinished run's slim copy (``gnwarp.rl.slim.slim_run``: no replay buffer's
    transitions) into ``<work>/_slim/<task>/<name>/s<seed>`` (an earlier call's copies replaced;
    ``only``: the runs whose ``<task>/<name>/s<seed>`` matches this glob, ``fnmatch``'s);
    a run still slim (restored, not yet checkpointed since) copied as it is; a finished run has
    none (its agent is exported). A run that fails is reported, the others go on. The lines."""
    import fnmatch
    import json
    import shutil

    from gnwarp.rl.run_log import load_checkpoint
    from gnwarp.rl.slim import slim_run
    work = Path(work)
    shutil.rmtree(work / "_slim", ignore_errors=True)
    lines = []
    for run in _run_folders(work, CHECKPOINT):
        rel = run.relative_to(work)
        if not fnmatch.fnmatchcase(rel.as_posix(), only):
            continue
        try:
            ck = load_checkpoint(run / CHECKPOINT)
            if ck["agent"]["env_steps"] >= json.loads((run / "config.json").read_text())["env_steps"]:
                continue   # finished: nothing to go on with
            if ck["buffer"].get("actions_only"):
                shutil.copytree(run, work / "_slim" / rel)
            else:
                slim_run(run, work / "_slim" / rel)
            lines.append(f"slim copy of {rel} ({ck['agent']['env_steps']} env steps)")
        except Exception as e:   # noqa: BLE001 - one run's failure must not cost the call's archives
            lines.append(f"no slim copy of {rel}: {type(e).__name__}: {e}")
    return lines


def restore(work, source) -> list[str]:
    """Put the slim copies of ``source`` (a ``slim.tar`` that ``pack(..., slim=True)`` wrote, its
    parts ``slim.tar.part-NNN`` beside the name, or a folder holding either) into ``work`` as run
    folders, where no run folder holds a checkpoint yet: those runs resume from them (their
    buffers rebuilt). A run folder there without a checkpoint (a run started from scratch that
    wrote no checkpoint yet) is moved aside to ``_replaced/task/name/sN[.K]``, never deleted.
    Only plain files and folders under ``slim/`` are read. The runs put, as ``task/name/sN``."""
    import io
    import shutil
    work, source = Path(work), Path(source)
    if source.is_dir():
        source = source / "slim.tar"
    parts = sorted(source.parent.glob(source.name + ".part-*"))
    if source.is_file():
        data = source.read_bytes()
    elif parts:
        data = b"".join(p.read_bytes() for p in parts)
    else:
        raise FileNotFoundError(f"no slim copies at {source} (nor its parts {source.name}.part-NNN)")
    put = []
    with tarfile.open(fileobj=io.BytesIO(data)) as t:
        members = t.getmembers()
        for m in members:   # slim/, slim/<task>/<name>/s<seed>/ and the run folders' own files only
            rel = Path(m.name)
            ok = (not rel.is_absolute() and ".." not in rel.parts and rel.parts and rel.parts[0] == "slim"
                  and all(not part.startswith(("_", ".")) for part in rel.parts[1:3])
                  and (len(rel.parts) < 4 or re.fullmatch(r"s\d+", rel.parts[3]))
                  and ((m.isdir() and len(rel.parts) <= 4) or (m.isfile() and len(rel.parts) == 5)))
            if not ok:
                raise ValueError(f"{source}: {m.name!r} is not a run folder's plain file or a folder under "
                                 "slim/<task>/<run>/s<seed>: refused")
        runs = sorted({Path(*Path(m.name).parts[1:4]) for m in members if len(Path(m.name).parts) == 5})
        for run in runs:
            dest = work / run
            if (dest / CHECKPOINT).exists():
                continue
            if dest.exists():
                aside = work / "_replaced" / run
                k = 0
                while aside.exists():
                    k += 1
                    aside = work / "_replaced" / run.parent / f"{run.name}.{k}"
                aside.parent.mkdir(parents=True, exist_ok=True)
                shutil.move(str(dest), str(aside))
            for m in members:
                rel = Path(*Path(m.name).parts[1:])
                if m.isfile() and rel.parts[:3] == run.parts:
                    (work / rel).parent.mkdir(parents=True, exist_ok=True)
                    (work / rel).write_bytes(t.extractfile(m).read())
            put.append(str(run))
    return put


def pack(work, dest, part_bytes: int = PART_BYTES, slim: bool = False, only: str | None = None) -> list[Path]:
    """``results.tar.xz``, ``logs.tar.xz`` and ``export.tar`` of ``work`` in ``dest`` (each
    written to a temporary name, then renamed); an ``export.tar`` over ``part_bytes`` is split
    into ``export.tar.part-NNN`` files (``split_file``), so the agents come back from a machine
    that sends no file over 16 MiB. ``slim``: also ``slim.tar`` of the unfinished runs' slim
    copies (``make_slim``: all a run needs to go on elsewhere, ``restore``), split the same way.
    ``only`` (a glob of ``<task>/<name>/s<seed>``): ``slim.tar`` of those runs alone, nothing else
    (so that several short calls bring back more copies than one call's 64 MiB holds)."""
    work, dest = Path(work), Path(dest)
    dest.mkdir(parents=True, exist_ok=True)
    made = []
    archives = [] if only is not None else [
        ("results.tar.xz", "w:xz", "_results"), ("logs.tar.xz", "w:xz", "_logs"), ("export.tar", "w", "_export")]
    if slim or only is not None:
        archives.append(("slim.tar", "w", "_slim"))
    for name in ("export.tar", "slim.tar"):   # a previous call's parts of an archive written again
        if any(a[0] == name for a in archives):   # would join into a corrupt tar
            for old in dest.glob(f"{name}.part-*"):
                old.unlink()
    if slim or only is not None:
        for line in make_slim(work, "*" if only is None else only):   # after the records and logs: a copy may fail
            print(line)
    for name, mode, part in archives:
        tmp = dest / (name + ".tmp")
        with tarfile.open(tmp, mode) as t:
            if (work / part).exists():
                t.add(work / part, arcname=part.lstrip("_"))
            if name == "logs.tar.xz":   # the probes' own output folder, each seed's log in its run folder
                if (work / "_probes").exists():
                    t.add(work / "_probes", arcname="probes")
                for run in _run_folders(work, "*.log"):
                    for log in sorted(run.glob("*.log")):
                        t.add(log, arcname=str(Path("runs") / log.relative_to(work)))
        tmp.replace(dest / name)
        made += split_file(dest / name, part_bytes) if name in ("export.tar", "slim.tar") else [dest / name]
    return made


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("spec", help="the sweep's TOML file")
    ap.add_argument("--call-seconds", type=float, default=590.0, help="this call's length (the runs stop before)")
    ap.add_argument("--work", default=str(Path("runs") / "rl"), help="folder of the runs (and of _results, _export, _logs)")
    ap.add_argument("--probes", action="store_true", help="run each GPU's probes first (the first call)")
    ap.add_argument("--pack", default=None, metavar="DIR", help="afterwards, the archives of what came out in DIR")
    ap.add_argument("--mps", action="store_true",
                    help="start the CUDA MPS daemon first where it is not running (processes sharing a GPU then "
                         "run side by side instead of taking turns)")
    ap.add_argument("--slim", action="store_true",
                    help="also pack the unfinished runs' slim copies (slim.tar: what a run needs to go on on another "
                         "machine, its replay buffer rebuilt there)")
    ap.add_argument("--restore", default=None, metavar="PATH",
                    help="first, the slim copies of PATH (a slim.tar, its parts, or their folder) as run folders where "
                         "none holds a checkpoint: those runs go on from them")
    ap.add_argument("--slim-only", default=None, metavar="GLOB",
                    help="run nothing: into --pack's DIR only slim.tar of the unfinished runs whose "
                         "<task>/<name>/s<seed> matches GLOB (e.g. 'swimmer6/*/s2[0-2]'), after the calls that "
                         "trained them: each such call brings back the copies that fit its 64 MiB")
    ap.add_argument("--dry-run", action="store_true", help="print the commands and stop")
    a = ap.parse_args(argv)
    try:
        spec = read_spec(a.spec)
    except (ConfigError, FileNotFoundError) as e:
        print(f"rl_sweep: {e}", file=sys.stderr)
        return 2
    budget = a.call_seconds - spec["margin_seconds"]
    if not budget >= 30 or budget == float("inf"):   # (NaN and Inf fail too)
        print(f"rl_sweep: --call-seconds {a.call_seconds:g} leaves {budget:.0f} s after the margin of "
              f"{spec['margin_seconds']:g} s: a call needs a finite 30 s or more to train", file=sys.stderr)
        return 2
    jobs = commands(spec, a.work, budget)
    if a.dry_run:
        for j in jobs:
            pre = " ".join(f"{k}={v}" for k, v in j["env"].items())
            for c in (j["probes"] if a.probes else []) + [r["cmd"] for r in j["runs"]]:
                print(f"GPU {j['index']}: {pre + ' ' if pre else ''}{shlex.join(c)}")
        return 0
    # the processes run in the repository's root, where a relative --work lies
    work = Path(a.work) if Path(a.work).is_absolute() else ROOT / a.work
    (work / "_logs").mkdir(parents=True, exist_ok=True)
    if a.restore:
        try:
            put = restore(work, a.restore)
        except (OSError, ValueError, tarfile.TarError) as e:
            print(f"rl_sweep: --restore: {e}", file=sys.stderr)
            return 2
        print(f"restored {len(put)} runs from their slim copies: {', '.join(put) or 'none'}")
    if a.slim_only is not None:
        if not a.pack:
            print("rl_sweep: --slim-only needs --pack DIR", file=sys.stderr)
            return 2
        made = pack(work, a.pack, only=a.slim_only)
        for p in made:
            print(f"wrote {p} ({p.stat().st_size / 1e6:.1f} MB)")
        if not _run_folders(work / "_slim", CHECKPOINT):
            print(f"rl_sweep: --slim-only {a.slim_only!r}: no unfinished run under {work} matches (a glob matches "
                  "the whole <task>/<name>/s<seed>)", file=sys.stderr)
            return 1
        return 0
    if a.mps:
        print(start_mps())
    started, lines = time.monotonic(), []
    deadline = started + a.call_seconds - PACK_SECONDS
    threads = [threading.Thread(target=_guarded, args=(j, work, started, budget, deadline, a.probes, lines))
               for j in jobs]
    try:
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    finally:
        print("\n".join(text for _, text in sorted(lines, key=lambda x: x[1])))
        print(f"call: {time.monotonic() - started:.0f} s")
        print(f"records of {collect(work)} seeds under {work / '_results'}")
        if a.pack:
            for p in pack(work, a.pack, slim=a.slim):
                print(f"wrote {p} ({p.stat().st_size / 1e6:.1f} MB)")
    failed = sum(bad for bad, _ in lines)
    if failed:
        print(f"rl_sweep: {failed} of the call's processes failed (above)", file=sys.stderr)
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
