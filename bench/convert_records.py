"""One-time conversion of the experiments' committed results to results records, and the check
that the summaries regenerated from them show the same numbers.

    PYTHONPATH=. python3 bench/convert_records.py [--check-only] [--only control sysid_figures ...]

Rewrites, in place, ``bench/results/control/{results,throughput,cpu_timing,swimmer_iterations}.jsonl``
and ``{fig10,fig11,iterations}/results.jsonl`` as ``gnwarp.eval.records`` lines, regenerates the
``summary.md`` of ``control``, ``fig10`` and ``fig11`` with ``gnwarp.eval.summarize``, and compares
each mean +- std cell and ratio of the first table of the summary at commit e848b55 (the row
format's last) with the regenerated one. Then, for each experiment of ``CONVERSIONS``, writes its
records from the committed results (forward_models, sysid_figures and every labelled run folder
under it, multi_system, ablation_h2, budget_retrain, speed_accuracy, mlp_sweep, recurrent_jaco,
sysid_sensitivity; every number unchanged, a file already in the record format left alone),
regenerates its summary and compares each number of its summary before (at e848b55 or
``SYSID_BASE``) with the records. Last ("provenance"), the seeds and commits that the raw results
or their notes name are written into the records (``fill_provenance``). Exit 1 on a difference.
Running it again changes nothing.
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

from bench.experiments import (ablation_h2, budget_retrain, control, control_sysid, forward_models,  # noqa: E402
                               mlp_sweep, multi_system, recurrent_jaco, speed_accuracy, sysid_figures,
                               sysid_sensitivity)
from gnwarp.eval.records import FORMAT, read_records, write_records  # noqa: E402
from gnwarp.eval.summarize import groups, summary_lines, write_summary  # noqa: E402

CONTROL = ROOT / "bench" / "results" / "control"
ROW_FILES = ["results.jsonl", "throughput.jsonl", "cpu_timing.jsonl", "swimmer_iterations.jsonl",
             "fig11/results.jsonl", "iterations/results.jsonl"]
# old column label -> regenerated column name
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


def compare(old_md: str, new_lines: list[str]) -> list[str]:
    """Differences between the old summary's first table and the regenerated mean +- std table."""
    head, rows = table(old_md.splitlines())
    i = next(k for k, line in enumerate(new_lines) if line.startswith("Mean +- std over episodes"))
    nhead, nrows = table(new_lines[i:])
    problems = []
    if len(rows) != len(nrows):
        return [f"{len(rows)} rows before, {len(nrows)} regenerated"]
    for old, new in zip(rows, nrows):
        for label, cell in zip(head[1:], old[1:]):
            if label in RATIO_COLUMNS:
                got, cell = new[-1], re.sub(r" \(goal (met|missed)\)", "", cell)
            elif label in COLUMNS:
                got = new[nhead.index(COLUMNS[label])] if COLUMNS[label] in nhead else "-"
            else:
                continue
            if got != cell:
                problems.append(f"{old[0]} / {label}: {cell} before, {got} regenerated")
    return problems


FORWARD = ROOT / "bench" / "results" / "forward_models"


def convert_forward_models() -> list[str]:
    """``forward_models/<system>/results.json`` as ``forward_models/results.jsonl`` records (their
    summary.md regenerated); the differences from the errors of the summary at ``BASE``."""
    old = subprocess.run(["git", "show", f"{BASE}:{(FORWARD / 'summary.md').relative_to(ROOT)}"], cwd=ROOT,
                         capture_output=True, text=True, check=True).stdout.splitlines()
    title = old[0][2:]
    gpu = title[title.index("(") + 1:title.index(")")]
    head, rows = table(old)
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


SYSID = ROOT / "bench" / "results" / "sysid_figures"
SYSID_BASE = "3c77a89"  # the commit whose sysid_figures summaries (written from rows) are compared with


def old_text(path: Path, commit: str) -> str:
    """``path`` as committed at ``commit``."""
    return subprocess.run(["git", "show", f"{commit}:{path.relative_to(ROOT)}"], cwd=ROOT, capture_output=True,
                          text=True, check=True).stdout


