"""The data loop's learned terminal value (LoopConfig.value) on the CPU with a tiny pendulum model,
the loop planning with the hybrid and the sampling planners through the learned model: the value
is fitted after an iteration's training on the stored episodes and saved, its TD errors recorded
(recomputed from the saved file), the next iteration's planner gets it, a kill after the fit
resumes fitting from the previous value (each episode fitted once), and a value whose gamma
disagrees with the planner's discount is refused."""
import json
import shutil

import numpy as np
import pytest
import torch
from test_data_loop import EPISODES, STEPS, config

from gnwarp.control import data_loop
from gnwarp.control.data_loop import LoopConfig, run_loop
from gnwarp.control.loop_store import read_state
from gnwarp.control.loop_value import shard_episodes, value_path
from gnwarp.control.value import TerminalValue, episode_rewards
from gnwarp.data.dataset import load
from gnwarp.eval.records import read_records
from gnwarp.validation import ConfigError

GAMMA = 0.9
VALUE = {"hidden": [16], "rounds": 2, "steps": 5, "batch": 16}
HYBRID = {"samples": 4, "elites": 2, "iterations": 1, "warmup": 0, "horizon": 3, "knots": 2, "discount": GAMMA}


def vconfig(out, iterations, **kw) -> LoopConfig:
    return config(out, iterations, **{"planner": "hybrid", "planner_settings": HYBRID, "value": VALUE, **kw})


@pytest.fixture(scope="module")
def vloop(tmp_path_factory):
    """A hybrid loop with a value: folder copies after iteration 0 and 1, and after 2 (the
    terminal values each planner was built with, in order)."""
    root = tmp_path_factory.mktemp("vloop")
    out = root / "run"
    got = []
    make = data_loop.make_loop_planner

    def spy(*a, terminal=None, **k):
        got.append(terminal)
        return make(*a, terminal=terminal, **k)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(data_loop, "make_loop_planner", spy)
        run_loop(vconfig(out, 0))
        shutil.copytree(out, root / "after0")
        run_loop(vconfig(out, 1))
        shutil.copytree(out, root / "after1")
        run_loop(vconfig(out, 2))
    return out, root, got


def _rewards(out, i):
    x, a, tg = shard_episodes(load(out / f"data/iter-{i:04d}.h5", lazy=False))
    return x, episode_rewards("pendulum-balance", x, a, tg)


def test_the_value_is_fitted_saved_and_its_td_error_recorded(vloop):
    out, _, _ = vloop
    recs = read_records(out / "records.jsonl")
    assert [r.metrics["iteration"] for r in recs] == [1, 2]
    assert not value_path(out, 1).exists() and value_path(out, 2).is_file() and value_path(out, 3).is_file()
    m1, m2 = recs[0].metrics["value"], recs[1].metrics["value"]
    assert (m1["file"], m2["file"]) == ("value/iter-0002.pt", "value/iter-0003.pt")
    assert (m1["episodes"], m2["episodes"]) == (EPISODES, 2 * EPISODES)
    assert len(m1["td_error_rounds"]) == VALUE["rounds"] + 1 and m1["td_error_new"] is None
    # the recorded TD errors are those of the saved values on the episodes (recomputed here)
    v2, v3 = TerminalValue.load(value_path(out, 2)), TerminalValue.load(value_path(out, 3))
    assert (v2.gamma, v2.hidden) == (GAMMA, (16,))
    x1, r1 = _rewards(out, 1)
    x2, r2 = _rewards(out, 2)
    assert x1.shape[:2] == (EPISODES, STEPS + 1) and r1.shape == (EPISODES, STEPS)
    assert m1["td_error"] == pytest.approx(v2.td_error(x1, r1), rel=1e-5)
    assert m2["td_error"] == pytest.approx(v3.td_error(torch.cat([x1, x2]), torch.cat([r1, r2])), rel=1e-5)
    assert m2["td_error_new"] == pytest.approx(v2.td_error(x2, r2), rel=1e-5)   # before the fit, new episodes
    # warm start: the second fit continues from the first (its feature statistics kept, weights moved)
    assert torch.equal(v2.mean, v3.mean) and not torch.equal(v2.net[0].weight, v3.net[0].weight)
    assert recs[1].metrics["value_seconds"] >= 0 and read_state(out).iteration == 2


