"""Shared fixtures: tiny random targets (built in milliseconds) and the trained toy pipeline (built once)."""

from __future__ import annotations

import os
import tempfile
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
    return build_tiny_llava()


def build_tiny_llava():
    """The ``tiny_llava`` fixture's model, built anew (seeded): a 1-layer CLIP tower, 4 image tokens, a tiny Llama."""
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


@pytest.fixture(scope="session")
def toy_pipeline(tmp_path_factory):
    """The shipped toy target + its self-distilled draft head (``policies/toy_dot``, what ``hf-specvla demo`` times),
    copied to a folder of the session's own (tests write beside it) and loaded: nothing is trained at test time.
    ``tests/training/test_toy_reproduction.py`` (slow tier) checks that ``demo --train``'s command still makes it."""
    import shutil

    from hf_specvla.benchmarks.toy import SHIPPED_TOY_DIR, build_toy_pipeline

    folder = tmp_path_factory.mktemp("toy") / "toy_dot"
    shutil.copytree(Path(__file__).resolve().parents[1] / SHIPPED_TOY_DIR, folder)
    return build_toy_pipeline(str(folder), progress=False)  # loaded: the settings its run.json records


def llava_prompt(generator: torch.Generator, text_len: int = 4) -> dict[str, torch.Tensor]:
    """``[<s>, 4 image tokens, random text]`` plus a random 16x16 image."""
    text = torch.randint(6, 64, (1, text_len), generator=generator)
    input_ids = torch.cat([torch.tensor([[1] + [IMAGE_TOKEN] * 4]), text], dim=1)
    return {"input_ids": input_ids, "pixel_values": torch.randn(1, 3, 16, 16, generator=generator)}


# ---------------------------------------------------------------------------------------------------- the two tiers
# The default run is the fast tier: every test but the slow ones (transformers' way: its ``@slow`` tests run with
# RUN_SLOW=1). ``RUN_SLOW=1 pytest`` or ``pytest --runslow`` runs both tiers; ``pytest -m slow --runslow`` the slow one
# alone (tox -e slow). A test is slow when it is marked ``slow`` or for what it does, marked from its module or its
# fixtures below (each kind a marker of its own, ``pytest -m ray --runslow`` runs one kind).

#: the kinds of slow test: marker -> what it stands for
SLOW_KINDS = {
    "training": "trains a model at test time",
    "ray": "starts a local Ray cluster",
    "rollouts": "rolls policies out in the simulator",
    "commands": "runs whole commands with worker processes (kill, resume, compare)",
    "sampling": "draws thousands of samples to check a distribution",
    "scripts": "runs an example script end to end",
}
#: module file -> the kind of slow test every test in it is
SLOW_MODULES = {
    "test_example_scripts.py": "scripts",
    "test_kill_resume.py": "commands",
    "test_compare_worker_death.py": "commands",
    "test_ray_serve.py": "ray",
}
#: fixture -> the kind of slow test every test using it is
SLOW_FIXTURES = {"ray_cluster": "ray", "distilled_head": "training"}
#: what a fast-tier test's phase (setup or call) should take on 2 cores: the run ends listing those over it (move them
#: to the slow tier or make them faster), on any machine, whatever its speed (HF_SPECVLA_TEST_TARGET_S overrides)
FAST_TEST_TARGET_S = float(os.environ.get("HF_SPECVLA_TEST_TARGET_S") or 60)
#: a fast-tier phase over this many seconds fails, naming itself: CI's tool (``.ci/run`` sets HF_SPECVLA_TEST_BUDGET_S),
#: unset on a user's machine, so that a test's verdict never depends on the machine's speed (0 or unset: no limit)
FAST_TEST_BUDGET_S = float(os.environ.get("HF_SPECVLA_TEST_BUDGET_S") or 0)


def pytest_addoption(parser):
    parser.addoption(
        "--runslow",
        action="store_true",
        default=False,
        help="run the slow tier too (as RUN_SLOW=1 does): training, Ray, rollouts, whole commands, ...",
    )


#: a folder of compiled graphs the tests keep from run to run (tox's tf525: ``{env_dir}/test-graphs``)
TEST_GRAPHS_ENV = "HF_SPECVLA_TEST_GRAPHS"