def sections(md: str) -> dict[str, tuple[list[str], list[list[str]]]]:
    """The tables of a markdown file by the heading (or paragraph) above them: {title: (header, rows)}."""
    lines, out, title = md.splitlines(), {}, ""
    i = 0
    while i < len(lines):
        if lines[i].startswith("|"):
            head, rows = table(lines[i:])
            out[title] = (head, rows)
            i += len(rows) + 2
            continue
        if lines[i].strip():
            title = lines[i]
        i += 1
    return out


def convert_sysid_figures() -> list[str]:
    """Every ``sysid_figures/**/results.jsonl`` of rows as ``records.jsonl`` beside it (its error rows;
    the rows' other keys in their config); the ``summary.md`` of the folders that have one regenerated
    from the records and ``probe.md`` from the rows. Returns the differences between each number of the
    summary at ``SYSID_BASE`` (Figure 8, ratios, Figure 9, training, probe) and the regenerated ones."""
    problems = []
    for path in sorted(SYSID.rglob("results.jsonl")):
        rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
        if not rows or "part" not in rows[0]:
            continue                      # sysid_sensitivity's rows
        records = sysid_figures.to_records(rows)
        write_records(path.parent / "records.jsonl", records, append=False)
        records = read_records(path.parent / "records.jsonl")
        assert len(records) == sum({"fig8": 1, "oracle": 1, "fig9": 2}.get(r["part"], 0) for r in rows), path
        summary = path.parent / "summary.md"
        if not summary.exists():
            continue
        where = str(path.parent.relative_to(ROOT))
        old = sections(old_text(summary, SYSID_BASE))
        gs = {(g.task, g.variant): g for g in groups(records)}
        mean = {k: g.mean for k, g in gs.items()}
        last = {k: g.records[-1] for k, g in gs.items()}

        def check(what, cell, value):
            got = sysid_figures._g(value) if not isinstance(value, str) else value
            if got != cell:
                problems.append(f"{where}: {what}: {cell} before, {got} regenerated")

        head, rows8 = old["## Figure 8"]
        for row in rows8:
            s = row[0]
            v = {k: mean.get((s, k)) for k in sysid_figures.MODELS}
            for k in sysid_figures.MODELS:
                check(f"{s} / {k}", row[head.index(k)], v[k])
            check(f"{s} / sysid / true", row[head.index("sysid / true")], v["sysid same"] / v["true params"])
            check(f"{s} / sysid / no params", row[head.index("sysid / no params")], v["sysid same"] / v["no params"])
        key9 = next(k for k in old if k.startswith("50 sequences") or "sequences per length" in k)
        head, rows9 = old[key9]
        for row in rows9:
            task = f"pendulum length x{row[0]}, {row[1]}"
            check(f"{task} / sysid", row[2], mean.get((task, "sysid same")))
            check(f"{task} / true params", row[3], mean.get((task, "true params")))
        head, rowst = old["Training (each model capped at the same steps and wall clock):"]
        for row in rowst:
            variant = "sysid same" if row[1] == "sysid" else row[1]
            m = last[row[0], variant].metrics
            check(f"{row[0]} / {row[1]} training steps", row[2], str(m["train_steps"]))
            check(f"{row[0]} / {row[1]} training seconds", row[3], str(m["train_seconds"]))
        write_summary_sysid = sysid_figures.write_summary(path.parent, records)
        sysid_figures.write_probe(path.parent, sysid_figures.latest([json.loads(line) for line in
                                                                      path.read_text().splitlines() if line.strip()]))
        probe_old = [r for k, (h, rs) in old.items() if k.startswith("Least squares") for r in rs]
        probe_new = [r for k, (h, rs) in sections((path.parent / "probe.md").read_text()).items()
                     if k.startswith("Least squares") for r in rs]
        if probe_old != probe_new:
            problems.append(f"{where}: the probe table differs from the summary's")
        print(f"{where}: {len(records)} records; {write_summary_sysid.name} and probe.md regenerated")
    return problems


MULTI = ROOT / "bench" / "results" / "multi_system"


