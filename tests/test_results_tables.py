"""The results tables are generated from records (``bench/results_tables.py``): regenerating a
small committed set gives its committed blocks, a changed record changes its row, and the
repository's README and ``bench/results`` tables are exactly what their records give."""
import json
import math
import shutil
from pathlib import Path

import numpy as np
import pytest

from bench import results_tables as rt

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT / "tests" / "data" / "results_tables"
FIG10 = Path("bench/results/control/fig10/results.jsonl")
DOC = Path("bench/results/control/README.md")


def _block(text: str, name: str) -> str:
    m = next(m for m in rt.BLOCK.finditer(text) if m.group("name") == name)
    return m.group("body")


def test_small_set_regenerates_its_committed_blocks():
    docs = rt.documents(DATA)
    assert {p.relative_to(DATA).as_posix() for p in docs} == {
        DOC.as_posix(), "bench/results/sysid_figures/small/compare.md"}
    assert rt.run(DATA, check=True) == []          # the committed blocks are what the records give
    for doc in docs:
        assert rt.render(doc.read_text(), DATA, doc) == doc.read_text()


def test_cells_are_the_mean_and_95_interval_of_the_episodes():
    """Reference: the t interval from the records' per-episode returns (19 degrees of freedom)."""
    recs = [json.loads(line) for line in (DATA / FIG10).read_text().splitlines()]
    r = next(x for x in recs if x["task"] == "pendulum-balance" and x["variant"] == "no_params")
    v = np.asarray(r["returns"], dtype=np.float64)
    half = 2.093 * v.std(ddof=1) / math.sqrt(len(v))
    body = _block((DATA / DOC).read_text(), "control-fig10")
    row = next(line for line in body.splitlines() if line.startswith("| pendulum-balance |"))
    assert row.split(" | ")[1] == f"{v.mean():.1f} +- {half:.0f}"
    assert "95% t interval" in body


def test_a_changed_record_changes_its_row(tmp_path):
    root = tmp_path / "root"
    shutil.copytree(DATA, root)
    lines = (root / FIG10).read_text().splitlines()
    rec = json.loads(lines[0])
    assert rec["task"] == "pendulum-balance" and rec["variant"] == "no_params"
    rec["returns"] = [x + 100.0 for x in rec["returns"]]
    lines[0] = json.dumps(rec)
    (root / FIG10).write_text("\n".join(lines) + "\n")
    before = (root / DOC).read_text()
    assert rt.run(root, check=True) == [root / DOC]           # --check sees the difference, writes nothing
    assert (root / DOC).read_text() == before
    assert rt.main(["--root", str(root), "--check"]) == 1
    assert rt.run(root) == [root / DOC]
    after = (root / DOC).read_text()
    def row(text, task):
        return next(x for x in _block(text, "control-fig10").splitlines() if x.startswith(f"| {task} |"))
    assert row(after, "pendulum-balance") != row(before, "pendulum-balance")
    assert row(after, "pendulum-balance").split(" | ")[1].startswith(f"{np.mean(rec['returns']):.1f} +- ")
    assert row(after, "cartpole-balance") == row(before, "cartpole-balance")
    # the text outside the markers is kept
    assert before.split("<!-- results:begin")[0] == after.split("<!-- results:begin")[0]
    assert before.split("<!-- results:end control-fig10 -->")[1] == after.split("<!-- results:end control-fig10 -->")[1]
    assert rt.main(["--root", str(root), "--check"]) == 0


def test_unknown_block_is_refused(tmp_path):
    doc = tmp_path / "README.md"
    doc.write_text("<!-- results:begin nope -->\n<!-- results:end nope -->\n")
    with pytest.raises(KeyError, match="unknown results block 'nope'"):
        rt.run(tmp_path, files=[doc])


def test_repository_tables_are_what_their_records_give():
    assert rt.run(ROOT, check=True) == [], "a generated table differs: run python bench/results_tables.py"
    readme = (ROOT / "README.md").read_text()
    assert "<!-- results:begin headline -->" in readme


def test_seed_ids_as_runs():
    assert rt._seed_ids([9, 0, 1, 2, 6, 8]) == "0-2, 6, 8-9"
    assert rt._seed_ids([4]) == "4" and rt._seed_ids([]) == ""
