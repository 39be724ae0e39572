"""Checkpoints never run code, are checked whole on load, and survive kills.

Tiny models on the CPU. Kills are simulated deterministically (debris folders made by hand, an
exception between the two renames that replace a checkpoint) and for real: a ``gnwarp train`` /
dataset save in a subprocess that sends itself SIGKILL at a chosen moment, then a rerun.
"""
import csv
import json
import os
import shutil
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
import torch

import gnwarp
from gnwarp import data
from gnwarp.gn import RunOptions
from gnwarp.models import GNCoreConfig, ModelConfig
from gnwarp.models.config import MLPCoreConfig, check_model_size, weight_count
from gnwarp.models.forward import ForwardModel
from gnwarp.train import CheckpointError, TrainConfig, load_model, train
from gnwarp.train import checkpoint as ck
from gnwarp.train.checkpoint import check_checkpoint, load_checkpoint

TINY = dict(latent=8, edge_hidden=(16,), node_hidden=(16,), global_hidden=(16,))
REPO = Path(__file__).resolve().parent.parent


@pytest.fixture(scope="module")
def pendulum():
    return data.generate("pendulum", (12, 3, 2), num_steps=12, seed=0, backend="mujoco", progress=False)


@pytest.fixture(scope="module")
def trained(tmp_path_factory, pendulum):
    """A finished tiny run (20 steps): its folder, to copy and damage."""
    out = tmp_path_factory.mktemp("trained")
    train(config(out, "run", steps=20), [pendulum])
    return out / "run"


def config(tmp_path, name="run", **kw):
    model = ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch"))
    base = dict(out=str(Path(tmp_path) / name), model=model, steps=20, batch_size=16, lr=3e-3, lr_decay_steps=1000,
                valid_every=10, valid_sequences=2, log_every=5, checkpoint_every=10, normalizer_warmup=2,
                progress=False, device="cpu")
    base.update(kw)
    return TrainConfig(**base)


def copy(src, dst):
    shutil.copytree(src, dst)
    return Path(dst)


def resign(folder):
    """Rewrite the manifest so it matches the folder's files again (as an attacker would)."""
    folder = Path(folder)
    names = sorted(p.name for p in folder.iterdir() if p.name != "manifest.json")
    (folder / "manifest.json").write_text(json.dumps({n: gnwarp.files.sha256_file(folder / n) for n in names}))


def logged_steps(out):
    with open(Path(out) / "log.csv") as f:
        return [int(r["step"]) for r in csv.DictReader(f)]


def dead_pid():
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


def run_to_death(cmd, **kw):
    """Run a command that is to kill itself with SIGKILL; returns its pid."""
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, **kw)
    _, err = p.communicate(timeout=120)
    assert p.returncode == -signal.SIGKILL, err[-3000:]
    return p.pid


def assert_same_parameters(a, b):
    ma, mb = load_model(a, device="cpu"), load_model(b, device="cpu")
    for k, v in ma.state_dict().items():
        torch.testing.assert_close(v, mb.state_dict()[k], rtol=1e-6, atol=1e-7, msg=k)