def test_the_next_iterations_planner_gets_the_value(vloop):
    out, _, got = vloop
    assert len(got) == 2 and got[0] is None and isinstance(got[1], TerminalValue)
    saved = TerminalValue.load(value_path(out, 2))
    assert all(torch.equal(a, b) for a, b in zip(got[1].state_dict().values(), saved.state_dict().values()))
    recs = read_records(out / "records.jsonl")
    assert "value" not in recs[0].config and recs[1].config["value"] == "value/iter-0002.pt"
    assert load(out / "data/iter-0002.h5").meta["loop"]["value"] == "value/iter-0002.pt"
    # the value changes what the planner scores: a rollout's planned return with it and without
    from gnwarp.control.returns import planned_return
    from gnwarp.control.tasks import get_task
    x, _ = _rewards(out, 1)
    a = torch.zeros(EPISODES, 3, 1)
    task = get_task("pendulum-balance")
    with_v = planned_return(task.reward, x[:, :4], a, None, GAMMA, saved)
    without = planned_return(task.reward, x[:, :4], a, None, GAMMA, None)
    assert torch.allclose(with_v - without, GAMMA ** 3 * saved(x[:, 3]), rtol=1e-4, atol=1e-6)
    assert not torch.allclose(with_v, without)


def test_a_kill_after_the_fit_refits_from_the_previous_value(vloop, tmp_path, monkeypatch):
    out, root, _ = vloop
    run = tmp_path / "run"
    shutil.copytree(root / "after1", run)
    # iteration 2 killed after its training and its value fit, before its record and state
    monkeypatch.setattr(data_loop, "_record", lambda *a, **k: (_ for _ in ()).throw(KeyboardInterrupt()))
    with pytest.raises(KeyboardInterrupt):
        run_loop(vconfig(run, 2))
    assert read_state(run).iteration == 1 and value_path(run, 3).is_file()
    killed = TerminalValue.load(value_path(run, 3))
    monkeypatch.undo()
    fits = []
    fit = data_loop.fit_loop_value

    def counted(cfg, task, system, folder, shards, j, gamma):
        fits.append((j, len(shards)))
        return fit(cfg, task, system, folder, shards, j, gamma)
    monkeypatch.setattr(data_loop, "fit_loop_value", counted)
    monkeypatch.setattr(data_loop, "_collect", lambda *a, **k: pytest.fail("planned iteration 2 again"))
    run_loop(vconfig(run, 2))
    assert fits == [(3, 2)]   # once, on shards 1 and 2
    rec = read_records(run / "records.jsonl")[-1]
    assert rec.metrics["value"]["episodes"] == 2 * EPISODES
    # fitted from value/iter-0002 again (not from the killed call's iter-0003): the same value as that call's
    again = TerminalValue.load(value_path(run, 3))
    for k, v in killed.state_dict().items():
        assert torch.allclose(again.state_dict()[k], v, rtol=1e-5, atol=1e-6), k
    direct = read_records(out / "records.jsonl")[-1].metrics["value"]
    assert rec.metrics["value"]["td_error_new"] == pytest.approx(direct["td_error_new"], rel=1e-4)


def test_the_sampling_planner_through_the_model_with_a_value(vloop, tmp_path):
    """Iteration 1 and 2 with the sampling planner, from the hybrid loop's seed data and model."""
    _, root, _ = vloop
    run = tmp_path / "run"
    run.mkdir()
    shutil.copytree(root / "after0" / "data", run / "data")
    shutil.copytree(root / "after0" / "model", run / "model")   # trained: no steps left to train at iteration 0
    sampling = {"samples": 4, "horizon": 3, "knots": 2, "discount": GAMMA}
    r = run_loop(vconfig(run, 2, planner="sampling", planner_settings=sampling))
    recs = read_records(run / "records.jsonl")
    assert r["iterations"] == 2 and [x.planner for x in recs] == ["sampling", "sampling"]
    assert recs[1].config["value"] == "value/iter-0002.pt" and np.all(np.isfinite(recs[1].returns))
    assert value_path(run, 3).is_file()


