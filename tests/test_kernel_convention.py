"""The parameter convention of the Warp kernels in ``kernels/`` (stated in ``kernels/__init__.py``).

Every ``@wp.kernel``, and every ``@wp.func`` that takes an array, module-level or built inside a
factory function, lists its parameters under section comments ``# Model:``, ``# Parameters:``,
``# Data in:`` or ``# Data out:`` (text in parentheses may follow the section's name). Arrays
under ``# Data in:`` end in ``_in``; everything under ``# Data out:`` ends in ``_out``; a
parameter the body writes (a subscript assignment, an atomic add, a tile store) is under
``# Data out:``. A kernel's outputs are its last parameters: ``gnwarp.interop.Launcher`` passes
the arguments from the first ``*_out`` on as ``outputs=``. Read with ``ast`` and the source lines
only: nothing is imported or compiled.
"""
import ast
import re
from pathlib import Path

import pytest

KERNELS = Path(__file__).resolve().parents[1] / "kernels"
SECTIONS = ("Model", "Parameters", "Data in", "Data out")
SECTION_RE = re.compile(r"^\s*#\s*(Model|Parameters|Data in|Data out)\s*(\(.*\))?\s*:\s*$")
# calls whose first argument is written
WRITERS = {"atomic_add", "atomic_sub", "atomic_min", "atomic_max", "tile_store", "tile_atomic_add",
           "tile_atomic_add_indexed"}
# (file relative to kernels/, function name, parameter): why it breaks the convention. Empty:
# every kernel follows it; add an entry only with a reason a reviewer would accept.
EXCEPTIONS: dict = {}


def _decorator_name(d) -> str:
    """``wp.kernel`` / ``wp.func`` for ``@wp.kernel``, ``@wp.kernel(...)``, ``@wp.func``."""
    if isinstance(d, ast.Call):
        d = d.func
    if isinstance(d, ast.Attribute) and isinstance(d.value, ast.Name):
        return f"{d.value.id}.{d.attr}"
    return ""


def _is_array(annotation) -> bool:
    """An annotation ``wp.array(...)``, ``wp.array2d(...)`` ... (``wp.array`` without a call too)."""
    node = annotation.func if isinstance(annotation, ast.Call) else annotation
    return isinstance(node, ast.Attribute) and node.attr.startswith("array")


def _written(fn: ast.FunctionDef) -> set:
    """Names of the parameters ``fn``'s body writes: ``x[...] = ``, ``x[...] += ``, and the first
    argument of an atomic add or a tile store."""
    out = set()
    for node in ast.walk(fn):
        targets = []
        if isinstance(node, ast.Assign):
            targets = node.targets
        elif isinstance(node, (ast.AugAssign, ast.AnnAssign)):
            targets = [node.target]
        for t in targets:
            if isinstance(t, ast.Subscript) and isinstance(t.value, ast.Name):
                out.add(t.value.id)
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute)
                and node.func.attr in WRITERS and node.args and isinstance(node.args[0], ast.Name)):
            out.add(node.args[0].id)
    return out


def _sections(fn: ast.FunctionDef, lines: list) -> dict:
    """{parameter: section} from the comments between the ``def`` line and each parameter;
    None for a parameter before any section comment."""
    section, line_no, found = None, fn.lineno, {}
    for arg in fn.args.args:
        for text in lines[line_no - 1:arg.lineno - 1]:
            m = SECTION_RE.match(text)
            if m:
                section = m.group(1)
            elif text.strip().startswith("#"):
                assert False, f"unknown section comment {text.strip()!r} in {fn.name}"
        line_no = arg.lineno
        found[arg.arg] = section
    return found


def _kernels():
    """(path relative to kernels/, function node, source lines) of every kernel and of every
    ``wp.func`` that takes an array."""
    for path in sorted(KERNELS.rglob("*.py")):
        text = path.read_text()
        lines = text.splitlines()
        for node in ast.walk(ast.parse(text)):
            if not isinstance(node, ast.FunctionDef):
                continue
            names = {_decorator_name(d) for d in node.decorator_list}
            if "wp.kernel" in names or ("wp.func" in names and any(
                    a.annotation is not None and _is_array(a.annotation) for a in node.args.args)):
                yield str(path.relative_to(KERNELS)), node, lines