class Payload:
    """Unpickling this runs ``os.mkdir(marker)``."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (os.mkdir, (self.marker,))


# -- no code on load -------------------------------------------------------------------------
def test_a_pickle_payload_is_refused_unread(tmp_path, trained, pendulum):
    # not vacuous: the payload runs under weights_only=False
    probe = tmp_path / "probe.pt"
    torch.save({"x": Payload(tmp_path / "probe-ran")}, probe)
    torch.load(probe, weights_only=False)
    assert (tmp_path / "probe-ran").is_dir()

    marker = tmp_path / "payload-ran"
    run = tmp_path / "run"
    bad = copy(trained / "last", run / "last")
    t = torch.load(bad / "training.pt", weights_only=True)
    t["state"]["evil"] = Payload(marker)
    torch.save(t, bad / "training.pt")
    resign(bad)
    with pytest.raises(CheckpointError, match="training.pt holds objects other than tensors.*could run code"):
        load_checkpoint(bad, device="cpu")
    with pytest.raises(CheckpointError, match="refused unread"):   # resuming the run does not run it either
        train(config(tmp_path, "run", steps=30), [pendulum])
    lines = check_checkpoint(bad)
    assert any(x.startswith("error:") and "training.pt" in x for x in lines), lines
    assert not marker.exists()

    bad = copy(trained / "last", tmp_path / "weights")
    w = torch.load(bad / "model.pt", weights_only=True)
    w["evil"] = Payload(marker)
    torch.save(w, bad / "model.pt")
    resign(bad)
    with pytest.raises(CheckpointError, match="model.pt holds objects other than tensors"):
        load_model(bad, device="cpu")
    assert not marker.exists()


def test_training_state_is_tensors_and_plain_values(tmp_path, trained, pendulum):
    for opt in ("adam", "flat_adam"):
        r = train(config(tmp_path, opt, steps=5, optimizer=opt), [pendulum])
        t = torch.load(Path(r["last"]) / "training.pt", weights_only=True)
        assert set(t) == {"optimizer", "state", "generator"} and t["state"]["step"] == 5
    # what is not plain is refused when saving, naming where it is
    model = load_model(trained / "last", device="cpu")
    ck.save_checkpoint(tmp_path / "np", model, {"state": {"best": np.float64(0.5)}, "x": np.arange(3)})
    assert torch.load(tmp_path / "np" / "training.pt", weights_only=True)["state"]["best"] == 0.5
    with pytest.raises(TypeError, match=r"training\['state'\]\['evil'\] is a .*Payload"):
        ck.save_checkpoint(tmp_path / "evil", model, {"state": {"evil": Payload(tmp_path / "m")}})
    assert not (tmp_path / "evil").exists() and not list(tmp_path.glob(".evil*"))


# -- the manifest, the weights, the sizes ----------------------------------------------------
def test_the_manifest_covers_every_file(tmp_path, trained):
    bad = copy(trained / "last", tmp_path / "extra")
    (bad / "notes.txt").write_text("hi")
    with pytest.raises(CheckpointError, match="notes.txt not covered by manifest.json"):
        load_model(bad, device="cpu")
    bad = copy(trained / "last", tmp_path / "uncovered")
    man = json.loads((bad / "manifest.json").read_text())
    del man["model.pt"]
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(CheckpointError, match="does not cover model.pt"):
        load_model(bad, device="cpu")
    man["model.pt"], man["../x"] = "0" * 64, "0" * 64
    (bad / "manifest.json").write_text(json.dumps(man))
    with pytest.raises(CheckpointError, match="lists '../x'"):
        load_model(bad, device="cpu")
    bad = copy(trained / "last", tmp_path / "tampered")
    t = torch.load(bad / "training.pt", weights_only=True)
    t["state"]["step"] = 10**6
    torch.save(t, bad / "training.pt")          # manifest not re-signed
    with pytest.raises(CheckpointError, match="training.pt is corrupt"):
        load_checkpoint(bad, device="cpu")


@pytest.mark.parametrize("value", [float("nan"), float("inf")])
def test_nonfinite_weights_are_refused_naming_the_tensor(tmp_path, trained, value):
    bad = copy(trained / "last", tmp_path / "nan")
    w = torch.load(bad / "model.pt", weights_only=True)
    name = next(k for k in w if k.endswith("weight"))
    w[name].view(-1)[3] = value
    torch.save(w, bad / "model.pt")
    resign(bad)
    with pytest.raises(CheckpointError, match=f"NaN or Inf in {name}"):
        load_model(bad, device="cpu")
    assert any(x.startswith("error:") and name in x for x in check_checkpoint(bad))


def test_absurd_sizes_are_refused_before_allocating(tmp_path, trained, pendulum):
    sizes = pendulum.layout.sizes
    for mcfg in (ModelConfig(gn=GNCoreConfig(**TINY)), ModelConfig(),
                 ModelConfig(core="mlp", mlp=MLPCoreConfig(layers=2, width=32, n_node=2, n_edge=2))):
        m = ForwardModel(mcfg, pendulum.layout)
        assert weight_count(mcfg, sizes) == sum(p.numel() for p in m.core.parameters())
    for gn, key in (({"latent": 10**7}, "latent"), ({"edge_hidden": [40000, 40000]}, "edge_hidden")):
        bad = copy(trained / "last", tmp_path / key)
        cfg = json.loads((bad / "config.json").read_text())
        cfg["model"]["gn"].update(gn)
        (bad / "config.json").write_text(json.dumps(cfg))
        resign(bad)
        with pytest.raises(CheckpointError, match=f"gn.{key}"):
            load_model(bad, device="cpu")
    with pytest.raises(CheckpointError, match=r"model.gn.edge_hidden = \(40000, 40000\) makes a model of 3.\d+e\+09"):
        load_model(bad, device="cpu")
    with pytest.raises(ValueError, match="model.gn.edge_hidden"):
        check_model_size(ModelConfig(gn=GNCoreConfig(latent=8, edge_hidden=(40000, 40000))), sizes)
    with pytest.raises(ValueError, match="model.mlp.width"):
        check_model_size(ModelConfig(core="mlp", mlp=MLPCoreConfig(layers=3, width=60000, n_node=2)), sizes)
    with pytest.raises(ValueError, match="model.gn.edge_hidden"):   # training refuses it too, before allocating
        train(config(tmp_path, "huge-run", model=ModelConfig(gn=GNCoreConfig(latent=8, edge_hidden=(40000, 40000)))),
              [pendulum])


def test_check_checkpoint_reports_without_raising(tmp_path, trained):
    lines = check_checkpoint(trained / "last")
    assert lines and all(x.startswith("ok: ") for x in lines), lines
    assert any("training.pt" in x and "weights_only=True" in x for x in lines)
    assert check_checkpoint(tmp_path / "nowhere")[0].startswith("error: no checkpoint folder")
    bad = copy(trained / "best", tmp_path / "json")
    (bad / "config.json").write_text("{not json")
    assert check_checkpoint(bad)[-1].startswith("error: ") and "config.json is corrupt" in check_checkpoint(bad)[-1]
    bad = copy(trained / "best", tmp_path / "other")   # weights of another architecture, consistently signed
    cfg = json.loads((bad / "config.json").read_text())
    cfg["model"]["gn"]["latent"] = 9
    (bad / "config.json").write_text(json.dumps(cfg))
    resign(bad)
    lines = check_checkpoint(bad)
    assert [x.split(":")[0] for x in lines] == ["ok", "ok", "ok", "error", "ok"], lines


# -- resuming with another config ------------------------------------------------------------
def test_resuming_with_another_model_is_refused_or_restarts(tmp_path, pendulum):
    train(config(tmp_path, steps=10), [pendulum])
    log = (tmp_path / "run" / "log.csv").read_text()
    bigger = ModelConfig(gn=GNCoreConfig(**{**TINY, "latent": 16}), run=RunOptions(impl="torch"))
    with pytest.raises(CheckpointError, match=r"model.gn.latent: 8 -> 16.*on_config_change='restart'"):
        train(config(tmp_path, steps=20, model=bigger), [pendulum])
    other = ModelConfig(core="mlp", mlp={"layers": 2, "width": 16}, run=RunOptions(impl="torch"))
    with pytest.raises(CheckpointError, match=r"model.core: 'gn' -> 'mlp'"):
        train(config(tmp_path, steps=20, model=other), [pendulum])
    assert (tmp_path / "run" / "log.csv").read_text() == log       # nothing touched
    # run options may change on resume: fp64 continues the run
    fp64 = ModelConfig(gn=GNCoreConfig(**TINY), run=RunOptions(impl="torch", precision="fp64"))
    r = train(config(tmp_path, steps=15, model=fp64), [pendulum])
    assert r["steps"] == 15 and load_model(r["last"], device="cpu").dtype == torch.float64
    # by option: the old run moves aside whole, a new one starts
    with pytest.warns(UserWarning, match="replaced-1"):
        r = train(config(tmp_path, steps=10, model=bigger, on_config_change="restart"), [pendulum])
    old = tmp_path / "run" / "replaced-1"
    assert load_model(old / "last", device="cpu").config.gn.latent == 8 and logged_steps(old)[-1] == 15
    cfg = json.loads((tmp_path / "run" / "last" / "config.json").read_text())
    assert cfg["model"]["gn"]["latent"] == 16 == load_model(r["last"], device="cpu").config.gn.latent
    # the recorded training config says what the model is
    assert cfg["train"]["model"] == cfg["model"] and logged_steps(tmp_path / "run")[0] == 5


# -- kills -----------------------------------------------------------------------------------
def test_a_failure_between_the_renames_keeps_the_old_checkpoint(tmp_path, trained, monkeypatch):
    last = copy(trained / "last", tmp_path / "last")
    before = (last / "manifest.json").read_text()
    model = load_model(last, device="cpu")
    calls = []
    real = os.replace

    def replace(a, b):
        calls.append((a, b))
        if len(calls) == 2:
            raise OSError("disk gone")
        return real(a, b)
    monkeypatch.setattr(ck.os, "replace", replace)
    with pytest.raises(OSError, match="disk gone"):
        ck.save_checkpoint(last, model, {"state": {"step": 99}})
    monkeypatch.undo()
    assert Path(calls[0][1]).name.startswith(".last.old-")
    assert (last / "manifest.json").read_text() == before and not list(tmp_path.glob(".last*"))


def test_background_writes_hold_the_state_at_submit_and_report_failures(tmp_path, trained, monkeypatch):
    """The training loop's CheckpointWriter: what is written is the state when submitted, even
    though training changes the weights and optimizer tensors before the thread writes them; a
    write that fails raises in the caller's thread, and the previous checkpoint stays."""
    model = load_model(trained / "last", device="cpu")
    before = {k: v.clone() for k, v in model.state_dict().items()}
    moment = torch.arange(4.0)
    gate = __import__("threading").Event()
    real_write = ck._write

    def slow_write(path, snap):
        gate.wait(10)          # the write starts only after training has changed everything
        return real_write(path, snap)
    monkeypatch.setattr(ck, "_write", slow_write)
    w = ck.CheckpointWriter()
    w.submit("a", tmp_path / "a", model, {"optimizer": {"m": moment}, "state": {"step": 7}})
    assert w.done() == []      # not written yet: nothing reported
    with torch.no_grad():
        for p in model.parameters():
            p.add_(1.0)
    moment += 5
    gate.set()
    assert w.wait() == [("a", tmp_path / "a")]
    again = load_model(tmp_path / "a", device="cpu")
    for k, v in again.state_dict().items():
        torch.testing.assert_close(v, before[k], rtol=0, atol=0)
    training = torch.load(tmp_path / "a" / "training.pt", weights_only=True)
    torch.testing.assert_close(training["optimizer"]["m"], torch.arange(4.0))
    monkeypatch.setattr(ck, "_write", lambda path, snap: (_ for _ in ()).throw(OSError("disk full")))
    w.submit("b", tmp_path / "a", model)
    with pytest.raises(OSError, match="disk full"):
        w.wait()
    for k, v in load_model(tmp_path / "a", device="cpu").state_dict().items():   # the previous one is intact
        torch.testing.assert_close(v, before[k], rtol=0, atol=0)
    w.close()