def convert_multi_system() -> list[str]:
    """``multi_system/<run>/results.json`` as ``results.jsonl`` records, for the folder's three runs and
    for ``swimmerN_captured/``; their ``summary.md`` regenerated. Returns the differences between
    each number of the summaries at ``SYSID_BASE`` (steps, one-, 20- and 100-step errors) and the
    records."""
    problems = []
    for folder, runs in ((MULTI, ["multi4", "multi5", "swimmerN"]), (MULTI / "swimmerN_captured", [None])):
        old = old_text(folder / "summary.md", SYSID_BASE)
        title = re.sub(r", [a-z]+ \d+\)$", ")", old.splitlines()[0][2:])   # without the old title's run label
        m = re.search(r"Data: (\d+)/(\d+)/(\d+) sequences x (\d+) steps per trained system", old)
        seqs, steps = [int(m.group(i)) for i in (1, 2, 3)], int(m.group(4))
        seconds = float(re.search(r"capped at ([\d.]+) s of training", old).group(1))
        records = []
        for run in runs:
            s = json.loads(((folder / run if run else folder) / "results.json").read_text())
            records += multi_system.to_records(s, env_steps=seqs[0] * steps * len(s["train_systems"]), gpu=title[
                title.rindex("(") + 1:].split(",")[0].rstrip(")"), config={"sequences": seqs, "sequence_steps": steps,
                                                                           "seconds": seconds, "gn": [128, 256, 128]})
        write_records(folder / "results.jsonl", records, append=False)
        records = read_records(folder / "results.jsonl")
        by = {(r.variant, r.task, r.episode_steps): r for r in records}
        head, rows = table(old.splitlines())
        for row in rows:
            run, name = row[0], row[2]
            for col, horizon in (("one-step", 1), ("20-step", 20), ("100-step", 100)):
                got = f"{by[run, name, horizon].reported['mean']:.3g}"
                if got != row[head.index(col)]:
                    problems.append(f"multi_system {folder.name}: {run} / {name} / {col}: {row[head.index(col)]} "
                                    f"before, {got} from the records")
            r1 = by[run, name, 1]
            for col, got in (("steps", str(r1.metrics["train_steps"])),
                             ("seen in training", "yes" if r1.metrics["seen_in_training"] else "no")):
                if got != row[head.index(col)]:
                    problems.append(f"multi_system {folder.name}: {run} / {name} / {col}: {row[head.index(col)]} "
                                    f"before, {got} from the records")
        write_summary(records, folder, title)
        print(f"{folder.relative_to(ROOT)}: {len(records)} records; summary.md regenerated")
    return problems


ABLATION = ROOT / "bench" / "results" / "ablation_h2"


def convert_ablation_h2() -> list[str]:
    """``ablation_h2/results.jsonl``'s rows (one per variant and seed) as records in place, its
    ``summary.md`` regenerated. Returns the differences between each number of the summary at
    ``SYSID_BASE`` (seeds, parameters, 20-step mean and std, one-step mean) and the regenerated
    groups; "seconds per run" (a mean over seeds) is not regenerated."""
    path = ABLATION / "results.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if rows and rows[0].get("format") != FORMAT:
        for r in rows:   # every committed run: 2000 training sequences of 100 steps, 200 test sequences
            r.setdefault("test_sequences", 200)
            r.setdefault("env_steps", 2000 * 100)
        write_records(path, [x for r in rows for x in ablation_h2.to_records(r)], append=False)
    records = read_records(path)
    gs = {(g.variant, g.episode_steps): g for g in groups(records)}
    old = old_text(ABLATION / "summary.md", SYSID_BASE)
    head, table_rows = table(old.splitlines())
    problems = []
    for row in table_rows:
        g20, g1 = gs[row[0], 20], gs[row[0], 1]
        for col, got in (("seeds", str(g20.n)), ("parameters", str(g20.records[-1].metrics["parameters"])),
                         ("20-step error mean", f"{g20.mean:.3g}"), ("std", f"{g20.std:.2g}"),
                         ("one-step mean", f"{g1.mean:.3g}")):
            if got != row[head.index(col)]:
                problems.append(f"ablation_h2: {row[0]} / {col}: {row[head.index(col)]} before, {got} regenerated")
    ablation_h2.summarize(ABLATION)
    return problems


BUDGET = ROOT / "bench" / "results" / "budget_retrain"


