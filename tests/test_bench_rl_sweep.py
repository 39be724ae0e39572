"""bench/rl_sweep.py: a sweep spec checked, its command lines, and one CPU-sized call packed."""
import json
import re
import tarfile

import numpy as np
import pytest

from bench import rl_sweep
from gnwarp.validation import ConfigError

SPEC = '''
margin_seconds = 60
[[gpu]]
index = 0
runs = [{agent = "svg1", task = "cheetah-run", seeds = "1-2", env_steps = 500000}]
[[gpu]]
index = 3
probes = [["bench/rl_loop.py", "--task", "swimmer6"]]
runs = [{agent = "svg1", task = "swimmer6", seeds = "0", set = ["act_ahead=true"]},
        {agent = "svg0", task = "swimmer6", seeds = "0", networks = "gn"}]
'''


# the quick run's name: its own sizes are settings off the defaults (bench/rl_seeds.run_name)
QUICK_RUN = "svg0-spinningup-mlp-batch_size16-hidden16-start_steps40-update_after40"


def write(tmp_path, text, name="spec.toml"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_dry_run_prints_each_gpus_commands_with_the_calls_budget(tmp_path, capsys):
    assert rl_sweep.main([str(write(tmp_path, SPEC)), "--dry-run", "--probes", "--call-seconds", "500",
                          "--work", "w"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 4
    assert all(ln.startswith("GPU 0: CUDA_VISIBLE_DEVICES=0 ") for ln in lines[:1])
    assert lines[1].startswith("GPU 3: CUDA_VISIBLE_DEVICES=3 ") and "bench/rl_loop.py --task swimmer6" in lines[1]
    assert "--seeds 1-2" in lines[0] and "--env-steps 500000" in lines[0] and "--budget-seconds 440" in lines[0]
    assert "--runs w/cheetah-run" in lines[0] and "--results w/_results" in lines[0]
    assert "--set act_ahead=true" in lines[2] and "--networks gn" in lines[3] and "--env-steps" not in lines[3]
    capsys.readouterr()
    rl_sweep.main([str(write(tmp_path, SPEC)), "--dry-run", "--call-seconds", "500"])
    assert "rl_loop" not in capsys.readouterr().out     # probes only where asked


@pytest.mark.parametrize("text, where, why", [
    ("margin_seconds = 1\n", "gpu", "one [[gpu]] table"),
    ("colour = 1\n[[gpu]]\nindex = 0\n", "colour", "unknown sweep key"),
    ("[[gpu]]\nindex = -1\n", "gpu[0].index", "GPU index >= 0"),
    ("[[gpu]]\nindex = 0\n[[gpu]]\nindex = 0\n", "gpu[1].index", "appears twice"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6'}]\n", "gpu[0].runs[0].seeds", "required"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '1,1'}]\n", "gpu[0].runs[0].seeds",
     "distinct"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0', speed = 2}]\n",
     "gpu[0].runs[0].speed", "unknown key"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0', env_steps = 0}]\n",
     "gpu[0].runs[0].env_steps", "integer >= 1"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0-1'}]\n"
     "[[gpu]]\nindex = 1\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '1'}]\n", "gpu[1].runs[0].seeds",
     "already in the sweep"),
    ("[[gpu]]\nindex = 0\nprobes = [['bench/no_such_probe.py']]\n", "gpu[0].probes", "no script"),
    ("[[gpu]]\nindex = 0\nprobe_seconds = 0\n", "gpu[0].probe_seconds", "finite seconds > 0"),
    ("[[gpu]]\nindex = 0\nprobe_seconds = inf\n", "gpu[0].probe_seconds", "finite seconds > 0"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0', set = ['act_ahead=maybe']}]\n",
     "gpu[0].runs[0].set", "true or false"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0'}, "
     "{agent = 'svg1', task = 'dmc-swimmer-swimmer6', seeds = '0'}]\n", "gpu[0].runs[1].seeds", "already in the sweep"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'pendulum', seeds = '0', quick = true}, "
     "{agent = 'ddpg', task = 'cartpole', seeds = '0', quick = true}]\n", "gpu[0].runs[1].seeds", "already in the sweep"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'no-such-task', seeds = '0'}]\n",
     "gpu[0].runs[0].task", "no-such-task"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg9', task = 'swimmer6', seeds = '0'}]\n",
     "gpu[0].runs[0].agent", "svg9"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0', set = ['no_such_key=1']}]\n",
     "gpu[0].runs[0].no_such_key", "unknown RL run config keys"),
    ("[[gpu]]\nindex = 0\nruns = [{agent = 'svg1', task = 'swimmer6', seeds = '0', quick = 'false'}]\n",
     "gpu[0].runs[0].quick", "true or false"),
])
def test_bad_specs_name_the_key(tmp_path, capsys, text, where, why):
    p = write(tmp_path, text)
    with pytest.raises(ConfigError, match=re.escape(why)) as e:
        rl_sweep.read_spec(p)
    assert e.value.path == where
    assert rl_sweep.main([str(p), "--dry-run"]) == 2
    assert where in capsys.readouterr().err


