"""Imports point down: the package's import graph, read from the source (no module is imported), obeys the house
rules. A forbidden edge fails naming the module, the line and the imported name."""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / "src" / "hf_specvla"


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _imports(path: Path, module: str | None = None) -> list[tuple[int, str]]:
    """``(line, absolute module)`` of every import in ``path`` (functions' local imports included), read as the
    module ``module`` (default: the package module at ``path``); ``from . import x`` gives ``package.x``."""
    module = module or _module_name(path)
    package = module if path.name == "__init__.py" else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join(anchor + ([base] if base else []))
            if node.module is None:  # from . import a, b: each name may be a submodule
                found += [(node.lineno, f"{base}.{alias.name}") for alias in node.names]
            else:
                found.append((node.lineno, base))
    return found


EDGES = [
    (_module_name(path), line, imported, path)
    for path in sorted(PACKAGE.rglob("*.py"))
    for line, imported in _imports(path)
    if imported.startswith("hf_specvla")
]


def _violations(rule) -> list[str]:
    return [f"{path.relative_to(PACKAGE.parent)}:{line} imports {imported}" for module, line, imported, path in EDGES
            if rule(module, imported)]  # fmt: skip


def test_the_graph_was_read():
    modules = {module for module, *_ in EDGES}
    assert {"hf_specvla.policies.modeling_vla", "hf_specvla.speculative.loop", "hf_specvla.cli"} <= modules
    assert ("hf_specvla.speculative.decoder", "hf_specvla.speculative.cache") in {(m, i) for m, _, i, _ in EDGES}


def _inside(module: str, *packages: str) -> bool:
    return any(module == package or module.startswith(package + ".") for package in packages)


def test_the_tree_shows_the_jobs():
    """One folder per job; only shared utilities sit at the top."""
    folders = {path.name for path in PACKAGE.iterdir() if path.is_dir() and (path / "__init__.py").exists()}
    assert folders == {
        "actions",
        "speculative",
        "openvla",
        "policies",
        "training",
        "metaworld",
        "benchmarks",
        "cli",
        "serving",
    }
    top_level = {path.stem for path in PACKAGE.glob("*.py")}
    assert top_level == {"__init__", "_lazy", "_moved", "_validation", "progress", "run_folder"}


def test_actions_import_nothing_of_the_package():
    def rule(module, imported):
        return _inside(module, "hf_specvla.actions") and not _inside(imported, "hf_specvla.actions", "hf_specvla._lazy")

    assert _violations(rule) == []


def test_the_engine_imports_nothing_of_the_package_but_actions():
    def rule(module, imported):
        return _inside(module, "hf_specvla.speculative") and not _inside(
            imported, "hf_specvla.speculative", "hf_specvla.actions"
        )

    assert _violations(rule) == []


def test_nothing_outside_the_engine_imports_its_private_modules():
    def rule(module, imported):
        return not _inside(module, "hf_specvla.speculative") and imported.startswith("hf_specvla.speculative.")

    assert _violations(rule) == []


def test_no_module_imports_one_that_imports_it_back():
    """No import circle, local imports included: each module's imports form a graph without cycles (a lazy import
    that closes a circle hides which module builds on which)."""
    modules = {_module_name(path) for path in PACKAGE.rglob("*.py")}
    graph: dict[str, set[str]] = {}
    for module, _, imported, _ in EDGES:
        while imported not in modules and "." in imported:  # ``from a.b import name``: the module a.b
            imported = imported.rsplit(".", 1)[0]
        if imported in modules and imported != module and not module.startswith(imported + "."):
            graph.setdefault(module, set()).add(imported)  # (a package's own __init__, imported by its modules, aside)
    circles, done = [], set()

    def visit(module: str, path: list[str]) -> None:
        for imported in sorted(graph.get(module, ())):
            if imported in path:
                circles.append(path[path.index(imported) :] + [imported])
            elif imported not in done:
                visit(imported, path + [imported])
        done.add(module)

    for module in sorted(graph):
        if module not in done:
            visit(module, [module])
    assert circles == [], [" -> ".join(circle) for circle in circles]


def test_nothing_imports_the_cli():
    rule = lambda module, imported: _inside(imported, "hf_specvla.cli") and not _inside(module, "hf_specvla.cli")  # noqa: E731
    assert _violations(rule) == []


SIMULATOR_TRAINING_CLI = ("hf_specvla.metaworld", "hf_specvla.training", "hf_specvla.benchmarks", "hf_specvla.cli")


def test_models_import_no_simulator_training_or_cli():
    """A policy or the OpenVLA port is a model: it loads, acts and saves without the simulator or the trainers."""

    def rule(module, imported):
        return _inside(module, "hf_specvla.policies", "hf_specvla.openvla") and _inside(
            imported, *SIMULATOR_TRAINING_CLI
        )

    assert _violations(rule) == []