def _violations(rel: str, fn: ast.FunctionDef, lines: list) -> list:
    problems = []
    sections = _sections(fn, lines)
    written = _written(fn)
    for arg in fn.args.args:
        name, section = arg.arg, sections[arg.arg]
        if (rel, fn.name, name) in EXCEPTIONS:
            continue
        where = f"{rel}:{fn.lineno} {fn.name}({name})"
        if section is None:
            problems.append(f"{where}: under no section comment ({', '.join(SECTIONS)})")
        elif section == "Data out" and not name.endswith("_out"):
            problems.append(f"{where}: an output not named *_out")
        elif section != "Data out" and name.endswith("_out"):
            problems.append(f"{where}: named *_out under '# {section}:'")
        elif section == "Data in" and arg.annotation is not None and _is_array(arg.annotation) \
                and not name.endswith("_in"):
            problems.append(f"{where}: an input array not named *_in")
        if name in written and section not in (None, "Data out"):
            problems.append(f"{where}: written by the body but under '# {section}:'")
    names = [a.arg for a in fn.args.args]
    outs = [i for i, n in enumerate(names) if n.endswith("_out")]
    if outs and not all(n.endswith("_out") for n in names[outs[0]:]):
        problems.append(f"{rel}:{fn.lineno} {fn.name}: an input after the first output {names[outs[0]]}")
    return problems


def test_kernels_are_found():
    """The scan sees the kernels (a broken scan would pass every check below vacuously)."""
    found = {(rel, fn.name) for rel, fn, _ in _kernels()}
    assert len(found) >= 25, sorted(found)
    assert ("gn/graph_ops.py", "concat") in found  # a factory-built kernel
    assert ("gn/graph_ops.py", "copy_piece") in found  # a factory-built wp.func with arrays
    assert ("sim/mujoco_warp.py", "record_body_state") in found  # a module-level kernel


def test_kernel_parameters_follow_the_convention():
    problems = [p for rel, fn, lines in _kernels() for p in _violations(rel, fn, lines)]
    assert not problems, "\n".join(problems)


def test_exceptions_are_used():
    """Every listed exception names a parameter that exists (no stale entries)."""
    params = {(rel, fn.name, a.arg) for rel, fn, _ in _kernels() for a in fn.args.args}
    assert not set(EXCEPTIONS) - params, sorted(set(EXCEPTIONS) - params)


@pytest.mark.parametrize("source, message", [
    ("@wp.kernel\ndef k(x: wp.array(dtype=float)):\n    x[0] = 1.0\n", "under no section"),
    ("@wp.kernel\ndef k(\n    # Data in:\n    x: wp.array(dtype=float),\n):\n    pass\n", "not named *_in"),
    ("@wp.kernel\ndef k(\n    # Data in:\n    x_in: wp.array(dtype=float),\n):\n    x_in[0] = 1.0\n",
     "written by the body"),
    ("@wp.kernel\ndef k(\n    # Data in:\n    x_in: wp.array(dtype=float),\n):\n"
     "    wp.atomic_add(x_in, 0, 1.0)\n", "written by the body"),
    ("@wp.kernel\ndef k(\n    # Data out:\n    y: wp.array(dtype=float),\n):\n    y[0] = 1.0\n", "not named *_out"),
    ("@wp.kernel\ndef k(\n    # Data out:\n    y_out: wp.array(dtype=float),\n    # Data in:\n    n: int,\n):\n"
     "    y_out[0] = 1.0\n", "an input after the first output"),
    ("@wp.kernel\ndef k(\n    # Data out:\n    y_out: wp.array(dtype=float),\n):\n    y_out[0] = 1.0\n", None),
])
def test_checker_catches_violations(source, message):
    """The checker flags each kind of break (and passes a kernel that follows the convention)."""
    fn = ast.parse(source).body[0]
    problems = _violations("x.py", fn, source.splitlines())
    if message is None:
        assert problems == []
    else:
        assert any(message in p for p in problems), problems