def test_a_call_too_short_for_its_margin_is_refused(tmp_path, capsys):
    for seconds in ("80", "nan", "inf"):   # NaN killed every run at 0 s
        assert rl_sweep.main([str(write(tmp_path, SPEC)), "--call-seconds", seconds, "--dry-run"]) == 2
        assert "a call needs a finite 30 s or more to train" in capsys.readouterr().err
    with pytest.raises(ConfigError, match="finite seconds >= 0"):
        rl_sweep.read_spec(write(tmp_path, SPEC.replace("margin_seconds = 60", "margin_seconds = nan")))


def test_one_cpu_call_trains_copies_and_packs(tmp_path, capsys):
    """A CPU-sized run (``quick``) through the whole call: its records copied to _results and
    packed with its log and exported agent."""
    spec = write(tmp_path, '[[gpu]]\nindex = "cpu"\nruns = [{agent = "svg0", task = "pendulum-balance", '
                           'seeds = "0", quick = true}]\n')
    work, out = tmp_path / "work", tmp_path / "out"
    assert rl_sweep.main([str(spec), "--call-seconds", "300", "--work", str(work), "--pack", str(out)]) == 0
    text = capsys.readouterr().out
    assert f"GPU cpu: pendulum-balance-{QUICK_RUN}-s0: exit 0" in text and "seed 0: exit 0" in text
    assert '"stop": "done"' in text
    with tarfile.open(out / "results.tar.xz") as t:
        names = t.getnames()
        rec = t.extractfile(f"results/pendulum-balance/{QUICK_RUN}/s0/config.json")
        assert json.load(rec)["out"] == str(work / "pendulum-balance" / QUICK_RUN / "s0")
    assert f"results/pendulum-balance/{QUICK_RUN}/s0/records.jsonl" in names
    with tarfile.open(out / "logs.tar.xz") as t:
        assert f"logs/pendulum-balance-{QUICK_RUN}-s0.log" in t.getnames()
        assert f"runs/pendulum-balance/{QUICK_RUN}/s0/call.log" in t.getnames()
    with tarfile.open(out / "export.tar") as t:
        assert any(n.startswith(f"export/pendulum-balance/{QUICK_RUN}/s0/") for n in t.getnames())
    assert not list(out.glob("*.tmp"))