def convert_budget_retrain() -> list[str]:
    """``budget_retrain/results.jsonl``'s rows (one per system, with the forward-model table's numbers
    as ``before``) as records in place, its ``summary.md`` regenerated. Returns the differences
    between each number of the summary at ``SYSID_BASE`` (steps and errors, before and after) and
    the records."""
    path = BUDGET / "results.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    if rows and rows[0].get("format") != FORMAT:
        for r in rows:   # every committed run: 2000 training sequences of 100 steps, 200 test sequences
            r.setdefault("test_sequences", 200)
            r.setdefault("env_steps", 2000 * 100)
        write_records(path, [x for r in rows for x in budget_retrain.to_records(r)], append=False)
    by = {(r.task, r.variant, r.episode_steps): r for r in read_records(path)}
    head, table_rows = table(old_text(BUDGET / "summary.md", SYSID_BASE).splitlines())
    problems = []

    def g2(x):
        return f"{x:.2g}"
    for row in table_rows:
        s = row[0]
        cells = [("steps before", str(by[s, "eager loop", 1].metrics["train_steps"])),
                 ("steps after", str(by[s, "captured loop", 1].metrics["train_steps"]))]
        for i, h in ((4, 1), (6, 20), (8, 100)):
            cells += [(head[i], g2(by[s, "eager loop", h].reported["mean"])),
                      (f"{head[i]} after", g2(by[s, "captured loop", h].reported["mean"]))]
        got = [c for _, c in cells]
        want = [row[1], row[2], row[4], row[5], row[6], row[7], row[8], row[9]]
        for (what, g), w in zip(cells, want):
            if g != w:
                problems.append(f"budget_retrain: {s} / {what}: {w} before, {g} from the records")
        assert len(got) == len(want)
    budget_retrain.report(BUDGET)
    return problems


SPEED = ROOT / "bench" / "results" / "speed_accuracy"


def convert_speed_accuracy() -> list[str]:
    """``speed_accuracy/rows.json`` as ``results.jsonl`` records (``rows.json`` removed), its
    ``summary.md`` regenerated. Returns the differences between each number of the summary at
    ``SYSID_BASE`` (error, ms per step, graph-steps/s, MuJoCo-Warp ms per step) and the records."""
    rows_path = SPEED / "rows.json"
    old = old_text(SPEED / "summary.md", SYSID_BASE)
    if rows_path.exists():
        gpu = old.splitlines()[0][old.index("(") + 1:-1] if "(" in old.splitlines()[0] else "unknown"
        records = [x for r in json.loads(rows_path.read_text()) if "error" not in r
                   for x in speed_accuracy.to_records(r, gpu=gpu, test_sequences=200, env_steps=2000 * 100,
                                                      config={"seconds": 150.0, "sequences": [2000, 50, 200],
                                                              "sequence_steps": 100})]
        write_records(SPEED / "results.jsonl", records, append=False)
        rows_path.unlink()
    by = {(r.task, r.variant): r for r in read_records(SPEED / "results.jsonl")}
    head, rows = table(old.splitlines())
    problems = []
    for row in rows:
        r = by[row[0], f"{row[1]}, {row[2]}"]
        m = r.metrics
        for what, got, want in ((head[3], f"{r.reported['mean']:.3g}", row[3]),
                                ("ms per step", f"{m['ms_per_step']:.3f}", row[4]),
                                ("graph-steps/s", f"{m['graph_steps_per_s']:.3g}", row[5]),
                                ("mode", r.config["mode"], row[6]),
                                ("MuJoCo-Warp ms per step", f"{m['mjwarp_ms_per_step']:.3f}", row[7])):
            if got != want:
                problems.append(f"speed_accuracy: {row[0]} / {row[1]} / {row[2]} / {what}: {want} before, {got} "
                                "from the records")
    if len(rows) != len(by):
        problems.append(f"speed_accuracy: {len(rows)} rows before, {len(by)} records")
    speed_accuracy.report(SPEED)
    return problems


MLP = ROOT / "bench" / "results" / "mlp_sweep"


