"""The core is closed: nothing in ``gtsjax/core`` or ``gtsjax/gp`` imports the host side.

The numeric core and the GP library may import each other, ``gtsjax.precision`` below them both, and
third-party packages; never the command line, the drivers, file formats, training, the simulator,
the sensor table, the user-facing errors, the figures or the viewer. Every import statement is read
with ``ast`` (module level and inside functions, absolute and relative), so a host import hidden in a
function body fails too.
"""

import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "gtsjax"
CLOSED = ("core", "gp")
HOST = ("cli", "drivers", "io", "train", "sim", "sensors", "errors", "viz", "viewer")


def _imported(path: Path, src: str | None = None) -> list[tuple[int, str]]:
    """Every module the file at ``path`` imports (``src``: its text, if not read from there), as
    absolute dotted names, with the line of the import."""
    package = ["gtsjax", *path.relative_to(PACKAGE).parent.parts]
    out = []
    for node in ast.walk(ast.parse(path.read_text() if src is None else src, str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                stem = ".".join(base + ([node.module] if node.module else []))
            else:
                stem = node.module or ""
            # ``from . import io`` and ``from .. import errors`` name the modules in their aliases.
            out += [(node.lineno, f"{stem}.{a.name}") for a in node.names] if not node.module else [(node.lineno, stem)]
    return out


def _host(name: str) -> bool:
    parts = name.split(".")
    return parts[0] == "gtsjax" and len(parts) > 1 and parts[1] in HOST


def _closed_files() -> list[Path]:
    return sorted(p for d in CLOSED for p in (PACKAGE / d).rglob("*.py"))


@pytest.mark.parametrize("path", _closed_files(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_core_and_gp_import_nothing_of_the_host(path):
    bad = [f"line {n}: {name}" for n, name in _imported(path) if _host(name)]
    assert not bad, f"{path.relative_to(PACKAGE)} imports the host side: {'; '.join(bad)}"


def test_the_check_reads_relative_and_absolute_imports():
    """The reader itself: a relative import two levels up, an absolute one, one in a function body
    and ``from .. import errors`` are all seen as the host modules they are."""
    fake = PACKAGE / "core" / "_probe_not_a_module.py"
    src = (
        "from ..io.logs import x\nimport gtsjax.sensors\ndef f():\n    from .. import errors\nfrom .scan import Scan\n"
    )
    tree = dict(_imported(fake, src))
    assert tree == {1: "gtsjax.io.logs", 2: "gtsjax.sensors", 4: "gtsjax.errors", 5: "gtsjax.core.scan"}
    assert [_host(tree[n]) for n in sorted(tree)] == [True, True, True, False]


def test_the_model_file_loader_is_the_hosts():
    """The model's parameter tree is in the core; loading it from a file is not."""
    names = {name for p in _closed_files() for _, name in _imported(p)}
    assert "gtsjax.io.modelfile" not in names and "gtsjax.drivers.setup" not in names
    assert (PACKAGE / "core" / "model.py").is_file() and not (PACKAGE / "model.py").exists()
    assert (PACKAGE / "precision.py").is_file() and not (PACKAGE / "core" / "precision.py").exists()


@pytest.mark.parametrize("path", sorted((PACKAGE / "gp").rglob("*.py")), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_the_gp_library_sits_below_the_core(path):
    """The core uses the GP library; the GP library uses nothing of the core (what both need, the
    full-precision products, is ``gtsjax.precision`` below them)."""
    bad = [f"line {n}: {name}" for n, name in _imported(path) if name.startswith("gtsjax.core")]
    assert not bad, f"{path.relative_to(PACKAGE)} imports the core: {'; '.join(bad)}"