def test_an_export_over_the_part_size_comes_in_parts_that_join(tmp_path):
    """The agents' tar over ``part_bytes`` is split into parts that ``cat`` joins into the same
    tar; a previous call's stale part is removed first, a small export stays one file."""
    blob = np.random.default_rng(0).bytes(5000)
    (tmp_path / "work" / "_export" / "a" / "b" / "s0").mkdir(parents=True)
    (tmp_path / "work" / "_export" / "a" / "b" / "s0" / "agent.pt").write_bytes(blob)
    out = tmp_path / "out"
    out.mkdir()
    (out / "export.tar.part-007").write_bytes(b"stale")
    made = rl_sweep.pack(tmp_path / "work", out, part_bytes=2048)
    parts = sorted(out.glob("export.tar.part-*"))
    assert [p.name for p in parts] == [f"export.tar.part-{i:03d}" for i in range(len(parts))]
    assert len(parts) >= 3 and set(parts) <= set(made) and not (out / "export.tar").exists()
    assert all(p.stat().st_size <= 2048 for p in parts) and not list(out.glob("*.tmp"))
    (tmp_path / "joined.tar").write_bytes(b"".join(p.read_bytes() for p in parts))
    with tarfile.open(tmp_path / "joined.tar") as t:
        assert t.extractfile("export/a/b/s0/agent.pt").read() == blob
    made = rl_sweep.pack(tmp_path / "work", out)   # the default part size: one file, no parts left
    assert (out / "export.tar").exists() and not list(out.glob("export.tar.part-*"))


def test_committed_sweep_specs_are_valid():
    from pathlib import Path
    specs = sorted((Path(rl_sweep.ROOT) / "bench" / "results" / "rl" / "sweeps").glob("*.toml"))
    assert specs
    for p in specs:
        spec = rl_sweep.read_spec(p)
        assert spec["gpu"] and all(g["runs"] or g["probes"] for g in spec["gpu"])


def test_mps_is_started_only_where_it_can_be(monkeypatch):
    import shutil
    import subprocess
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert "not found" in rl_sweep.start_mps()
    monkeypatch.setattr(shutil, "which", lambda name: "/x/" + name)
    ran = []

    def fake_run(cmd, **kw):
        ran.append(cmd)
        return subprocess.CompletedProcess(cmd, 0 if cmd[0] == "pgrep" and running else 1, "", "no GPU")
    monkeypatch.setattr(subprocess, "run", fake_run)
    running = True
    assert rl_sweep.start_mps() == "MPS: the daemon runs already" and ran[-1][0] == "pgrep"
    running = False
    assert rl_sweep.start_mps() == "MPS: could not start the daemon (no GPU)"
    assert ran[-1] == ["/x/nvidia-cuda-mps-control", "-d"]


def test_a_failing_run_shows_its_log_and_a_late_one_is_killed_at_the_deadline(tmp_path):
    """A run that fails reports its exit code and its log's last lines; one still running at the
    call's deadline is killed with its process group (the call then packs)."""
    import sys
    import time
    (tmp_path / "_logs").mkdir()
    code = ("import subprocess, sys, time; print('boom', flush=True); "
            "sys.exit(3) if sys.argv[-1] == 'fail' else (print('child', subprocess.Popen([sys.executable, '-c', "
            "'import time; time.sleep(60)']).pid, flush=True), time.sleep(60))")
    job = {"index": 7, "env": {}, "probes": [], "runs": [
        {"cmd": [sys.executable, "-c", code, "--budget-seconds", "9", "fail"], "log": "a.log"},
        {"cmd": [sys.executable, "-c", code, "--budget-seconds", "9", "sleep"], "log": "b.log"}]}
    lines, t0 = [], time.monotonic()
    rl_sweep._guarded(job, tmp_path, t0, 100.0, t0 + 3.0, False, lines)
    text = dict((t.split(":")[1].strip(), (bad, t)) for bad, t in lines)
    assert text["a"][0] and "exit 3" in text["a"][1] and "boom" in text["a"][1]
    assert text["b"][0] and "killed at the call's deadline" in text["b"][1]
    child = int((tmp_path / "_logs" / "b.log").read_text().split("child ")[1].split()[0])

    def alive(pid):   # the killed group's grandchild: gone, or a zombie until init reaps it
        try:
            with open(f"/proc/{pid}/stat") as f:
                return f.read().split(")")[1].split()[0] != "Z"
        except FileNotFoundError:
            return False
    # SIGKILL lands asynchronously (a process in uninterruptible sleep dies when it leaves it, a
    # loaded machine tears it down late): wait a while; one never signalled sleeps on for 60 s
    end = time.monotonic() + 15.0
    while alive(child) and time.monotonic() < end:
        time.sleep(0.05)
    assert not alive(child)                      # killed with its parent's group, not left running
    assert (tmp_path / "_logs" / "a.log").read_text().startswith("boom")