def convert_mlp_sweep() -> list[str]:
    """``mlp_sweep/<system>[/<size>]/results.json`` and the forward models' GN as
    ``mlp_sweep/results.jsonl`` records, its ``summary.md`` regenerated. Returns the differences
    between each number of the summary at ``SYSID_BASE`` (GN steps, GN and MLP 20-step errors) and
    the records."""
    old = old_text(MLP / "summary.md", SYSID_BASE)
    first = old.splitlines()[0]
    gpu = first[first.rindex("(") + 1:-1]
    head, rows = table(old.splitlines())
    records = []
    for row in rows:
        s = row[0].split(" ")[0]
        gn = json.loads((FORWARD / s / "results.json").read_text())
        records += mlp_sweep.to_records(s, gn, mlp_sweep.collect(MLP, s), gpu=gpu)
    write_records(MLP / "results.jsonl", records, append=False)
    by = {(r.task, r.variant, r.episode_steps): r for r in read_records(MLP / "results.jsonl")}
    problems = []
    for row in rows:
        s = row[0].split(" ")[0]
        cells = [(row[0], f"{s} ({by[s, 'GN', 20].metrics['train_steps']})"), (row[1], f"{by[s, 'GN', 20].reported['mean']:.3g}")]
        cells += [(row[head.index(size)], f"{by[s, f'MLP {size}', 20].reported['mean']:.3g}")
                  for size in head[2:7]]
        problems += [f"mlp_sweep: {s}: {want} before, {got} from the records" for want, got in cells if want != got]
    write_summary(records, MLP, "MLP baseline sweep (section E) beside the GN of bench/experiments/forward_models.py "
                  f"({gpu})")
    return problems


RECURRENT = ROOT / "bench" / "results" / "recurrent_jaco"


def convert_recurrent_jaco() -> list[str]:
    """``recurrent_jaco/results.json`` as ``results.jsonl`` records, ``summary.md`` generated from them
    in place of ``results.md``. Returns the differences between each number of ``results.md`` at
    ``SYSID_BASE`` (angle and velocity errors per horizon) and the records."""
    from gnwarp.data import proprio
    res = json.loads((RECURRENT / "results.json").read_text())
    system = proprio.proprio_jaco(res["meta"]["lag"], res["meta"]["servo_scale"])
    records = recurrent_jaco.to_records(res, system, gpu="NVIDIA H200")   # the run's GPU (README.md)
    write_records(RECURRENT / "results.jsonl", records, append=False)
    by = {(r.variant, r.episode_steps): r for r in read_records(RECURRENT / "results.jsonl")}
    head, rows = table(old_text(RECURRENT / "results.md", SYSID_BASE).splitlines())
    problems = []
    for row in rows:
        for col, cell in zip(head[1:], row[1:]):
            q, h = col.split(" h=")
            label = recurrent_jaco.QUANTITIES["angle" if q == "angle" else "velocity"]
            got = f"{by[f'{row[0]}, {label}', int(h)].reported['mean']:.3g}"
            if got != cell:
                problems.append(f"recurrent_jaco: {row[0]} / {col}: {cell} before, {got} from the records")
    (RECURRENT / "results.md").unlink(missing_ok=True)
    recurrent_jaco.report(RECURRENT, records)
    return problems


SENSITIVITY = ROOT / "bench" / "results" / "sysid_figures" / "sensitivity"


def convert_sysid_sensitivity() -> list[str]:
    """``sysid_figures/sensitivity/results.jsonl``'s rows as records in place (seed 0, the script's
    default, and the run's date), its ``summary.md`` regenerated. Returns the differences between
    each error of the summary at ``SYSID_BASE`` and the records."""
    path = SENSITIVITY / "results.jsonl"
    rows = [json.loads(line) for line in path.read_text().splitlines() if line.strip()]
    old = old_text(SENSITIVITY / "summary.md", SYSID_BASE)
    if rows and rows[0].get("format") != FORMAT:
        date = re.search(r"\((\d{4}-\d\d-\d\d);", old).group(1)
        write_records(path, [sysid_sensitivity.to_record({**r, "date": date}, seed=0) for r in rows], append=False)
    by = {(r.task, r.variant): r for r in read_records(path)}
    head, rows = table(old.splitlines())
    problems = []
    for row in rows:
        for col, cell in zip(head[2:], row[2:]):
            got = f"{by[f'{row[0]}: {row[1]}', col].reported['mean']:.2g}"
            if got != cell:
                problems.append(f"sysid_sensitivity: {row[0]} / {row[1]} / {col}: {cell} before, {got} from the records")
    sysid_sensitivity.report(SENSITIVITY)
    return problems


# the experiments converted after the control ones: name -> conversion (returns the differences)
# commits the run notes name: (records file under sysid_figures, config key, value) -> commit
NOTED_COMMITS = {("pool/records.jsonl", "run", "pool-"): "acb6f08",           # pool/NOTES.md: its code
                 ("nominal_static/records.jsonl", "gpu_command", "e"): "c331ccf",  # "GPU command e, commit c331ccf"
                 ("options/records.jsonl", "run", "unroll-"): "d75ad35"}       # "unroll=U existed at commit d75ad35"


