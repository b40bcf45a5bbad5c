"""The layer order of DESIGN.md holds: every import in the package points downward.

The test reads the source with ``ast`` (nothing is imported), so a violation is found even in
a module no other test loads. A newcomer who adds a folder adds it to ``LAYERS``.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "bodyspace"

# Layer of each top-level part of the package (DESIGN.md, "Layers"). Parts on one layer may not
# import each other (semantics and mapping are siblings); within layer 13, cli sits on report,
# which sits on studies.
LAYERS = {
    "errors": 1, "atomic": 1, "parallel": 1, "units": 1, "validation": 1, "rowfile": 1, "distributions": 1,
    "mesh": 2,
    "encoding": 3,
    "shape": 4,
    "measure": 5,
    "data": 6,
    "rig": 7,
    "synth": 8,
    "semantics": 9, "mapping": 9,
    "motion": 10, "register": 10,
    "export": 11,
    "model": 12,
    "studies": 13.0, "report": 13.1, "cli": 13.2,
}
BASE = {"errors", "atomic", "parallel", "units", "validation", "rowfile", "distributions"}
# Entry points sit above everything.
EXEMPT = {"__init__", "__main__"}


def _part(module: str) -> str:
    """'bodyspace.mesh.io' -> 'mesh'; 'bodyspace.errors' -> 'errors'."""
    return module.split(".")[1]


def _module_name(path: Path) -> str:
    rel = path.relative_to(PACKAGE.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _imports(tree: ast.Module, module: str):
    """(line, imported module, inside a function?) for every bodyspace import."""
    package = module if module.count(".") == 0 else module.rsplit(".", 1)[0]
    out = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if isinstance(child, ast.Import):
                out.extend((child.lineno, a.name, in_function) for a in child.names if a.name.startswith("bodyspace"))
            elif isinstance(child, ast.ImportFrom):
                name = child.module or ""
                if child.level:
                    base = package.split(".")
                    name = ".".join(base[: len(base) - child.level + 1] + ([name] if name else []))
                if name.startswith("bodyspace"):
                    if name == "bodyspace":       # from bodyspace import x -> bodyspace.x, if x is a module
                        out.extend((child.lineno, f"bodyspace.{a.name}", in_function) for a in child.names
                                   if (PACKAGE / a.name).is_dir() or (PACKAGE / f"{a.name}.py").is_file())
                    else:
                        out.append((child.lineno, name, in_function))
            visit(child, inner)

    visit(tree, False)
    return out


def _sources():
    return sorted(p for p in PACKAGE.rglob("*.py") if "__pycache__" not in p.parts)


def test_every_part_has_a_layer():
    parts = {p.relative_to(PACKAGE).parts[0].removesuffix(".py") for p in _sources()}
    missing = sorted(parts - set(LAYERS) - EXEMPT)
    assert not missing, f"add these parts of the package to LAYERS (DESIGN.md): {missing}"


def test_imports_point_downward():
    bad = []
    for path in _sources():
        module = _module_name(path)
        if module.count(".") == 0 or path.stem in EXEMPT and path.parent == PACKAGE:
            continue
        src = _part(module)
        tree = ast.parse(path.read_text(), filename=str(path))
        for line, target, _ in _imports(tree, module):
            if target == "bodyspace":
                continue
            dst = _part(target)
            if dst == src or (src in BASE and dst in BASE):
                continue
            if dst in EXEMPT or LAYERS.get(dst, 99) >= LAYERS.get(src, 0):
                bad.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {src} (layer {LAYERS.get(src)}) "
                           f"imports {target} (layer {LAYERS.get(dst)})")
    assert not bad, "imports against the layer order of DESIGN.md:\n" + "\n".join(bad)


def test_imports_stand_at_the_top():
    """Library code imports at the top of the file; a function may import only when its docstring
    says why (an optional heavy dependency), naming the word 'import'."""
    bad = []
    for path in _sources():
        tree = ast.parse(path.read_text(), filename=str(path))
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)):
                continue
            doc = (ast.get_docstring(fn) or "").lower()
            for node in ast.walk(fn):
                if isinstance(node, (ast.Import, ast.ImportFrom)) and "import" not in doc:
                    names = node.module if isinstance(node, ast.ImportFrom) else node.names[0].name
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: {fn.name}() imports {names}")
                    break
    assert not bad, "imports inside functions (move them to the top, or say why in the docstring):\n" + "\n".join(bad)


@pytest.mark.parametrize("source, target, ok", [
    ("bodyspace.mapping.forest", "bodyspace.mesh.io", True),
    ("bodyspace.mesh.io", "bodyspace.mapping.forest", False),
    ("bodyspace.semantics.morph", "bodyspace.mapping.refine", False),
    ("bodyspace.cli.build", "bodyspace.report.render", True),
    ("bodyspace.report.render", "bodyspace.cli.common", False),
])
def test_the_rule_itself(source, target, ok):
    src, dst = _part(source), _part(target)
    assert (dst == src or LAYERS[dst] < LAYERS[src]) is ok


def test_no_private_name_crosses_a_module():
    """A name starting with ``_`` is private to its module: another module that needs it gets a
    public name (bodyspace.validation for the argument checks)."""
    bad = []
    for path in _sources():
        tree = ast.parse(path.read_text(), filename=str(path))
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom) and (node.level or (node.module or "").startswith("bodyspace")):
                private = [a.name for a in node.names if a.name.startswith("_") and not a.name.startswith("__")]
                if private:
                    bad.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno}: imports {private} "
                               f"from {node.module}")
    assert not bad, "private names imported across modules (make them public):\n" + "\n".join(bad)


BUILTIN_ERRORS = {"ValueError", "KeyError", "TypeError", "RuntimeError", "IndexError", "Exception"}


def test_every_error_is_a_bodyspace_error():
    """Library code raises the classes of errors.py (a user catches BodyspaceError), and defines
    error classes only there."""
    bad = []
    for path in _sources():
        tree = ast.parse(path.read_text(), filename=str(path))
        where = path.relative_to(PACKAGE.parent)
        for node in ast.walk(tree):
            if isinstance(node, ast.Raise) and node.exc is not None:
                exc = node.exc.func if isinstance(node.exc, ast.Call) else node.exc
                if isinstance(exc, ast.Name) and exc.id in BUILTIN_ERRORS:
                    bad.append(f"{where}:{node.lineno}: raises {exc.id}")
            if isinstance(node, ast.ClassDef) and path.name != "errors.py" and \
                    any(isinstance(b, ast.Name) and b.id.endswith(("Error", "Exception")) for b in node.bases):
                bad.append(f"{where}:{node.lineno}: defines {node.name} outside errors.py")
    assert not bad, "use (or add) a class of bodyspace/errors.py:\n" + "\n".join(bad)