def test_collect_keeps_a_killed_runs_records(tmp_path):
    """A run folder's records reach _results at the call's end whether or not its process
    finished (rl_seeds copies them only on a clean exit); the _-folders are not runs."""
    seed = tmp_path / "swimmer6" / "svg1-spinningup-mlp-ahead" / "s3"
    seed.mkdir(parents=True)
    (seed / "records.jsonl").write_text('{"env_steps": 10000}\n')
    (seed / "progress.csv").write_text("env_steps\n10000\n")
    (seed / "checkpoint.pt").write_bytes(b"x")
    old = tmp_path / "_results" / "swimmer6" / "svg1-spinningup-mlp-ahead" / "s3"
    old.mkdir(parents=True)
    (old / "records.jsonl").write_text("stale\n")
    (tmp_path / "_export" / "a" / "b" / "s0").mkdir(parents=True)
    (tmp_path / "_export" / "a" / "b" / "s0" / "records.jsonl").write_text("not a run\n")
    quick = tmp_path / "cheetah-run" / "svg0-x" / "s0"   # a quick run: its config names another task
    quick.mkdir(parents=True)
    (quick / "records.jsonl").write_text("{}\n")
    (quick / "config.json").write_text('{"task": "pendulum-balance"}')
    assert rl_sweep.collect(tmp_path) == 2
    assert (tmp_path / "_results" / "pendulum-balance" / "svg0-x" / "s0" / "config.json").is_file()
    assert not (tmp_path / "_results" / "cheetah-run").exists()
    assert (old / "records.jsonl").read_text() == '{"env_steps": 10000}\n'
    assert (old / "progress.csv").is_file() and not (old / "checkpoint.pt").exists()
    assert not (old / "config.json").exists() and not list(old.glob("*.tmp"))
    assert not (tmp_path / "_results" / "_export").exists()


def test_device_tests_probe_exits_with_pytests_code(tmp_path):
    """bench/probes/device_tests.py: pytest's exit code, so a failing test fails the sweep's probe."""
    import subprocess
    import sys
    from pathlib import Path
    script = Path(rl_sweep.ROOT) / "bench" / "probes" / "device_tests.py"
    (tmp_path / "test_ok.py").write_text("def test_ok():\n    assert 1 + 1 == 2\n")
    (tmp_path / "test_bad.py").write_text("def test_bad():\n    assert 1 + 1 == 3\n")
    run = lambda name: subprocess.run([sys.executable, str(script), "-q", "-p", "no:cacheprovider",  # noqa: E731
                                       str(tmp_path / name)], capture_output=True, text=True, cwd=tmp_path)
    ok, bad = run("test_ok.py"), run("test_bad.py")
    assert ok.returncode == 0 and "1 passed" in ok.stdout
    assert bad.returncode == 1 and "1 failed" in bad.stdout


@pytest.mark.parametrize("seeds", ["5-0", "x", "-1"])
def test_rl_seeds_refuses_a_seed_list_it_cannot_read(seeds, capsys):
    """An unreadable --seeds is argparse's usage error (exit 2), not a traceback."""
    from bench.rl_seeds import main
    with pytest.raises(SystemExit) as e:
        main(["--quick", "--seeds", seeds])
    assert e.value.code == 2 and "error:" in capsys.readouterr().err