def test_a_run_killed_between_the_renames_resumes_from_what_it_left(tmp_path, pendulum):
    """The state a kill between the renames leaves (no ``last``, the complete checkpoint under
    ``.last.old-<pid>``), with the debris of other kills: the rerun restores it, removes the
    debris, and ends where an uninterrupted run does."""
    full = train(config(tmp_path, "full", steps=30), [pendulum])
    train(config(tmp_path, "half", steps=20), [pendulum])
    out, pid = tmp_path / "half", dead_pid()
    os.replace(out / "last", out / f".last.old-{pid}")
    (out / f".last.tmp-{pid}").mkdir()                                # a save killed while writing
    (out / f".last.tmp-{pid}" / "config.json").write_text("{")
    shutil.copytree(out / "best", out / f".best.tmp-{pid}")           # killed before its manifest
    (out / f".best.tmp-{pid}" / "manifest.json").unlink()
    live = out / f".last.tmp-{os.getppid()}"                          # a live process's: left alone
    live.mkdir()
    with open(out / "log.csv", "a") as f:                             # rows written after the checkpoint
        f.write("25,1.0,0.003,1,1,1,1,1,\n26,1.")
    with pytest.warns(UserWarning, match=f"restored .*last from .last.old-{pid}"):
        r = train(config(tmp_path, "half", steps=30), [pendulum])
    assert r["steps"] == 30
    assert_same_parameters(full["last"], r["last"])
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".")) == [live.name]
    assert logged_steps(out) == logged_steps(tmp_path / "full")       # no row twice, none half


