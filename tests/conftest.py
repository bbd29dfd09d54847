"""Shared fixtures: tiny random targets (built in milliseconds) and the trained toy pipeline (built once)."""

from __future__ import annotations

import logging
import os
import re
import time
from contextlib import contextmanager, nullcontext
from pathlib import Path

# every read of a cache's length inside a speculative call checks the host's count against the cache's own counter
os.environ["HF_SPECVLA_CHECK_CACHE_LENGTH"] = "1"

import pytest
import torch
from transformers import CLIPVisionConfig, LlamaConfig, LlamaForCausalLM, LlavaConfig, LlavaForConditionalGeneration

from hf_specvla import ActionTokenizer, DraftHead, enable_speculation

# One thread: on 2 cores that anything else uses too, torch's second thread spin-waits for a core and the suite crawls
# (the toy pipeline trained in 30 s with 2 threads on 2 idle cores, 96 s beside one busy process, 12 min at load 5;
# with 1 thread: 46 s idle, 47 s beside the busy process). tox sets OMP_NUM_THREADS=1 for the commands tests start.
torch.set_num_threads(1)

VOCAB = 320  # 64 text ids + 256 action ids (64..319)
IMAGE_TOKEN = 5


def tiny_llama_config(**overrides) -> LlamaConfig:
    settings = dict(
        vocab_size=VOCAB,
        hidden_size=64,
        intermediate_size=128,
        num_hidden_layers=2,
        num_attention_heads=4,
        num_key_value_heads=2,
        max_position_embeddings=256,
        bos_token_id=1,
        eos_token_id=2,
        pad_token_id=0,
    )
    settings.update(overrides)
    return LlamaConfig(**settings)


@pytest.fixture(scope="session")
def action_tokenizer() -> ActionTokenizer:
    return ActionTokenizer(VOCAB)


@pytest.fixture(scope="session")
def tiny_llama():
    torch.manual_seed(0)
    return enable_speculation(LlamaForCausalLM(tiny_llama_config()).eval())


@pytest.fixture(scope="session")
def tiny_llava():
    torch.manual_seed(1)
    vision = CLIPVisionConfig(
        hidden_size=32,
        intermediate_size=64,
        num_hidden_layers=1,
        num_attention_heads=2,
        image_size=16,
        patch_size=8,
        projection_dim=32,
    )
    config = LlavaConfig(
        vision_config=vision,
        text_config=tiny_llama_config(),
        image_token_id=IMAGE_TOKEN,
        image_seq_length=4,
        vision_feature_select_strategy="default",
        vision_feature_layer=-1,
    )
    return enable_speculation(LlavaForConditionalGeneration(config).eval())


@pytest.fixture(scope="session")
def random_draft(tiny_llama, action_tokenizer):
    torch.manual_seed(2)
    return DraftHead.from_target(tiny_llama, action_tokenizer, action_dim=7, draft_action_tokens_only=False).eval()


@pytest.fixture(scope="session")
def random_llava_draft(tiny_llava, action_tokenizer):
    torch.manual_seed(3)
    return DraftHead.from_target(tiny_llava, action_tokenizer, action_dim=7).eval()


#: the tests' toy draft head trains 2400 steps, half the demo's (``toy.TOY_HEAD_STEPS``): its tree drafted 90% of 128
#: held-out actions whole before the prefill in a probe (800 steps: 29%, too few for the test that most are), and the
#: suite saves the other half's minutes
TOY_TEST_HEAD_STEPS = 2400


@pytest.fixture(scope="session")
def toy_pipeline(tmp_path_factory, request):
    """The toy target + a self-distilled draft head, trained once per test session (minutes on 2 CPU cores). It says
    so on the terminal, a line per stage, and draws the stages' progress bars on stderr past pytest's capture (every
    30 s when stderr is a file or a pipe, as on CI): a long silence would look like a hang."""
    from hf_specvla.benchmarks.toy import build_toy_pipeline

    with _on_the_terminal(request.config, "toy_pipeline") as say:
        say("training the toy target, then self-distilling its draft head (once per session)")
        start = time.perf_counter()
        pipeline = build_toy_pipeline(str(tmp_path_factory.mktemp("toy")), draft_steps=TOY_TEST_HEAD_STEPS)
        say(f"ready in {time.perf_counter() - start:.0f} s")
    return pipeline


@contextmanager
def _on_the_terminal(config: pytest.Config, name: str):
    """Inside the block, ``say(text)`` and hf_specvla's INFO log lines (a training stage's summary) go to the terminal
    as ``name: ...`` lines, and stderr is not captured (progress bars show)."""
    reporter = config.pluginmanager.get_plugin("terminalreporter")
    capture = config.pluginmanager.get_plugin("capturemanager")

    def say(text: str) -> None:
        if reporter is not None:
            reporter.write_line(f"{name}: {text}")

    class ToTerminal(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            say(self.format(record))

    library = logging.getLogger("hf_specvla")
    handler, level = ToTerminal(logging.INFO), library.level
    library.addHandler(handler)
    library.setLevel(logging.INFO)
    try:
        with capture.global_and_fixture_disabled() if capture is not None else nullcontext():
            yield say
    finally:
        library.removeHandler(handler)
        library.setLevel(level)


def llava_prompt(generator: torch.Generator, text_len: int = 4) -> dict[str, torch.Tensor]:
    """``[<s>, 4 image tokens, random text]`` plus a random 16x16 image."""
    text = torch.randint(6, 64, (1, text_len), generator=generator)
    input_ids = torch.cat([torch.tensor([[1] + [IMAGE_TOKEN] * 4]), text], dim=1)
    return {"input_ids": input_ids, "pixel_values": torch.randn(1, 3, 16, 16, generator=generator)}


#: what makes a test slow: a fixture that trains a model, or a module that kills and reruns whole commands
SLOW_FIXTURES = {"toy_pipeline"}
SLOW_MODULES = {"test_kill_resume.py"}


def pytest_collection_modifyitems(config, items):
    """Marks the slow tests ``slow`` (``pytest -m "not slow"`` for a quick pass; CI runs everything)."""
    for item in items:
        if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())) or item.path.name in SLOW_MODULES:
            item.add_marker(pytest.mark.slow)


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """With pytest-xdist (tox runs ``-n 2``): whole modules per worker (a module's fixtures are built once, its servers
    and Ray cluster are its own), and every module that uses a fixture of ``SLOW_FIXTURES`` on one worker, so that the
    model it trains is trained once, not once per worker. (``--dist loadgroup`` cannot do it: xdist 3.8 renames the
    nodes it groups, which pytest 9.2 no longer lets it.)"""
    from xdist.scheduler import LoadScopeScheduling

    uses = re.compile(r"\b(" + "|".join(SLOW_FIXTURES) + r")\b")
    root = Path(__file__).resolve().parent
    training = {
        path.relative_to(root.parent).as_posix()
        for path in root.rglob("test_*.py")
        if uses.search(path.read_text(encoding="utf-8"))
    }

    class ModulesAndTrainedFixtures(LoadScopeScheduling):
        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "the modules that train a fixture's model" if module in training else module

    return ModulesAndTrainedFixtures(config, log)