def test_probe_seconds_stops_a_long_probe_and_the_runs_start(tmp_path):
    """A GPU's probes past its ``probe_seconds`` are killed (reported), and its runs start with the
    call's budget less the time the probes took."""
    import sys
    import time
    (tmp_path / "_logs").mkdir()
    sleeper = [sys.executable, "-c", "import time; print('probing', flush=True); time.sleep(60)"]
    run = [sys.executable, "-c", "import sys; print('seed 0: budget', sys.argv[2], flush=True)",
           "--budget-seconds", "999"]
    job = {"index": 5, "env": {}, "probes": [sleeper + ["probe.py"]], "probe_seconds": 1.5,
           "runs": [{"cmd": run, "log": "r.log"}]}
    lines, t0 = [], time.monotonic()
    rl_sweep._guarded(job, tmp_path, t0, 100.0, t0 + 60.0, True, lines)
    (probe_bad, probe_line), (run_bad, run_line) = lines
    assert probe_bad and "probe" in probe_line and "killed at the GPU's probe_seconds (1.5 s)" in probe_line
    assert not run_bad and "exit 0" in run_line
    budget = float(run_line.split("seed 0: budget ")[1].split()[0])
    assert budget <= 100 - 1.5                            # 100 s less the probe's time (at least its 1.5 s)
    spec = rl_sweep.read_spec(write(tmp_path, SPEC.replace("index = 3\n", "index = 3\nprobe_seconds = 240\n")))
    jobs = rl_sweep.commands(spec, tmp_path / "w", 500)
    assert [j["probe_seconds"] for j in jobs] == [None, 240]


def test_slim_copies_packed_restore_elsewhere_and_go_on(tmp_path, capsys):
    """A call with ``--slim`` packs each unfinished run's slim copy; ``restore`` in another work
    folder puts it in place and the run goes on from where it stopped (its replay buffer rebuilt),
    its records kept; a tar with a name out of slim/<task>/<run>/s<seed>/ is refused."""
    import json as _json

    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.run import run_rl
    run = 'runs = [{agent = "svg0", task = "pendulum-balance", seeds = "0", quick = true, env_steps = 160%s}]\n'
    spec1 = write(tmp_path, '[[gpu]]\nindex = "cpu"\n' + run % ', set = ["chunk=40"]', "one.toml")   # stops at 40
    out1 = tmp_path / "out1"
    assert rl_sweep.main([str(spec1), "--call-seconds", "300", "--work", str(tmp_path / "w1"), "--pack", str(out1),
                          "--slim"]) == 0
    assert (out1 / "slim.tar").exists() and (out1 / "export.tar").exists()
    with tarfile.open(out1 / "slim.tar") as t:
        assert f"slim/pendulum-balance/{QUICK_RUN}/s0/checkpoint.pt" in t.getnames()
    assert f"slim copy of pendulum-balance/{QUICK_RUN}/s0 (40 env steps)" in capsys.readouterr().out
    w2 = tmp_path / "w2"
    folder = w2 / "pendulum-balance" / QUICK_RUN / "s0"
    folder.mkdir(parents=True)                              # a run begun here, no checkpoint yet
    (folder / "records.jsonl").write_text("begun\n")
    assert rl_sweep.restore(w2, out1) == [f"pendulum-balance/{QUICK_RUN}/s0"]
    assert rl_sweep.restore(w2, out1) == []               # a run folder with a checkpoint stays as it is
    aside = w2 / "_replaced" / "pendulum-balance" / QUICK_RUN / "s0" / "records.jsonl"
    assert aside.read_text() == "begun\n"                 # set aside, not deleted
    w4 = tmp_path / "w4"   # a second folder to set aside where one lies already: s0.1
    for k, where in enumerate(("_replaced/pendulum-balance", "pendulum-balance")):
        (w4 / where / QUICK_RUN / "s0").mkdir(parents=True)
        (w4 / where / QUICK_RUN / "s0" / "records.jsonl").write_text(f"{k}\n")
    assert rl_sweep.restore(w4, out1) == [f"pendulum-balance/{QUICK_RUN}/s0"]
    assert [(w4 / "_replaced" / "pendulum-balance" / QUICK_RUN / s / "records.jsonl").read_text()
            for s in ("s0", "s0.1")] == ["0\n", "1\n"]
    cfg = _json.loads((folder / "config.json").read_text())
    r = run_rl(RLConfig.from_dict({**cfg, "out": str(folder), "chunk": None}))
    assert r["stop"] == "done" and r["env_steps"] == 160
    steps = [_json.loads(line)["env_steps"] for line in (folder / "records.jsonl").read_text().splitlines()]
    assert steps == [0, 80, 160]          # the first call's evaluation kept, the rest added
    assert rl_sweep.make_slim(w2) == []   # finished: no slim copy
    for name in ("slim/../../escape.toml", "slim/_results/t/s0/f", "slim/t/n/s0/deeper/f", "slim/t/n/x0/f"):
        bad = tmp_path / "bad.tar"
        with tarfile.open(bad, "w") as t:
            t.add(spec1, arcname=name)
        assert rl_sweep.main([str(spec1), "--call-seconds", "300", "--work", str(tmp_path / "w3"),
                              "--restore", str(bad)]) == 2
        assert "refused" in capsys.readouterr().err, name