def test_load_model_restores_a_checkpoint_a_kill_left_aside(tmp_path, trained):
    pid = dead_pid()
    copy(trained / "last", tmp_path / f".last.old-{pid}")
    (tmp_path / f".last.tmp-{pid}").mkdir()                           # incomplete: not a candidate
    with pytest.warns(UserWarning, match=f"restored .*last from .last.old-{pid}"):
        m = load_model(tmp_path / "last", device="cpu")
    assert m.checkpoint_info["state"]["step"] == 20 and (tmp_path / "last" / "model.pt").is_file()
    assert [p.name for p in ck.clean_debris(tmp_path)] == [f".last.tmp-{pid}"]
    with pytest.raises(CheckpointError, match="no checkpoint folder"):
        load_model(tmp_path / "best", device="cpu")


def test_lost_progress_is_never_overwritten(tmp_path, pendulum):
    train(config(tmp_path, steps=20), [pendulum])
    out = tmp_path / "run"
    shutil.rmtree(out / "last")     # `best` is intact: the newest checkpoint left, resumed from
    best_step = json.loads((out / "best" / "config.json").read_text())["state"]["step"]
    with pytest.warns(UserWarning, match="restored .*last from best"):
        r = train(config(tmp_path, steps=25), [pendulum])
    assert r["steps"] == 25 and logged_steps(out)[-1] == 25 and best_step in logged_steps(out)
    log = (out / "log.csv").read_text()
    shutil.rmtree(out / "last")
    shutil.rmtree(out / "best")
    with pytest.raises(CheckpointError, match="log.csv records training up to step 25 but no checkpoint"):
        train(config(tmp_path, steps=30), [pendulum])
    assert (out / "log.csv").read_text() == log
    with pytest.warns(UserWarning, match="moved it to"):
        train(config(tmp_path, steps=5, on_config_change="restart"), [pendulum])
    assert (out / "replaced-1" / "log.csv").read_text() == log and logged_steps(out) == [5]