def test_gamma_and_discount_must_agree(tmp_path):
    with pytest.raises(ConfigError, match=r"value.gamma: is 0.95 but planner_settings.discount is 0.9; they must "
                                          r"agree"):
        vconfig(tmp_path, 1, value={**VALUE, "gamma": 0.95})
    with pytest.raises(ConfigError, match=r"value.gamma: the value needs a discount < 1: set "
                                          r"planner_settings.discount"):
        vconfig(tmp_path, 1, planner_settings={k: v for k, v in HYBRID.items() if k != "discount"})
    with pytest.raises(ConfigError, match="value: planner 'random' takes no terminal value"):
        vconfig(tmp_path, 1, planner="random", planner_settings={})
    with pytest.raises(ConfigError, match="value.hidden"):
        vconfig(tmp_path, 1, value={"hidden": [0]})
    with pytest.raises(ConfigError, match="value.nope: unknown"):
        vconfig(tmp_path, 1, value={"nope": 1})
    assert vconfig(tmp_path, 1, value={"gamma": GAMMA}).value.gamma == GAMMA
    assert config(tmp_path, 1).value is None


def test_a_folder_config_without_the_value_key_reads_it_unset(vloop, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(vloop[1] / "after1", run)
    saved = json.loads((run / "config.json").read_text())
    del saved["value"]
    (run / "config.json").write_text(json.dumps(saved))
    with pytest.raises(ConfigError, match="value: None in the folder"):
        run_loop(vconfig(run, 1))
    # the same folder under the config it holds (no value): nothing to do at iteration 1
    assert run_loop(vconfig(run, 1, value=None))["iterations"] == 1


def test_an_ensemble_trains_each_member_and_plans_over_all(vloop, tmp_path, monkeypatch):
    """Two members from the hybrid loop's seed data (member 0's model trained there, member 1's
    trained here from its own seed), the sampling planner over both, with the value."""
    from gnwarp.control.sampling import EnsembleDynamics
    from gnwarp.train.checkpoint import load_model
    run = tmp_path / "run"
    run.mkdir()
    shutil.copytree(vloop[1] / "after0" / "data", run / "data")
    shutil.copytree(vloop[1] / "after0" / "model", run / "model")
    got = []
    from gnwarp.control import planner as planner_module
    build = planner_module.make_planner

    def spy(name, dynamics, *a, **k):
        got.append(dynamics)
        return build(name, dynamics, *a, **k)
    monkeypatch.setattr(planner_module, "make_planner", spy)
    sampling = {"samples": 4, "horizon": 3, "knots": 2, "discount": GAMMA}
    run_loop(vconfig(run, 2, planner="sampling", planner_settings=sampling, ensemble=2, ensemble_penalty=0.5))
    assert len(got) == 2 and all(isinstance(d, EnsembleDynamics) and len(d.members) == 2 for d in got)
    assert got[0].penalty == 0.5
    for j in (1, 2, 3):
        a, b = load_model(run / f"models/iter-{j:04d}"), load_model(run / f"models/iter-{j:04d}-m1")
        pa, pb = (torch.cat([p.detach().flatten() for p in m.parameters()]) for m in (a, b))
        assert pa.shape == pb.shape and not torch.allclose(pa, pb)   # other seeds, other weights
    assert read_state(run).train_steps == read_state(vloop[0]).train_steps and (run / "model-1/last").is_dir()
    with pytest.raises(ConfigError, match="ensemble: planner 'gradient' plans through one model"):
        config(tmp_path, 1, ensemble=2)
