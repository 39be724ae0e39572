"""The command line as a new user meets it on a CPU: help for every command and option, output
paths and sizes refused before any work, quiet modes that still say where results went, and no
Warp CUDA-driver warning."""
import argparse
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from gnwarp import data
from gnwarp.cli import build_parser, main
from gnwarp.files import check_output_path
from gnwarp.gn import RunOptions
from gnwarp.models import GNCoreConfig, ModelConfig
from gnwarp.train import TrainConfig, train
from gnwarp.validation import available_memory, check_memory, config_keys

ROOT = Path(__file__).resolve().parents[1]
SWITCHES = (argparse._StoreTrueAction, argparse._StoreFalseAction, argparse._HelpAction)


def _commands(parser):
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


def test_every_command_and_option_has_help_and_its_default():
    commands = _commands(build_parser())
    assert set(commands) >= {"systems", "generate", "train", "evaluate", "demo", "check", "mpc"}
    for name, sp in commands.items():
        assert sp.description and len(sp.description) > 20, f"gnwarp {name} has no description"
        formatter = sp._get_formatter()
        for action in sp._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            what = f"gnwarp {name} {'/'.join(action.option_strings) or action.dest}"
            assert action.help, f"{what} has no help"
            if isinstance(action, SWITCHES) or action.required or (not action.option_strings and action.nargs != "?"):
                continue  # a switch, a required value or a positional: no default to show
            assert "default" in formatter._get_help_string(action), f"{what} shows no default"


def test_top_level_help_is_plain_text():
    text = build_parser().format_help()
    assert "``" not in text and "`" not in text
    assert "gnwarp demo" in text and "--quick" in text


def test_train_help_lists_every_config_key_with_its_default():
    text = _commands(build_parser())["train"].format_help()
    keys = config_keys(TrainConfig)
    assert len(keys) > 40 and {"steps", "model.gn.latent", "model.run.impl"} <= {k for k, *_ in keys}
    for key, default, allowed, _ in keys:
        assert f"  {key}=" in text, key
    assert "steps=100000: an integer >= 0" in text
    assert "--quick sets steps=" in text


def test_quick_preset_is_a_valid_cpu_sized_config():
    from gnwarp.cli.common import apply_overrides, merged
    from gnwarp.demo import DemoConfig, quick_train_keys
    quick = quick_train_keys()
    cfg = TrainConfig.from_dict(apply_overrides(merged(quick, {"model": {"core": "gn"}}), ["steps=50"]))
    assert cfg.steps == 50 and cfg.model.gn.latent == DemoConfig().gn.latent < GNCoreConfig().latent
    assert cfg.max_seconds == DemoConfig().train_seconds and cfg.model.gn.blocks == 2


def test_check_output_path(tmp_path):
    assert check_output_path(tmp_path / "x.h5") == tmp_path / "x.h5"
    assert check_output_path(tmp_path / "a" / "b", folder=True) == tmp_path / "a" / "b"  # made with parents
    with pytest.raises(FileNotFoundError, match="does not exist: .*missing"):
        check_output_path(tmp_path / "missing" / "x.h5")
    (tmp_path / "f").write_text("")
    with pytest.raises(NotADirectoryError, match="is a file"):
        check_output_path(tmp_path / "f" / "run", folder=True)
    with pytest.raises(IsADirectoryError):
        check_output_path(tmp_path)
    if os.geteuid() != 0:  # root writes anywhere
        ro = tmp_path / "ro"
        ro.mkdir(mode=0o500)
        with pytest.raises(PermissionError, match="not writable"):
            check_output_path(ro / "x.h5")


@pytest.mark.parametrize("argv", [
    ["generate", "-n", "3", "--steps", "5", "-o", "{tmp}/missing/x.h5"],
    ["train", "--data", "{tmp}/none.h5", "-o", "{tmp}/file/run"],
    ["evaluate", "{tmp}/ckpt", "--data", "{tmp}/none.h5", "-o", "{tmp}/file/out"],
    ["demo", "-q", "-o", "{tmp}/file/demo"],
])
def test_unwritable_output_is_refused_before_work(argv, tmp_path, capsys):
    (tmp_path / "file").write_text("")
    t0 = time.perf_counter()
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    assert time.perf_counter() - t0 < 5  # nothing simulated, trained or loaded
    err = capsys.readouterr().err
    assert f"gnwarp {argv[0]}: error:" in err and ("does not exist" in err or "is a file" in err)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_size_that_cannot_fit_is_refused_naming_the_limit():
    from gnwarp.cli.mpc import episode_bytes
    need = episode_bytes(8, 10**12, 2, 1)
    assert need > 8 * 10**12 * 2 * 13 * 4
    avail = available_memory()
    assert avail is not None and avail > 0
    with pytest.raises(ValueError, match=r"8 episodes .* needs about .* GiB of memory; this machine has .* GiB "
                                         r"available\. Use fewer"):
        check_memory(need, "8 episodes x 1000000000000 steps", "Use fewer --steps")
    check_memory(episode_bytes(8, 100, 2, 1), "a small run")  # fits: no error


