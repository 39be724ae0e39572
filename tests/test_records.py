"""Results records: validated on write and read (malformed lines refused by file and line), and
summaries regenerated from a small committed set equal the committed summary (no number typed)."""
import json
import math
from pathlib import Path

import numpy as np
import pytest

from gnwarp.eval import summarize
from gnwarp.eval.records import (DYNAMICS, PLANNERS, RecordError, ResultRecord, git_commit, gpu_name, read_records,
                                 write_records)

DATA = Path(__file__).resolve().parent / "data"
SMALL = DATA / "records_small.jsonl"
RATIO = ["--ratio", "gradient (learned)/ilqg (true, MuJoCo C)"]


def record(**kw):
    base = dict(experiment="test", task="pendulum-balance", planner="gradient", dynamics="learned", episodes=2,
                episode_steps=10, returns=[-1.0, -2.0], seed=0, control_dt=0.05)
    base.update(kw)
    return ResultRecord(**base)


def test_summary_regenerated_from_committed_records(tmp_path):
    rc = summarize.main([str(SMALL), "--out", str(tmp_path), "--title", "Small records", "--no-plot"] + RATIO)
    assert rc == 0
    assert (tmp_path / "summary.md").read_text() == (DATA / "records_small_summary.md").read_text()


def test_summary_groups_pool_seeds_and_keep_the_last_rerun():
    recs = read_records(SMALL)
    gs = {(g.task, g.planner, g.dynamics, g.variant): g for g in summarize.groups(recs)}
    grad = gs["pendulum-balance", "gradient", "learned", ""]
    pooled = [x for r in recs if r.key == grad.records[0].key for x in r.values]
    assert grad.n == len(pooled) == 8 and grad.mean == pytest.approx(np.mean(pooled))
    ilqg = gs["pendulum-balance", "ilqg", "true_mujoco_c", ""]
    last = [r for r in recs if r.key == ilqg.records[0].key][-1]
    assert ilqg.n == 4 and ilqg.mean == pytest.approx(np.mean(last.values))  # same seed: the rerun stands
    sd = np.std(last.values, ddof=1)
    assert ilqg.ci == pytest.approx(summarize.t_quantile(3) * sd / 2)
    assert gs["cartpole-balance", "ilqg", "true_mujoco_c", ""].reported


def test_plot_is_written(tmp_path):
    path = summarize.write_summary(read_records(SMALL), tmp_path, "t")
    assert path.exists() and (tmp_path / "returns.png").stat().st_size > 1000


def test_t_quantile_matches_scipy():
    stats = pytest.importorskip("scipy.stats")
    for df in (1, 2, 5, 29, 30, 31, 40, 100, 1000):
        assert summarize.t_quantile(df) == pytest.approx(stats.t.ppf(0.975, df), abs=2e-3)
    with pytest.raises(ValueError):
        summarize.t_quantile(0)


def test_roundtrip_append_and_nan(tmp_path):
    path = tmp_path / "r.jsonl"
    a, b = record(), record(returns=[float("nan"), 3.5], planner="random", dynamics="none")
    write_records(path, [a])
    write_records(path, [b])
    back = read_records(path)
    assert [r.planner for r in back] == ["gradient", "random"]
    assert back[0] == a
    assert back[1].returns == [None, 3.5] and math.isnan(back[1].values[0])
    assert json.loads(path.read_text().splitlines()[0])["format"] == "gnwarp-result"
    write_records(path, [a], append=False)
    assert len(read_records(path)) == 1
    assert not list(tmp_path.glob(".*tmp"))  # no temporary left beside it


def test_write_refuses_a_missing_folder_and_non_records(tmp_path):
    with pytest.raises(FileNotFoundError, match="missing"):
        write_records(tmp_path / "missing" / "r.jsonl", [record()])
    with pytest.raises(RecordError, match="record 0 is a dict"):
        write_records(tmp_path / "r.jsonl", [record().to_dict()])
    assert not (tmp_path / "r.jsonl").exists()


@pytest.mark.parametrize("change, field", [
    (dict(planner="gradient_descent"), "planner"),
    (dict(dynamics="true"), "dynamics"),
    (dict(episodes=0), "episodes"),
    (dict(episodes=True), "episodes"),
    (dict(returns=[1.0]), "returns"),
    (dict(returns=["a", 1.0]), "returns"),
    (dict(returns=None), "returns"),
    (dict(errors=[1.0, 2.0]), "errors"),
    (dict(returns=None, reported={"mean": 1.0}), "reported"),
    (dict(reported={"mean": 1.0, "std": 0.5}), "reported"),
    (dict(control_dt=0.0), "control_dt"),
    (dict(seed=-1), "seed"),
    (dict(env_steps=1.5), "env_steps"),
    (dict(task=""), "task"),
    (dict(config={"x": object()}), "config"),
    (dict(version=2), "version"),
    (dict(format="other"), "format"),
])
def test_malformed_record_refused_by_field(change, field):
    with pytest.raises(RecordError, match=f"field '{field}'"):
        record(**change)


def test_names_are_the_documented_ones():
    assert {"gradient", "sampling", "ilqg", "random"} <= set(PLANNERS)
    assert set(DYNAMICS) >= {"learned", "true_mjwarp", "true_mujoco_c"}