def test_make_slim_copies_a_still_slim_run_and_reports_a_failing_one(tmp_path):
    """A restored run not yet checkpointed is copied as it is; a run whose copy fails is reported
    and the others still get theirs (the call's archives must not be lost)."""
    from gnwarp.rl.config import RLConfig
    from gnwarp.rl.run import run_rl
    from gnwarp.rl.slim import slim_run
    from tests.test_rl_run import TINY
    work = tmp_path / "w"
    run_rl(RLConfig(**{**TINY, "agent": "ddpg"}, out=str(work / "t" / "a" / "s0"), chunk=20))
    slim_run(work / "t" / "a" / "s0", work / "t" / "b" / "s0")          # still slim: copied as it is
    (work / "t" / "c" / "s0").mkdir(parents=True)
    (work / "t" / "c" / "s0" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    lines = rl_sweep.make_slim(work)
    assert any(ln.startswith("no slim copy of t/c/s0") for ln in lines), lines
    assert "slim copy of t/a/s0 (20 env steps)" in lines and "slim copy of t/b/s0 (20 env steps)" in lines
    assert (work / "_slim" / "t" / "b" / "s0" / "checkpoint.pt").read_bytes() == \
        (work / "t" / "b" / "s0" / "checkpoint.pt").read_bytes()
    # --slim-only: the matching runs' copies alone, and no other archive (one call's 64 MiB a share)
    out = tmp_path / "out"
    spec = tmp_path / "s.toml"
    spec.write_text('[[gpu]]\nindex = 0\nruns = [{agent = "ddpg", task = "swimmer6", seeds = "0"}]\n')
    assert rl_sweep.main([str(spec), "--work", str(work), "--slim-only", "t/a/*"]) == 2   # needs --pack
    assert rl_sweep.main([str(spec), "--work", str(work), "--slim-only", "t/a/*", "--pack", str(out)]) == 0
    assert sorted(p.name for p in out.iterdir()) == ["slim.tar"]
    with tarfile.open(out / "slim.tar") as t:
        runs = {m.name.rsplit("/", 1)[0] for m in t.getmembers() if m.name.endswith("checkpoint.pt")}
    assert runs == {"slim/t/a/s0"}
    (out / "export.tar.part-000").write_bytes(b"an earlier call's agents")   # not this call's archive: kept
    assert rl_sweep.main([str(spec), "--work", str(work), "--slim-only", "t/a/*", "--pack", str(out)]) == 0
    assert (out / "export.tar.part-000").read_bytes() == b"an earlier call's agents"
    assert rl_sweep.main([str(spec), "--work", str(work), "--slim-only", "a/*", "--pack", str(out)]) == 1   # whole path