KILLER = textwrap.dedent("""
    import os, signal, sys
    import torch
    torch.set_num_threads(1)
    from gnwarp.train import checkpoint as ck
    when, n = sys.argv[1], int(sys.argv[2])
    seen = []
    real_replace, real_save = os.replace, torch.save

    def replace(a, b):  # the n-th move of `last` aside, then SIGKILL before the new one is renamed in
        real_replace(a, b)
        if when == "between" and os.path.basename(str(b)).startswith(".last.old-"):
            seen.append(b)
            if len(seen) == n:
                os.kill(os.getpid(), signal.SIGKILL)

    def save(obj, f, *a, **k):  # SIGKILL in the middle of writing the n-th training.pt
        if when == "writing" and str(f).endswith("training.pt"):
            seen.append(f)
            if len(seen) == n:
                with open(f, "wb") as h:
                    h.write(b"PK half")
                os.kill(os.getpid(), signal.SIGKILL)
        return real_save(obj, f, *a, **k)
    ck.os.replace, ck.torch.save = replace, save
    from gnwarp.cli import main
    sys.exit(main(sys.argv[3:]))
""")


@pytest.mark.parametrize("when, n", [("between", 1), ("writing", 2)])
def test_kill_9_of_gnwarp_train_then_rerun_resumes(tmp_path, pendulum, when, n):
    """A real SIGKILL of a CPU ``gnwarp train`` at a chosen moment: between the two renames
    that replace ``last`` at step 20 (``last`` gone; the old one under ``.last.old-<pid>``, the
    new one complete under ``.last.tmp-<pid>``), or while writing the training.pt of the first
    ``last`` (step 10: only ``best`` is intact). The rerun resumes from the newest intact
    checkpoint, and ends with the parameters and log of an uninterrupted run."""
    h5 = tmp_path / "pend.h5"
    pendulum.save(h5)
    toml = tmp_path / "cfg.toml"
    toml.write_text('steps = 30\nbatch_size = 16\nlr = 0.003\nlr_decay_steps = 1000\nvalid_every = 10\n'
                    'valid_sequences = 2\nlog_every = 5\ncheckpoint_every = 10\nnormalizer_warmup = 2\n'
                    'progress = false\ndevice = "cpu"\n[model.gn]\nlatent = 8\nedge_hidden = [16]\n'
                    'node_hidden = [16]\nglobal_hidden = [16]\n[model.run]\nimpl = "torch"\n')
    (tmp_path / "killer.py").write_text(KILLER)
    out = tmp_path / "run"
    args = ["train", str(toml), "--data", str(h5), "--out", str(out), "--quiet"]
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    pid = run_to_death([sys.executable, str(tmp_path / "killer.py"), when, str(n), *args], cwd=tmp_path, env=env)
    debris = sorted(x.name for x in out.iterdir() if x.name.startswith("."))
    assert not (out / "last").exists() and (out / "best").is_dir()
    assert debris == ([f".last.old-{pid}", f".last.tmp-{pid}"] if when == "between" else [f".last.tmp-{pid}"])
    from gnwarp.cli import main
    src = f".last.tmp-{pid}" if when == "between" else "best"        # the newest intact checkpoint
    with pytest.warns(UserWarning, match=f"restored .*last from {src}"):
        assert main(args) == 0                                        # the rerun
    full = train(config(tmp_path, "full", steps=30), [pendulum])     # uninterrupted, the same config
    assert_same_parameters(full["last"], out / "last")
    assert not [x for x in out.iterdir() if x.name.startswith(".")]
    assert logged_steps(out) == logged_steps(tmp_path / "full")


# -- datasets ---------------------------------------------------------------------------------
def test_a_killed_dataset_save_leaves_a_temporary_the_next_save_removes(tmp_path, pendulum):
    path = tmp_path / "d" / "pend.h5"
    path.parent.mkdir()
    script = textwrap.dedent(f"""
        import os, signal
        from gnwarp import data
        from gnwarp.data import dataset
        ds = data.generate("pendulum", (2, 1, 1), num_steps=3, seed=0, backend="mujoco", progress=False)
        dataset.os.replace = lambda a, b: os.kill(os.getpid(), signal.SIGKILL)   # killed before the rename
        ds.save({str(path)!r})
    """)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    pid = run_to_death([sys.executable, "-c", script], cwd=tmp_path, env=env)
    assert [x.name for x in path.parent.iterdir()] == [f".pend.h5.tmp-{pid}"] and not path.exists()
    live = path.parent / f".pend.h5.tmp-{os.getppid()}"   # another live writer's: left alone
    live.write_bytes(b"")
    pendulum.save(path)
    assert sorted(x.name for x in path.parent.iterdir()) == sorted(["pend.h5", live.name])
    assert data.load(path).meta["system"] == "pendulum"
