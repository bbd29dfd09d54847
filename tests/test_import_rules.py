"""Imports point down: the package's import graph, read from the source (no module is imported), obeys the house
rules. A forbidden edge fails naming the module, the line and the imported name."""

from __future__ import annotations

import ast
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
    assert {"hf_specvla.policy", "hf_specvla.speculative.loop", "hf_specvla.cli"} <= modules
    assert ("hf_specvla.speculative.loop", "hf_specvla.speculative.cache") in {(m, i) for m, _, i, _ in EDGES}


def test_the_engine_imports_nothing_of_the_package_but_action_tokens():
    def rule(module, imported):
        inside = module.startswith("hf_specvla.speculative")
        allowed = imported.startswith("hf_specvla.speculative") or imported == "hf_specvla.action_tokenizer"
        return inside and not allowed

    assert _violations(rule) == []


def test_nothing_outside_the_engine_imports_its_private_modules():
    def rule(module, imported):
        return not module.startswith("hf_specvla.speculative") and imported.startswith("hf_specvla.speculative.")

    assert _violations(rule) == []


def test_nothing_imports_the_cli():
    assert (
        _violations(lambda module, imported: imported.startswith("hf_specvla.cli") and module != "hf_specvla.cli") == []
    )


#: modules a model is made of (OpenVLA's port); its draft-training recipe is training code, not the model's
MODEL_MODULES = ("hf_specvla.openvla",)
NOT_MODEL_MODULES = ("hf_specvla.openvla.draft_training",)
SIMULATOR_TRAINING_CLI = ("hf_specvla.envs", "hf_specvla.evaluation", "hf_specvla.comparison",
                          "hf_specvla.demonstrations", "hf_specvla.training", "hf_specvla.vla_training",
                          "hf_specvla.policy_draft", "hf_specvla.cli")  # fmt: skip


def test_models_import_no_simulator_training_or_cli():
    def rule(module, imported):
        is_model = module.startswith(MODEL_MODULES) and not module.startswith(NOT_MODEL_MODULES)
        return is_model and imported.startswith(SIMULATOR_TRAINING_CLI)

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
        if _module_name(path) == "hf_specvla.cli":
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