@pytest.fixture(scope="module")
def tiny_model(tmp_path_factory):
    ds = data.generate("pendulum", (8, 2, 2), num_steps=10, seed=0, backend="mujoco", progress=False)
    out = tmp_path_factory.mktemp("newcomer") / "run"
    cfg = TrainConfig(out=str(out), model=ModelConfig(gn=GNCoreConfig(latent=8, edge_hidden=(8,), node_hidden=(8,),
                                                                      global_hidden=(8,)),
                                                      run=RunOptions(impl="torch")),
                      steps=4, batch_size=4, valid_every=4, valid_sequences=2, checkpoint_every=4,
                      normalizer_warmup=1, progress=False, device="cpu")
    return train(cfg, [ds])["last"]


def test_mpc_refuses_steps_beyond_memory_before_planning(tiny_model, tmp_path, capsys):
    t0 = time.perf_counter()
    assert main(["mpc", "--model", str(tiny_model), "--task", "pendulum-balance", "--steps", "1000000000000",
                 "--backend", "mujoco", "--video", "none", "--records", str(tmp_path / "r.jsonl")]) == 2
    err = capsys.readouterr().err
    assert "1000000000000 steps" in err and "available" in err and time.perf_counter() - t0 < 30


def test_mpc_progress_bar_counts_the_warmup(tiny_model, tmp_path, capsys):
    argv = ["mpc", "--model", str(tiny_model), "--task", "pendulum-balance", "--episodes", "2", "--steps", "2",
            "--horizon", "3", "--iterations", "1", "--warmup", "4", "--backend", "mujoco", "--video", "none",
            "--records", str(tmp_path / "r.jsonl")]
    assert main(argv) == 0
    out = capsys.readouterr()
    assert "6/6" in out.err and "true return" in out.out  # 4 warm-up + 1 x 2 steps iterations
    assert main(argv + ["-q"]) == 0
    out = capsys.readouterr()
    assert "6/6" not in out.err and "true return" in out.out


def test_demo_quiet_prints_where_the_report_went(tmp_path, monkeypatch, capsys):
    import gnwarp.demo
    seen = {}

    def fake_run_demo(cfg):
        seen["cfg"] = cfg
        return {"timings_s": {"total": 1.0}}
    monkeypatch.setattr(gnwarp.demo, "run_demo", fake_run_demo)
    assert main(["demo", "-q", "-o", str(tmp_path / "d")]) == 0
    assert seen["cfg"].progress is False
    assert capsys.readouterr().out.strip() == f"wrote {tmp_path / 'd' / 'report.md'} in 1 s"


def test_no_cuda_warning_on_a_cpu_machine(tmp_path):
    """A CLI command that starts Warp prints no CUDA-driver warning where there is no driver."""
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    code = ("import sys; from gnwarp.interop import warp; warp(); from gnwarp.cli import main; "
            "sys.exit(main(sys.argv[1:]))")
    r = subprocess.run([sys.executable, "-c", code, "generate", "-n", "3", "--steps", "5", "-q",
                        "-o", str(tmp_path / "x.h5")], capture_output=True, text=True, env=env, timeout=600)
    assert r.returncode == 0, r.stderr
    assert "wrote" in r.stdout
    assert "CUDA" not in r.stdout + r.stderr


def _mpc_argv(model, records, *extra):
    return ["mpc", "--model", str(model), "--task", "pendulum-balance", "--episodes", "2", "--steps", "2",
            "--horizon", "3", "--backend", "mujoco", "--video", "none", "--records", str(records), "-q", *extra]


