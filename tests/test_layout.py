"""The package's layout: one public `__init__`, private subpackages by concern, each stating in its
docstring what it may import; the imports in the source follow those statements (lazy imports
inside functions included), the stated direction has no cycle, no module imports itself back
through others, and no module is over 700 lines."""

import ast
import re
from pathlib import Path

import pytest

PKG = Path(__file__).resolve().parents[1] / "jaxoptics"
PARTS = sorted(p.name for p in PKG.iterdir() if p.is_dir() and p.name.startswith("_") and (p / "__init__.py").exists())
MAX_LINES = 700


def _module(path: Path) -> str:
    parts = path.relative_to(PKG.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


MODULES = {_module(p): p for p in sorted(PKG.rglob("*.py"))}


def _imports(name: str) -> set[str]:
    """Every jaxoptics module `name` imports, anywhere in its source (at the top, inside functions,
    under `TYPE_CHECKING`): `from a import b` counts as `a.b` where that is a module, else `a`."""
    path = MODULES[name]
    package = name if path.name == "__init__.py" else name.rpartition(".")[0]
    found = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            found |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - (node.level - 1)]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            for a in node.names:
                found.add(f"{mod}.{a.name}" if f"{mod}.{a.name}" in MODULES else mod)
    return {m for m in found if m == "jaxoptics" or m.startswith("jaxoptics.")}


def _part(module: str) -> str:
    """The concern a module belongs to: its subpackage (`_films`, ..., `tools`), or the module
    itself at the top (`jaxoptics`, `jaxoptics.__main__`)."""
    parts = module.split(".")
    return parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in PARTS + ["tools"]) else module


def _allowed(part: str) -> set[str]:
    doc = ast.get_docstring(ast.parse((PKG / part / "__init__.py").read_text())) or ""
    line = re.search(r"^May import: (.*)$", doc, flags=re.M)
    assert line, f"{part}/__init__.py: its docstring says what it holds and ends with 'May import: ...'"
    if line.group(1).strip() == "nothing of jaxoptics.":
        return set()
    return set(re.findall(r"`(_\w+)`", line.group(1)))


def test_every_part_says_what_it_holds_and_may_import():
    assert {"_core", "_runtime", "_interface", "_films", "_render", "_io", "_fitting"} <= set(PARTS)
    for part in PARTS:
        allowed = _allowed(part)
        assert allowed <= set(PARTS), (part, allowed - set(PARTS))
        holds = set(re.findall(r"`(_\w+)`", ast.get_docstring(ast.parse((PKG / part / "__init__.py").read_text()))))
        modules = {p.stem for p in (PKG / part).glob("_*.py") if p.name != "__init__.py"}
        assert modules <= holds, f"{part}'s docstring does not name {sorted(modules - holds)}"
        assert not (PKG / part / "__init__.py").read_text().count("\nimport ") + \
            (PKG / part / "__init__.py").read_text().count("\nfrom "), f"{part}/__init__.py imports nothing"


def test_the_parts_form_a_layered_order():
    """The stated direction has no cycle: every part may import only parts listed before it."""
    order, left = [], {p: _allowed(p) for p in PARTS}
    while left:
        ready = sorted(p for p, deps in left.items() if deps <= set(order))
        assert ready, f"a cycle among the stated imports of {sorted(left)}"
        order += ready
        for p in ready:
            del left[p]


@pytest.mark.parametrize("part", PARTS)
def test_imports_follow_the_stated_direction(part):
    allowed = _allowed(part) | {part}
    for name in (m for m in MODULES if _part(m) == part):
        for target in _imports(name):
            assert _part(target) in allowed, f"{name} imports {target} ({_part(target)}); {part} may import {sorted(allowed - {part})}"


def test_nothing_imports_the_tools_or_the_command_line():
    """`jaxoptics.tools` and `jaxoptics.__main__` sit above the package: only the command line
    imports the tools (to run `bench` and `stress`)."""
    for name in MODULES:
        if _part(name) in ("tools", "jaxoptics.__main__"):
            continue
        for target in _imports(name):
            assert _part(target) != "tools" or name == "jaxoptics.__main__", (name, target)
            assert target != "jaxoptics.__main__", (name, target)


def test_no_import_cycle_between_modules():
    graph = {m: {t for t in _imports(m) if t in MODULES and t != m} for m in MODULES}
    # a package's `__init__` runs before its modules; an edge to a subpackage is to its docstring
    graph = {m: {t for t in ts if not (t in PARTS or MODULES[t].name == "__init__.py" and t != "jaxoptics")}
             for m, ts in graph.items()}
    state: dict[str, int] = {}

    def visit(m, path):
        state[m] = 1
        for t in sorted(graph[m]):
            if state.get(t) == 1:
                raise AssertionError("import cycle: " + " -> ".join(path[path.index(t):] + [t]))
            if t not in state:
                visit(t, path + [t])
        state[m] = 2

    for m in MODULES:
        if m not in state:
            visit(m, [m])


def test_no_module_over_700_lines():
    long = {str(p.relative_to(PKG)): n for p in MODULES.values() if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert not long, f"split these by concern: {long}"


def test_the_public_api_is_one_file():
    """`import jaxoptics as jo` shows every public name, each defined in a private module of a part
    (no subpackage re-exports anything: their `__init__` files import nothing)."""
    import jaxoptics as jo

    for name in jo.__all__:
        obj = getattr(jo, name)
        module = getattr(obj, "__module__", None)
        if callable(obj) and module is not None:
            assert _part(module) in PARTS and module.rpartition(".")[2].startswith("_"), (name, module)
