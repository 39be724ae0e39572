"""One-time conversion of the control experiments' row files to results records, and the check
that the summaries regenerated from them show the same numbers.

    PYTHONPATH=. python3 bench/convert_records.py [--check-only]

Rewrites, in place, ``bench/results/control/{results,throughput,cpu_timing,swimmer_iterations}.jsonl``
and ``{fig10,fig11,iterations}/results.jsonl`` as ``gnwarp.eval.records`` lines, and writes
``bench/results/forward_models/results.jsonl`` from its ``<system>/results.json`` files (every number
unchanged; a file already in the record format is left alone), regenerates the ``summary.md`` of
``control``, ``fig10`` and ``fig11`` with ``gnwarp.eval.summarize``, and compares each mean +- std
cell and ratio of the first table of the summary at commit e848b55 (the row format's last) with the
regenerated one, and each error of the forward models' table with its record (exit 1 on a
difference).
"""
from __future__ import annotations

import argparse
import json
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
BASE = "e848b55"  # the commit whose summaries the regenerated ones are compared with
sys.path.insert(0, str(ROOT))

from bench.experiments import control, control_sysid, forward_models  # noqa: E402
from gnwarp.eval.records import FORMAT, read_records, write_records  # noqa: E402
from gnwarp.eval.summarize import groups, summary_lines, write_summary  # noqa: E402

CONTROL = ROOT / "bench" / "results" / "control"
ROW_FILES = ["results.jsonl", "throughput.jsonl", "cpu_timing.jsonl", "swimmer_iterations.jsonl",
             "fig11/results.jsonl", "iterations/results.jsonl"]
# column label at BASE -> regenerated column name
COLUMNS = {"GN-MPC (learned)": "gradient (learned)", "iLQG (true, MuJoCo C)": "ilqg (true, MuJoCo C)",
           "sampling (true)": "sampling (true, MuJoCo-Warp)", "sampling (learned)": "sampling (learned)",
           "random": "random (no model)", "GN-MPC, no params": "gradient (learned, no_params)",
           "GN-MPC, true params": "gradient (learned, true_params)", "GN-MPC, system ID": "gradient (learned, sysid)"}
RATIO_COLUMNS = ("GN-MPC / iLQG", "sysid / true params")


def gradient_variant(row: dict) -> str:
    """"" for GN-MPC at the main table's 5 iterations per step and lr 0.1, else its settings."""
    m = re.match(r"(\d+) Adam steps/step \+ (\d+) at the first state, lr ([\d.]+)", row.get("note", ""))
    if row["planner"] != "gn_mpc" or not m or (m.group(1) == "5" and m.group(3) == "0.1"):
        return ""
    return f"{m.group(1)} iterations, lr {m.group(3)}"


def convert(path: Path) -> bool:
    """Rewrite one row file as records; False when it already is in the record format."""
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if rows and rows[0].get("format") == FORMAT:
        return False
    if path.parent.name == "fig10":
        recs = [control_sysid.to_record(r) for r in rows]
    else:
        recs = [control.to_record(r, experiment="control" + ("" if path.parent == CONTROL else f"/{path.parent.name}"),
                                  variant=gradient_variant(r)) for r in rows]
    write_records(path, recs, append=False)
    back = read_records(path)
    for r, rec in zip(rows, back):  # the numbers as they were
        if "returns" in r:
            assert rec.returns == [float(x) for x in r["returns"]], path
        else:
            assert rec.reported == {"mean": r["return_mean"], "std": r["return_std"]}, path
    return True


def table(lines: list[str]) -> tuple[list[str], list[list[str]]]:
    """The first markdown table of ``lines``: its header cells and rows of cells."""
    start = next(i for i, line in enumerate(lines) if line.startswith("| "))
    rows = []
    for line in lines[start:]:
        if not line.startswith("|"):
            break
        rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows[0], [r for r in rows[2:]]


def compare(base_md: str, new_lines: list[str]) -> list[str]:
    """Differences between the first table of the summary at BASE and the regenerated mean +- std table."""
    head, rows = table(base_md.splitlines())
    i = next(k for k, line in enumerate(new_lines) if line.startswith("Mean +- std over episodes"))
    nhead, nrows = table(new_lines[i:])
    problems = []
    if len(rows) != len(nrows):
        return [f"{len(rows)} rows before, {len(nrows)} regenerated"]
    for base, new in zip(rows, nrows):
        for label, cell in zip(head[1:], base[1:]):
            if label in RATIO_COLUMNS:
                got, cell = new[-1], re.sub(r" \(goal (met|missed)\)", "", cell)
            elif label in COLUMNS:
                got = new[nhead.index(COLUMNS[label])] if COLUMNS[label] in nhead else "-"
            else:
                continue
            if got != cell:
                problems.append(f"{base[0]} / {label}: {cell} before, {got} regenerated")
    return problems


FORWARD = ROOT / "bench" / "results" / "forward_models"


def convert_forward_models() -> list[str]:
    """``forward_models/<system>/results.json`` as ``forward_models/results.jsonl`` records (their
    summary.md regenerated); the differences from the errors of the summary at ``BASE``."""
    base = subprocess.run(["git", "show", f"{BASE}:{(FORWARD / 'summary.md').relative_to(ROOT)}"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.splitlines()
    title = base[0][2:]
    gpu = title[title.index("(") + 1:title.index(")")]
    head, rows = table(base)
    records = []
    for row in rows:
        s = json.loads((FORWARD / row[0] / "results.json").read_text())
        records += forward_models.to_records(s, gpu=gpu)
    write_records(FORWARD / "results.jsonl", records, append=False)
    by = {(r.task, r.variant, r.episode_steps): r.reported["mean"] for r in read_records(FORWARD / "results.jsonl")}
    problems = []
    for row in rows:
        mlp = next(r.variant for r in records if r.task == row[0] and r.variant != "GN")
        for label, cell in zip(head, row):
            m = re.match(r"(GN|MLP) (one|20|100)-step$", label)
            if not m:
                continue
            model = "GN" if m.group(1) == "GN" else mlp
            steps = {"one": 1, "20": 20, "100": 100}[m.group(2)]
            got = f"{by[row[0], model, steps]:.3g}"
            if got != cell:
                problems.append(f"forward_models: {row[0]} / {label}: {cell} before, {got} from the records")
    write_summary(records, FORWARD, title)
    return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check-only", action="store_true", help="convert nothing, write nothing: only compare")
    args = ap.parse_args()
    if not args.check_only:
        for name in ROW_FILES + ["fig10/results.jsonl"]:
            print(f"{name}: {'converted' if convert(CONTROL / name) else 'already records'}")
    bad = []
    for sub, title, ratio in [("", None, control.RATIO), ("fig10", None, control_sysid.RATIO),
                              ("fig11", None, control.RATIO)]:
        out = CONTROL / sub
        base = subprocess.run(["git", "show", f"{BASE}:{(out / 'summary.md').relative_to(ROOT)}"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout
        title = base.splitlines()[0][2:]
        recs = read_records(out / "results.jsonl")
        problems = compare(base, summary_lines(groups(recs), title, ratio))
        bad += [f"{sub or 'control'}: {p}" for p in problems]
        print(f"{sub or 'control'}: {len(problems)} differences")
        if not args.check_only:
            write_summary(recs, out, title, ratio_of=ratio)
    if not args.check_only:
        problems = convert_forward_models()
        print(f"forward_models: {len(problems)} differences")
        bad += problems
    for line in bad:
        print(line)
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