def pytest_configure(config):
    for kind, text in SLOW_KINDS.items():
        config.addinivalue_line("markers", f"{kind}: a slow test that {text}")
    # compiled graphs as files (speculative.graph_files) in one folder for the whole run, its workers included, so
    # that a graph one test compiled is loaded by the next; never the user's own cache. HF_SPECVLA_TEST_GRAPHS (tox
    # sets it) names a folder the tests keep from run to run, so that a later run loads what an earlier one compiled
    # (the key makes a change of code or versions a miss); the controller clears it of what no run of this code can
    # load, or what no run used for a week. Else a fresh folder per run.
    if "HF_SPECVLA_GRAPH_CACHE" not in os.environ:
        kept = os.environ.get(TEST_GRAPHS_ENV)
        if kept and not hasattr(config, "workerinput"):
            from hf_specvla.speculative.graph_files import remove_stale

            Path(kept).mkdir(parents=True, exist_ok=True)
            remove_stale(kept, unused_days=7)
        os.environ["HF_SPECVLA_GRAPH_CACHE"] = kept or tempfile.mkdtemp(prefix="hf_specvla-test-graphs-")


@pytest.fixture
def graphs_in_memory(monkeypatch):
    """Compiled graphs in memory (dynamo's own cache), not files, for a test that reads dynamo's state: its graph
    counts, guards and recompile limits."""
    monkeypatch.setenv("HF_SPECVLA_GRAPH_CACHE", "off")


def runs_slow(config) -> bool:
    """Whether this session runs the slow tier: ``--runslow`` or ``RUN_SLOW`` set to a true value."""
    return config.getoption("--runslow") or os.environ.get("RUN_SLOW", "").lower() in ("1", "true", "yes")


def pytest_collection_modifyitems(config, items):
    """Marks each test of a slow kind with its kind's marker and ``slow``; outside the slow tier they are skipped,
    saying how to run them."""
    skip = pytest.mark.skip(reason="slow tier: RUN_SLOW=1 or --runslow runs it")
    slow = runs_slow(config)
    for item in items:
        kinds = {SLOW_MODULES.get(item.path.name)} | {SLOW_FIXTURES.get(f) for f in getattr(item, "fixturenames", ())}
        kinds |= {kind for kind in SLOW_KINDS if item.get_closest_marker(kind) is not None}
        for kind in kinds - {None}:
            item.add_marker(getattr(pytest.mark, kind))
            item.add_marker(pytest.mark.slow)
        if not slow and item.get_closest_marker("slow") is not None:
            item.add_marker(skip)


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item, call):
    """In the fast tier, a setup or a call over ``FAST_TEST_BUDGET_S`` (when set: CI) fails the test, naming it and its
    time; one over ``FAST_TEST_TARGET_S`` is listed at the end of the run (``pytest_terminal_summary``)."""
    report = yield
    if report.when in ("setup", "call") and report.passed and report.duration > FAST_TEST_TARGET_S:
        if not runs_slow(item.config) and item.get_closest_marker("slow") is None:
            report.user_properties.append(("over_fast_target_s", round(report.duration, 1)))
            budget = FAST_TEST_BUDGET_S
            if budget and report.duration > budget:
                report.outcome = "failed"
                report.longrepr = (f"{item.nodeid}: its {report.when} took {report.duration:.0f} s, over the fast "
                                   f"tier's {budget:g} s a test (HF_SPECVLA_TEST_BUDGET_S): mark it slow (or a slow "
                                   f"kind: {', '.join(SLOW_KINDS)}) or make it faster")  # fmt: skip
    return report


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    """Lists the fast-tier tests whose setup or call took over ``FAST_TEST_TARGET_S`` (reported, not failed, unless
    ``HF_SPECVLA_TEST_BUDGET_S`` says otherwise): the fast tier's time is kept by moving them, not by failing a slower
    machine's run."""
    over = [(report.nodeid, report.when, dict(report.user_properties)["over_fast_target_s"])
            for reports in terminalreporter.stats.values() for report in reports
            if "over_fast_target_s" in dict(getattr(report, "user_properties", ()))]  # fmt: skip
    if over:
        terminalreporter.section(f"fast-tier tests over its {FAST_TEST_TARGET_S:g} s target (not failed)")
        for nodeid, when, seconds in sorted(over, key=lambda row: -row[2]):
            terminalreporter.write_line(f"{seconds:6.1f} s  {nodeid} ({when})")


@pytest.hookimpl(optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """With pytest-xdist (tox runs ``-n 2``): whole modules per worker (a module's fixtures are built once, its servers
    and Ray cluster are its own). (``--dist loadgroup`` cannot do it: xdist 3.8 renames the nodes it groups, which
    pytest 9.2 no longer lets it.)"""
    from xdist.scheduler import LoadScopeScheduling

    return LoadScopeScheduling(config, log)
