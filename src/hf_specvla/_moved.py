"""Old import paths of modules that moved when the package was split into folders by job.

``import hf_specvla.policy`` (what saved model cards and older scripts use) still works: a finder on
``sys.meta_path`` answers each old name with the module that now holds its code, the *same* module object, so
classes stay identical (``isinstance`` and pickles hold) and nothing is defined twice. A ``FutureWarning`` names
the new path.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
import warnings

#: old module -> the module that holds its public names now
MOVED_MODULES = {
    "hf_specvla.action_tokenizer": "hf_specvla.actions.tokenizer",
    "hf_specvla.tokenization": "hf_specvla.actions.vla_tokenizer",
    "hf_specvla.policy": "hf_specvla.policies",
    "hf_specvla.policy_draft": "hf_specvla.training.policy_draft",
    "hf_specvla.openvla.draft_training": "hf_specvla.training.openvla_draft",
    "hf_specvla.vla_training": "hf_specvla.training.behaviour_cloning",
    "hf_specvla.checkpointing": "hf_specvla.training.checkpoints",
    "hf_specvla.envs": "hf_specvla.metaworld",
    "hf_specvla.envs.metaworld": "hf_specvla.metaworld.env",
    "hf_specvla.envs.seeds": "hf_specvla.metaworld.seeds",
    "hf_specvla.demonstrations": "hf_specvla.metaworld.demonstrations",
    "hf_specvla.evaluation": "hf_specvla.metaworld.evaluation",
    "hf_specvla.comparison": "hf_specvla.metaworld.comparison",
    "hf_specvla.toy": "hf_specvla.benchmarks.toy",
    "hf_specvla.benchmark": "hf_specvla.benchmarks.speed",
}


class _AliasLoader(importlib.abc.Loader):
    def __init__(self, new_name: str):
        self.new_name = new_name

    def create_module(self, spec):
        return importlib.import_module(self.new_name)

    def exec_module(self, module) -> None:  # the module already ran under its new name
        pass


class MovedModuleFinder(importlib.abc.MetaPathFinder):
    """Resolves the names in [`MOVED_MODULES`] to the modules that replaced them."""

    def find_spec(self, fullname, path, target=None):
        new_name = MOVED_MODULES.get(fullname)
        if new_name is None:
            return None
        warnings.warn(f"{fullname} moved to {new_name}; import it from there", FutureWarning, stacklevel=2)
        return importlib.util.spec_from_loader(fullname, _AliasLoader(new_name))


def install() -> None:
    if not any(isinstance(finder, MovedModuleFinder) for finder in sys.meta_path):
        sys.meta_path.insert(0, MovedModuleFinder())  # before the path finder: an old name never loads twice