def test_models_import_no_serving():
    """The engine and the models know nothing of serving: it sits above them."""

    def rule(module, imported):
        below = ("hf_specvla.speculative", "hf_specvla.actions", "hf_specvla.policies", "hf_specvla.openvla")
        return _inside(module, *below) and _inside(imported, "hf_specvla.serving")

    assert _violations(rule) == []


def test_serving_imports_no_simulator_training_or_cli():
    """A policy server loads policies; it never imports the simulator, the trainers, the benchmarks or the CLI."""

    def rule(module, imported):
        return _inside(module, "hf_specvla.serving") and _inside(imported, *SIMULATOR_TRAINING_CLI)

    assert _violations(rule) == []


def test_robots_use_only_the_servers_client_side():
    """The simulator's robots talk to a server through its client, wire format and defaults, never its internals."""
    client_side = ("hf_specvla.serving.client", "hf_specvla.serving.protocol", "hf_specvla.serving.config")

    def rule(module, imported):
        return (_inside(module, "hf_specvla.metaworld") and _inside(imported, "hf_specvla.serving")
                and not _inside(imported, *client_side))  # fmt: skip

    assert _violations(rule) == []


def test_the_simulator_side_imports_no_benchmarks():
    def rule(module, imported):
        return _inside(module, "hf_specvla.metaworld") and _inside(imported, "hf_specvla.benchmarks")

    assert _violations(rule) == []


def test_relative_and_local_imports_are_resolved(tmp_path):
    """A private engine import written relatively, or inside a function, is seen as the absolute module it is."""
    probe = tmp_path / "probe.py"
    probe.write_text(
        "from .speculative.loop import as_drafter\n\ndef f():\n    from ..x import y\n    from . import cli\n"
    )
    assert _imports(probe, "hf_specvla.openvla.probe") == [
        (1, "hf_specvla.openvla.speculative.loop"),
        (4, "hf_specvla.x"),
        (5, "hf_specvla.openvla.cli"),
    ]
    assert _imports(probe, "hf_specvla.probe")[0] == (1, "hf_specvla.speculative.loop")


def test_only_the_cli_prints_or_raises_usage_errors():
    """The library logs and raises; writing to the terminal and usage errors are the CLI's."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if _inside(_module_name(path), "hf_specvla.cli"):
            continue
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if not isinstance(node, ast.Call):
                continue
            if isinstance(node.func, ast.Name) and node.func.id == "print":
                found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} print(...)")
            if (
                isinstance(node.func, ast.Attribute)
                and node.func.attr == "error"
                and getattr(node.func.value, "id", None) == "parser"
            ):
                found.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} parser.error(...)")
    assert found == []


def test_a_hook_runs_once_the_import_that_loads_its_module_has_finished(tmp_path, monkeypatch):
    """``when_imported``: not while a module of the package is half-initialised (``outer`` imports ``target`` and then
    ``late``), once, and at once for a module already imported."""
    from hf_specvla._lazy import when_imported

    package = tmp_path / "hookprobe"
    package.mkdir()
    (package / "__init__.py").write_text("")
    (package / "target.py").write_text("")
    (package / "late.py").write_text("")
    (package / "outer.py").write_text("import hookprobe.target\nimport hookprobe.late\nDONE = True\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    seen = []
    try:
        when_imported("hookprobe.target", lambda: seen.append(getattr(sys.modules["hookprobe.outer"], "DONE", False)))
        assert seen == []
        import hookprobe.outer  # noqa: F401

        assert seen == [True]
        import hookprobe.late  # noqa: F401

        assert seen == [True] and not any(type(finder).__name__ == "_WhenImported" for finder in sys.meta_path)
        when_imported("hookprobe.late", lambda: seen.append("now"))
        assert seen == [True, "now"]
    finally:
        for name in [name for name in sys.modules if name.partition(".")[0] == "hookprobe"]:
            del sys.modules[name]


def test_the_package_imports_without_torch_and_registers_the_draft_head_with_the_auto_classes_later():
    """``import hf_specvla`` loads neither torch nor transformers; importing a model class first (whose import loads
    the Auto classes midway) and then ``AutoConfig`` still finds the draft head (``AutoModel`` first:
    test_moved_paths)."""
    head = str(PACKAGE.parents[1] / "policies" / "mt10_vla3_draft")
    code = "\n".join([
        "import sys",
        "import hf_specvla",
        "print('torch' in sys.modules, 'transformers' in sys.modules)",
        "from transformers import LlamaForCausalLM",
        "from transformers import AutoConfig",
        f"print(type(AutoConfig.from_pretrained({head!r})).__name__)",
    ])  # fmt: skip
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300,
                            env={**os.environ, "HF_HUB_OFFLINE": "1"})  # fmt: skip
    assert result.returncode == 0, result.stderr[-2000:]
    assert result.stdout.split() == ["False", "False", "DraftHeadConfig"]
