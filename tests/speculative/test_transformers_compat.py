"""The transformers seam: the cache's name per release, the support check at the first speculative call, and the
tox environments that pin the releases the package claims."""

from __future__ import annotations

import configparser
import logging
import re
import warnings
from pathlib import Path

import pytest
import torch
import transformers
from packaging.version import Version

from hf_specvla.speculative import (
    CACHE_KEY,
    NEWEST_TESTED_TRANSFORMERS,
    OLDEST_TESTED_TRANSFORMERS,
    SUPPORTED_TRANSFORMERS,
    cache_of,
    check_transformers_support,
    compat,
)

from ..conftest import llava_prompt
from .test_backbones import ForwardCounter
from .test_speculative_decoding import greedy_continuation

ROOT = Path(__file__).resolve().parents[2]


def _release(version: str) -> Version:
    return Version(Version(version).base_version)


def test_the_cache_key_is_the_one_generate_hands_the_model(tiny_llama):
    """What ``prepare_inputs_for_generation`` returns, what the forward takes and what its output carries."""
    from transformers import DynamicCache

    cache = DynamicCache(config=tiny_llama.config)
    inputs = tiny_llama.prepare_inputs_for_generation(torch.tensor([[1, 7, 9]]), is_first_iteration=True,
                                                      **{CACHE_KEY: cache})  # fmt: skip
    assert inputs[CACHE_KEY] is cache
    out = tiny_llama(**inputs)
    assert cache_of(out) is cache and cache.get_seq_length() == 3
    expected = "cache" if _release(transformers.__version__) >= Version("5.24") else "past_key_values"
    assert CACHE_KEY == expected


def test_speculative_calls_raise_no_deprecation_warning(tiny_llama, tiny_llava, random_llava_draft, caplog):
    """Nothing the engine passes to transformers (target, draft head, outputs) uses a deprecated name: neither a
    ``FutureWarning`` nor transformers' logged ``warning_once``."""

    prompt = llava_prompt(torch.Generator().manual_seed(0), 3)
    with warnings.catch_warnings(record=True) as caught, caplog.at_level(logging.WARNING):
        warnings.simplefilter("always")
        out = tiny_llava.generate(**prompt, max_new_tokens=6, do_sample=False, assistant_model=random_llava_draft,
                                  return_dict_in_generate=True)  # fmt: skip
        cache_of(out).get_seq_length()
        tiny_llama.generate(input_ids=torch.tensor([[1, 7, 9]]), max_new_tokens=4, do_sample=False,
                            draft_ids=torch.tensor([[70, 71]]))  # fmt: skip
    messages = [str(w.message) for w in caught] + [r.getMessage() for r in caplog.records]
    assert [m for m in messages if "deprecated" in m] == []


def test_a_release_older_than_supported_is_refused_naming_both():
    with pytest.raises(RuntimeError, match=r"needs transformers >=5\.20\.0,<6, but 5\.19\.0 is installed"):
        check_transformers_support("5.19.0")


def test_a_newer_release_with_everything_is_used_with_a_warning(caplog):
    with caplog.at_level(logging.WARNING, logger=compat.__name__):
        check_transformers_support("5.99.0.dev0")
    assert "5.99.0.dev0 is newer than the newest release hf_specvla was tested with" in caplog.text


def test_a_release_missing_what_the_engine_needs_is_refused_before_any_forward(tiny_llama, monkeypatch):
    """A future release that drops something the engine relies on: a clear error at the first speculative call (the
    installed version, the tested range, what is missing), not a KeyError from inside a round."""
    real = compat._requirements
    monkeypatch.setattr(compat, "_requirements", lambda: real() + [("Cache.layers (per-layer keys / values)", False)])
    check_transformers_support.cache_clear()
    counter = ForwardCounter(tiny_llama)
    try:
        with pytest.raises(RuntimeError) as error:
            tiny_llama.generate(input_ids=torch.tensor([[1, 7, 9]]), max_new_tokens=3, do_sample=False,
                                draft_ids=torch.tensor([[70]]))  # fmt: skip
    finally:
        check_transformers_support.cache_clear()
    message = str(error.value)
    assert f"transformers {transformers.__version__} changed" in message
    assert "missing: Cache.layers" in message
    assert f"{OLDEST_TESTED_TRANSFORMERS} .. {NEWEST_TESTED_TRANSFORMERS}" in message
    assert counter.count == 0


def test_the_installed_release_has_everything_the_engine_needs(tiny_llama):
    assert [name for name, present in compat._requirements() if not present] == []
    out = tiny_llama.generate(input_ids=torch.tensor([[1, 7, 9]]), max_new_tokens=4, do_sample=False,
                              draft_ids=torch.tensor([[70, 71]]))  # fmt: skip
    assert out[0, 3:].tolist() == greedy_continuation(tiny_llama, {"input_ids": torch.tensor([[1, 7, 9]])}, 4)


# ----------------------------------------------------------------------------- what the project pins and claims
def _tox() -> configparser.ConfigParser:
    parser = configparser.ConfigParser(interpolation=None)
    parser.read(ROOT / "tox.ini")
    return parser


def _pinned_transformers(section: str) -> list[str]:
    deps = _tox()[section].get("deps", "")
    return re.findall(r"transformers==([\d.]+)", deps)


def test_tox_pins_the_oldest_and_newest_tested_releases_and_the_demo_pins_a_tested_one():
    tox = _tox()
    pinned = {v for section in tox.sections() for v in _pinned_transformers(section)}
    assert OLDEST_TESTED_TRANSFORMERS.rsplit(".", 1)[0] in {v.rsplit(".", 1)[0] for v in pinned}
    assert NEWEST_TESTED_TRANSFORMERS in pinned
    assert _pinned_transformers("testenv:demo") == [NEWEST_TESTED_TRANSFORMERS]
    assert "torch==" in tox["testenv:demo"]["deps"]


def test_ci_runs_the_readme_test_command_with_the_newest_release_env():
    readme = (ROOT / "README.md").read_text()
    ci = (ROOT / ".ci" / "run").read_text()
    command = re.search(r"python3 -m tox -e ([\w,]+)\n", ci).group(1)
    assert f'python3 -m pip install "tox>=4" && python3 -m tox -e {command}' in readme
    envs = command.split(",")
    assert "tflatest" in envs and any(env.startswith("tf5") for env in envs)
    # then the slow tier (docs/testing.md), after the fast one: a fast failure is reported first
    slow = "python3 -m tox -e tf525 -- -m slow --runslow\n"
    assert slow in ci and ci.index(slow) > ci.index(f"tox -e {command}")
    assert re.search(r"transformers>=[\d.]+,<6", _tox()["testenv:tflatest"]["deps"])
    # tflatest skips while the newest release is the pinned one: the release its check compares with is that pin
    skip_check = re.search(r"on_newer_transformers\.py ([\d.]+)", _tox()["testenv:tflatest"]["commands"])
    assert skip_check and skip_check.group(1) == NEWEST_TESTED_TRANSFORMERS


def test_pyproject_admits_the_supported_range():
    pyproject = (ROOT / "pyproject.toml").read_text()
    lower = OLDEST_TESTED_TRANSFORMERS.rsplit(".", 1)[0]
    assert f'"transformers>={lower},<6"' in pyproject
    assert SUPPORTED_TRANSFORMERS == f">={OLDEST_TESTED_TRANSFORMERS},<6"
