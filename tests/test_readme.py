"""Every ```python and ```bash block of README.md and docs/*.md runs as written on a CPU (blocks
marked ``<!-- no-run: why -->`` on the line before are skipped), and README.md stays short."""
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^(?P<ind>[ ]*)```(?P<lang>\w*)[ ]*$")


def code_blocks(path: Path) -> list[tuple[int, str, str, bool]]:
    """(line, language, code, run) of every fenced block; run is False after a no-run comment."""
    lines = path.read_text().split("\n")
    blocks, i = [], 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if not m:
            i += 1
            continue
        ind, start = len(m["ind"]), i
        j = i + 1
        while not (FENCE.match(lines[j]) and FENCE.match(lines[j])["lang"] == ""):
            j += 1
        prev = next((lines[k].strip() for k in range(start - 1, -1, -1) if lines[k].strip()), "")
        code = "\n".join(line[ind:] for line in lines[start + 1:j])
        blocks.append((start + 1, m["lang"], code, not prev.startswith("<!-- no-run:")))
        i = j + 1
    return blocks


def _env(bin_dir: Path) -> dict:
    """``gnwarp`` on PATH runs this checkout's CLI; no GPU is used."""
    bin_dir.mkdir(exist_ok=True)
    shim = bin_dir / "gnwarp"
    shim.write_text(f'#!/bin/sh\nexec "{sys.executable}" -m gnwarp.cli "$@"\n')
    shim.chmod(0o755)
    env = dict(os.environ, PATH=f"{bin_dir}{os.pathsep}{os.environ['PATH']}", CUDA_VISIBLE_DEVICES="")
    env["PYTHONPATH"] = os.pathsep.join([str(ROOT), env.get("PYTHONPATH", "")]).rstrip(os.pathsep)
    return env


def test_readme_is_at_most_300_lines():
    n = len((ROOT / "README.md").read_text().splitlines())
    assert n <= 300, f"README.md has {n} lines (at most 300: tables belong in bench/results/*/README.md)"


def test_blocks_are_found_and_few_are_skipped():
    blocks = [b for p in DOCS for b in code_blocks(p) if b[1] in ("python", "bash")]
    skipped = [b for b in blocks if not b[3]]
    assert len(blocks) >= 15 and len(skipped) <= 8, (len(blocks), len(skipped))
    readme = code_blocks(ROOT / "README.md")
    first_cli = next(line for line, lang, code, run in readme if lang == "bash" and run and "gnwarp " in code)
    assert first_cli <= 60, f"the quick start's command line starts at line {first_cli} (at most 60)"
    assert all(".cuda()" not in code and "[--" not in code for p in DOCS for _, _, code, _ in code_blocks(p))


@pytest.mark.parametrize("path", DOCS, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_code_blocks_run(path, tmp_path):
    """A file's blocks run in order in one folder; its Python blocks share one namespace."""
    env = _env(tmp_path / "bin")
    work = tmp_path / "work"
    work.mkdir()
    namespace = {"__name__": "__main__"}
    old = os.getcwd()
    os.chdir(work)
    try:
        for line, lang, code, run in code_blocks(path):
            if not run or lang not in ("python", "bash"):
                continue
            where = f"{path.name}:{line}"
            if lang == "bash":
                r = subprocess.run(["bash", "-euo", "pipefail", "-c", code], cwd=work, env=env,
                                   capture_output=True, text=True, timeout=1800)
                assert r.returncode == 0, f"{where} exited {r.returncode}:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
            else:
                exec(compile(code, where, "exec"), namespace)
    finally:
        os.chdir(old)


PATH_RE = re.compile(r"`((?:gnwarp/|kernels/|bench/|tests/|examples/)?[\w/]+\.py)`")
STAGE_DIRS = ("sim", "data", "gn", "models", "eval", "train", "control", "rl", "cli")
NAME_RE = re.compile(r"`(gnwarp(?:\.\w+)+)")
# the result folders' READMEs name scripts, modules and files too (their code blocks are not run)
NAMED = DOCS + sorted((ROOT / "bench" / "results").glob("*/README.md"))


def _source_path(rel: str) -> Path | None:
    """The file a path named in the docs means: rooted at the checkout, or a stage folder of gnwarp/."""
    if rel.split("/")[0] in STAGE_DIRS:
        return ROOT / "gnwarp" / rel
    if rel.split("/")[0] in ("gnwarp", "kernels", "bench", "tests", "examples"):
        return ROOT / rel
    return None


@pytest.mark.parametrize("path", NAMED, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_named_paths_exist(path):
    """Every source file the docs name (``gnwarp/x.py``, ``sim/env.py``, ``kernels/gn/mlp.py``) and
    every file or folder they link to exists."""
    text = path.read_text()
    named = {m for m in PATH_RE.findall(text) if "/" in m}
    assert named or path != ROOT / "README.md"
    missing = sorted(m for m in named if (p := _source_path(m)) is not None and not p.is_file())
    links = [m for m in re.findall(r"\]\(([^)#\s]+)", text) if "://" not in m]   # [text](relative link)
    missing += sorted(m for m in links if not (path.parent / m).exists())
    assert not missing, f"{path.name} names files that do not exist: {missing}"


@pytest.mark.parametrize("path", NAMED, ids=lambda p: p.relative_to(ROOT).as_posix())
def test_named_objects_exist(path):
    """Every dotted ``gnwarp.x.y`` the docs name imports (a module, or an attribute of one)."""
    import importlib
    missing = []
    for name in sorted(set(NAME_RE.findall(path.read_text()))):
        parts = name.split(".")
        obj, i = None, len(parts)
        while i > 0:   # the longest importable module prefix, then attributes
            try:
                obj = importlib.import_module(".".join(parts[:i]))
                break
            except ModuleNotFoundError:
                i -= 1
        for attr in parts[i:]:
            if not hasattr(obj, attr):
                missing.append(name)
                break
            obj = getattr(obj, attr)
    assert not missing, f"{path.name} names what gnwarp does not have: {missing}"


def test_architecture_table_names_every_module():
    """README's architecture table is the map: every module of gnwarp/ has its row (cli and demo
    are named as ``gnwarp.cli`` / ``gnwarp.demo``)."""
    text = (ROOT / "README.md").read_text()
    pkg = ROOT / "gnwarp"
    mods = [p.relative_to(pkg).as_posix() for p in sorted(pkg.glob("*.py")) + sorted(pkg.glob("*/*.py"))
            if p.name != "__init__.py" and p.parent.name != "kernels"]
    assert len(mods) > 50
    missing = [m for m in mods if f"`{m}`" not in text and f"`gnwarp/{m}`" not in text
               and f"gnwarp.{m.removesuffix('.py')}" not in text]
    assert not missing, f"README.md's architecture table lacks {missing}"