def fill_provenance() -> list[str]:
    """Seeds and commits that the raw results or their notes name, written into the converted
    records in place (run after the conversions, which leave them "unknown" / null):
    forward_models' runs (and the same GN runs in mlp_sweep and budget_retrain's "eager loop") take
    the seed of their ``<system>/results.json`` config; sysid_figures' records their run's seed
    (``sysid_figures.to_records``: the row's or the "s<K>-" label's) and the commits of
    ``NOTED_COMMITS``. Every number unchanged; returns the records whose values changed (none)."""
    seeds = {p.parent.name: json.loads(p.read_text())["config"].get("seed") for p in FORWARD.glob("*/results.json")}

    def fill(path, change):
        recs = read_records(path)
        before = [(r.key, r.episode_steps, r.values, r.reported) for r in recs]
        for r in recs:
            change(r)
        write_records(path, recs, append=False)
        return [f"{path}: {a[0]} changed" for a, b in zip(before, [(r.key, r.episode_steps, r.values, r.reported)
                                                                    for r in read_records(path)]) if a != b]
    problems = []

    def gn_seed(variants=None):   # None: every variant (the run's GN and MLP)
        def change(r):
            if r.seed is None and (variants is None or r.variant in variants) and seeds.get(r.task) is not None:
                r.seed = int(seeds[r.task])
        return change
    problems += fill(FORWARD / "results.jsonl", gn_seed())
    problems += fill(ROOT / "bench" / "results" / "mlp_sweep" / "results.jsonl", gn_seed({"GN"}))
    problems += fill(BUDGET / "results.jsonl", gn_seed({"eager loop"}))
    for path in sorted(SYSID.glob("**/records.jsonl")):
        rel = path.relative_to(SYSID).as_posix()

        def change(r, rel=rel):
            run = str(r.config.get("run") or "")
            if r.seed is None and isinstance(r.config.get("seed"), int):
                r.seed = r.config["seed"]
            if r.seed is None and re.match(r"s\d+-", run):
                r.seed = int(re.match(r"s(\d+)-", run).group(1))
            for (where, key, value), commit in NOTED_COMMITS.items():
                if rel == where and str(r.config.get(key, "")).startswith(value) and r.commit == "unknown":
                    r.commit = commit
        problems += fill(path, change)
    return problems


CONVERSIONS = {"forward_models": convert_forward_models, "sysid_figures": convert_sysid_figures,
               "multi_system": convert_multi_system, "ablation_h2": convert_ablation_h2,
               "budget_retrain": convert_budget_retrain, "speed_accuracy": convert_speed_accuracy,
               "mlp_sweep": convert_mlp_sweep, "recurrent_jaco": convert_recurrent_jaco,
               "sysid_sensitivity": convert_sysid_sensitivity, "provenance": fill_provenance}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--check-only", action="store_true", help="convert nothing, write nothing: only compare "
                    "the control summaries")
    ap.add_argument("--only", nargs="+", choices=["control", *CONVERSIONS], default=None,
                    help="convert and check only these experiments (default: all)")
    args = ap.parse_args()
    only = set(args.only or ["control", *CONVERSIONS])
    bad = []
    if "control" in only:
        if not args.check_only:
            for name in ROW_FILES + ["fig10/results.jsonl"]:
                print(f"{name}: {'converted' if convert(CONTROL / name) else 'already records'}")
        for sub, title, ratio in [("", None, control.RATIO), ("fig10", None, control_sysid.RATIO),
                                  ("fig11", None, control.RATIO)]:
            out = CONTROL / sub
            old = old_text(out / "summary.md", BASE)
            title = old.splitlines()[0][2:]
            recs = read_records(out / "results.jsonl")
            problems = compare(old, summary_lines(groups(recs), title, ratio))
            bad += [f"{sub or 'control'}: {p}" for p in problems]
            print(f"{sub or 'control'}: {len(problems)} differences")
            if not args.check_only:
                write_summary(recs, out, title, ratio_of=ratio)
    if not args.check_only:
        for name, conversion in CONVERSIONS.items():
            if name in only:
                problems = conversion()
                print(f"{name}: {len(problems)} differences")
                bad += problems
    for line in bad:
        print(line)
    return 1 if bad else 0

if __name__ == "__main__":
    sys.exit(main())