@pytest.mark.parametrize("planner, extra", [
    ("hybrid", ["--iterations", "1", "--warmup", "1", "--set", "samples=4", "--set", "elites=2", "--terminal", "V"]),
    ("sampling", ["--set", "samples=5", "--set", "noise=0.3"]),
    ("mppi", ["--set", "samples=4", "--seed", "2"]),
])
def test_mpc_plans_with_each_model_planner(tiny_model, tmp_path, capsys, planner, extra):
    """``--planner`` plans through the model with the settings of the flags and ``--set``; the
    record's returns are those of the same planner made by ``make_planner`` and run by hand."""
    from gnwarp.control import run_episodes
    from gnwarp.control.planner import make_planner, planner_settings
    from gnwarp.control.value import TerminalValue
    from gnwarp.data.generation import initial_states
    from gnwarp.eval.records import read_records
    from gnwarp.sim import make_env, systems
    from gnwarp.train import load_model
    import numpy as np
    pend = systems.make("pendulum")
    value = TerminalValue.for_system(pend, hidden=(8,))
    value.save(tmp_path / "v.pt")
    extra = [str(tmp_path / "v.pt") if x == "V" else x for x in extra]
    records = tmp_path / "r.jsonl"
    assert main(_mpc_argv(tiny_model, records, "--planner", planner, *extra)) == 0
    assert "true return" in capsys.readouterr().out
    (rec,) = read_records(records)
    assert rec.planner == planner and rec.config["horizon"] == 3 and len(rec.returns) == 2
    assert rec.variant == ("terminal" if "--terminal" in extra else "")
    fields = rec.config["settings"]
    assert fields["horizon"] == 3 and fields["samples"] == int(next(s for s in extra if s.startswith("samples="))[8:])
    seed = int(extra[extra.index("--seed") + 1]) if "--seed" in extra else 0
    assert fields["seed"] == seed and fields.get("method", "best") == ("mppi" if planner == "mppi" else "best")
    # the same planner by hand
    settings = planner_settings(planner, {k: tuple(v) if isinstance(v, list) else v for k, v in fields.items()})
    model = load_model(tiny_model, device="cpu")
    term = TerminalValue.load(tmp_path / "v.pt") if "--terminal" in extra else None
    p = make_planner(planner, model, "pendulum-balance", pend, 2, settings, None, term)
    qpos, qvel = initial_states(pend, 2, np.random.default_rng(seed))
    env = make_env(pend, 2, backend="mujoco")
    out = run_episodes(p, env, "pendulum-balance", 2, env.reset(qpos, qvel))
    np.testing.assert_allclose(rec.returns, out["returns"].double().numpy(), rtol=1e-6)


@pytest.mark.parametrize("extra, message", [
    (["--planner", "nope"], "--planner 'nope': gnwarp mpc plans through a learned model with one of gradient, "
                            "hybrid, sampling, mppi"),
    (["--planner", "ilqg"], "--planner 'ilqg' (it does not plan through a learned model)"),
    (["--planner", "hybrid", "--set", "nope=1"], "nope: is not a setting of planner 'hybrid'; HybridConfig has "
                                                 "horizon, samples, elites"),
    (["--planner", "sampling", "--proposals", "3"], "--proposals does not apply to planner 'sampling' (SamplingConfig "
                                                    "has no proposals; its settings: horizon, samples"),
    (["--set", "iterations=0"], "iterations: must be"),
    (["--set", "iterations=2", "--iterations", "3"], "--set iterations=2 and --iterations both set iterations"),
    (["--set", "lr"], "--set: expects KEY=VALUE (a field of GradientMPCConfig), got 'lr'"),
    (["--planner", "mppi", "--set", "method=best"], "registered with method='mppi'"),
    (["--terminal", "{tmp}/none.pt"], "--terminal: no terminal-value file at"),
])
def test_mpc_refuses_bad_planners_and_settings_before_loading(tmp_path, capsys, extra, message):
    argv = _mpc_argv(tmp_path / "no-model", tmp_path / "r.jsonl", *[x.format(tmp=tmp_path) for x in extra])
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert "gnwarp mpc: error:" in err and message in err and "no-model" not in err
    assert "from --set iterations=0" in err if "iterations=0" in extra else True
    assert not (tmp_path / "r.jsonl").exists()


def test_systems_lists_the_dmc_domains_where_dm_control_is_installed(monkeypatch, capsys):
    """`gnwarp systems`: the built-in systems, then the DMC domains marked as such (with
    dm-control); without it, the built-in ones and a line on how to get the others."""
    import gnwarp.cli.data as cli_data
    from gnwarp.sim import systems
    from gnwarp.sim.dmc import dmc_names
    monkeypatch.setattr(cli_data, "dm_control_installed", lambda: False)
    assert main(["systems"]) == 0
    rows = capsys.readouterr().out.splitlines()
    assert [r.split()[0] for r in rows[1:-1]] == [systems.make(n).name for n in systems.names()]
    assert "dm-control" in rows[-1]
    pytest.importorskip("dm_control")
    monkeypatch.undo()
    assert main(["systems"]) == 0
    rows = capsys.readouterr().out.splitlines()
    dmc = {r.split()[0]: r for r in rows[1:] if r.startswith("dmc-")}
    assert list(dmc) == dmc_names() and all("DMC domain" in r for r in dmc.values())
    assert not any("DMC domain" in r for r in rows[1:] if not r.startswith("dmc-"))
    cheetah = dmc["dmc-cheetah"].split()
    assert cheetah[1:5] == ["8", "9", "9", "6"]   # bodies, nq, nv, nu of DMC's own cheetah