@pytest.mark.parametrize("line, message", [
    ("{not json", "not JSON"),
    ("[1, 2]", "a JSON object"),
    ('{"format": "gnwarp-result", "version": 1}', "missing field"),
    (None, "unknown field"),
    (None, "field 'planner'"),
])
def test_malformed_line_refused_naming_file_and_line(tmp_path, line, message):
    good = json.dumps(record().to_dict())
    if line is None:
        d = record().to_dict()
        if message == "unknown field":
            d["retruns"] = [1.0, 2.0]
        else:
            d["planner"] = "nope"
        line = json.dumps(d)
    path = tmp_path / "bad.jsonl"
    path.write_text(f"{good}\n\n{line}\n")
    with pytest.raises(RecordError, match=rf"bad\.jsonl, line 3: .*{message}"):
        read_records(path)
    assert summarize.main([str(path), "--out", str(tmp_path / "s")]) == 2
    assert not (tmp_path / "s").exists()


def test_commit_and_gpu_helpers(tmp_path):
    c = git_commit()
    assert c == "unknown" or len(c.split("+")[0]) == 40
    assert git_commit(tmp_path) == "unknown"  # outside any repository
    assert isinstance(gpu_name(), str) and gpu_name("cpu") == "cpu"


def test_errors_without_std_are_summarized_by_their_mean(tmp_path):
    rec = record(planner="none", variant="GN", returns=None, episodes=200, episode_steps=20,
                 reported={"mean": 0.0123, "std": None, "of": "errors"})
    assert rec.kind == "errors" and rec.values is None
    (g,) = summarize.groups([rec])
    assert g.reported and g.mean == 0.0123 and math.isnan(g.std) and math.isnan(g.ci)
    lines = summarize.summary_lines([g])
    assert "| pendulum-balance | 0.0123 |" in lines and "errors per group" in lines[2]
    summarize.write_summary([rec], tmp_path)
    assert (tmp_path / "errors.png").exists()


def test_reported_means_of_several_seeds_pool_over_the_seeds():
    means = [0.0466, 0.0453, 0.0496]
    recs = [record(planner="none", variant="IN", returns=None, seed=s, episodes=200, episode_steps=20,
                   reported={"mean": m, "std": None, "of": "errors"}) for s, m in enumerate(means)]
    (g,) = summarize.groups(recs)
    assert g.over == "seeds" and g.reported and g.n == 3
    assert g.mean == pytest.approx(np.mean(means)) and g.std == pytest.approx(np.std(means))
    assert g.ci == pytest.approx(summarize.t_quantile(2) * np.std(means, ddof=1) / math.sqrt(3))
    assert any("| 3 seeds (reported means) |" in line for line in summarize.summary_lines([g]))
    rerun = record(planner="none", variant="IN", returns=None, seed=0, episodes=200, episode_steps=20,
                   reported={"mean": 0.5, "std": None, "of": "errors"})
    assert summarize.groups(recs + [rerun])[0].mean == pytest.approx(np.mean([0.5, *means[1:]]))  # the rerun stands
    with pytest.raises(ValueError, match="cannot be pooled"):
        summarize.groups(recs + [record(planner="none", variant="IN", seed=9, episode_steps=20)])


def test_a_binary_file_is_refused_as_records_naming_it(tmp_path):
    """A records path that names another kind of file (a dataset, say) is one RecordError naming
    the file and line, not a decoder's error; the file is left as it was."""
    from gnwarp.eval.records import RecordError, read_records
    f = tmp_path / "data.h5"
    f.write_bytes(b"\x89HDF\r\n\x1a\n\xff\xfe\x00binary")
    with pytest.raises(RecordError, match=r"data\.h5, line 1: not text"):
        read_records(f)
    assert f.read_bytes().startswith(b"\x89HDF")


def test_summarize_refuses_a_file_where_its_folder_goes(tmp_path, capsys):
    """--out naming a file (or a binary file given as records) is one error line, not a traceback."""
    taken = tmp_path / "taken"
    taken.write_text("mine")
    assert summarize.main([str(SMALL), "--out", str(taken)]) == 2
    assert "is a file" in capsys.readouterr().err and taken.read_text() == "mine"
    binary = tmp_path / "x.h5"
    binary.write_bytes(b"\x89HDF\xff\xfe")
    assert summarize.main([str(binary), "--out", str(tmp_path / "s")]) == 2
    assert "x.h5, line 1: not text" in capsys.readouterr().err


def _append_many(path, k, n):
    for i in range(n):
        write_records(path, [ResultRecord(experiment=f"w{k}", task="pendulum-balance", planner="gradient",
                                          dynamics="learned", episodes=1, episode_steps=5, returns=[1.0], seed=i)])


def test_writers_appending_at_once_keep_every_record(tmp_path):
    """Each append reads the file, adds to it and renames it over: writers in several processes
    take turns (a lock on the folder), so none loses another's records; nothing else is left."""
    import multiprocessing as mp
    path = tmp_path / "r.jsonl"
    procs = [mp.get_context("fork").Process(target=_append_many, args=(path, k, 40)) for k in range(3)]
    for p in procs:
        p.start()
    for p in procs:
        p.join(60)
    assert [p.exitcode for p in procs] == [0, 0, 0]
    recs = read_records(path)
    assert len(recs) == 120 and {(r.experiment, r.seed) for r in recs} == {(f"w{k}", i) for k in range(3)
                                                                            for i in range(40)}
    assert [p.name for p in tmp_path.iterdir()] == ["r.jsonl"]
