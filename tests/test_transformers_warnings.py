"""No call we make is one transformers deprecates or warns about (issue 65): the demo's calls (greedy, compiled
greedy, transformers' assisted generation with the toy's early-exit assistant, our drafters eager and compiled), the
policies' ``predict_action`` entry points (with and without a ``generation_config``), run with warnings as errors.

transformers says most of this through its logger, once per message per process (``logger.warning_once``): the
harness clears that memory first, so that an earlier test cannot have used up the warning this one should see."""

from __future__ import annotations

import logging
import warnings
from contextlib import contextmanager
from pathlib import Path

import numpy as np
import pytest
import torch
from transformers import GenerationConfig

from hf_specvla.cli import main

from .cli.test_cli import eager_backend_compiled_kwargs

#: what transformers logs when a generate call is made in a way it deprecates or duplicates
GENERATE_WARNINGS = ("deprecated", "also created", "will be removed")


@contextmanager
def transformers_warnings_as_errors():
    """Inside the block, a ``DeprecationWarning`` / ``FutureWarning`` raises (torch's own, raised while torch imports
    its compiler, aside), and so does a warning transformers logs about a ``generate`` call (see
    [`GENERATE_WARNINGS`]), at the call that caused it."""

    class Raise(logging.Handler):
        def emit(self, record: logging.LogRecord) -> None:
            message = record.getMessage()
            if any(words in message for words in GENERATE_WARNINGS):
                raise AssertionError(f"transformers warned ({record.name}): {message}")

    logging.Logger.warning_once.cache_clear()  # transformers' once-per-process memory of what it logged
    handler, transformers_logger = Raise(logging.WARNING), logging.getLogger("transformers")
    transformers_logger.addHandler(handler)
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("error", DeprecationWarning)
            warnings.simplefilter("error", FutureWarning)
            warnings.filterwarnings("ignore", module="torch")  # e.g. torch.jit.script_method, at inductor's import
            yield
    finally:
        transformers_logger.removeHandler(handler)


def test_the_harness_catches_what_transformers_logs_and_warns():
    """The harness can fail: transformers' own deprecation of a generation_config passed beside generation settings
    (logged), and a FutureWarning of any module but torch (raised)."""
    from transformers import LlamaConfig, LlamaForCausalLM

    model = LlamaForCausalLM(LlamaConfig(vocab_size=16, hidden_size=16, intermediate_size=32, num_hidden_layers=1,
                                         num_attention_heads=2, num_key_value_heads=1)).eval()  # fmt: skip
    with transformers_warnings_as_errors(), pytest.raises(AssertionError, match="is deprecated"):
        model.generate(torch.tensor([[1, 2]]), generation_config=GenerationConfig(do_sample=False), max_new_tokens=2)
    with transformers_warnings_as_errors(), pytest.raises(FutureWarning):
        warnings.warn("going away", FutureWarning, stacklevel=1)


@pytest.fixture(scope="module")
def untrained_toy(tmp_path_factory):
    """The demo's toy target and draft head, untrained (built in seconds): the demo's calls, not its results. The
    action tokens' output rows are scaled up so that greedy decoding lands on action tokens, as the trained toy's
    does (the action prior drafts from them)."""
    from hf_specvla import DraftHead, enable_speculation
    from hf_specvla.benchmarks.toy import ACTION_DIM, TOY_HEAD_SETTINGS, ToyPipeline, build_toy_target

    target, tokenizer, action_tokenizer = build_toy_target(seed=0)
    with torch.no_grad():
        target.get_output_embeddings().weight[-action_tokenizer.n_bins :] *= 8.0
    target = enable_speculation(target.eval())
    torch.manual_seed(0)
    head = DraftHead.from_target(
        target, action_tokenizer, action_dim=ACTION_DIM, num_draft_tokens=ACTION_DIM - 1, **TOY_HEAD_SETTINGS
    ).eval()  # the demo's head: drafts from the image too
    return ToyPipeline(str(tmp_path_factory.mktemp("toy")), target, tokenizer, action_tokenizer, head)


# the whole demo command, its verdict's rows or every table: ~65 s each (the fast tier keeps predict_action's and the
# port's calls warning-free, and tests/cli/test_demo.py the verdict's reading)
@pytest.mark.commands
@pytest.mark.parametrize("all_tables", [False, True], ids=["verdict", "all"])
def test_the_demos_calls_warn_nothing_and_it_ends_with_its_verdict(untrained_toy, monkeypatch, capsys, all_tables):
    """``hf-specvla demo --train`` with small arguments (the verdict's rows: eager and compiled greedy, `exact`, the
    head, a relaxed r; with ``--all-tables`` every kind of row: transformers' assisted generation eager and
    compiled, strict and relaxed chains, the prior, Jacobi, the head's tree; compiled with dynamo's cheap eager
    backend) on an untrained toy: no deprecation or duplicate warning from transformers, and the last screen is the
    verdict, naming the file that holds the full tables."""
    from hf_specvla.benchmarks import toy
    from hf_specvla.cli.demo import REPORT_FILE

    monkeypatch.setattr(toy, "build_toy_pipeline", lambda *args, **kwargs: untrained_toy)
    monkeypatch.setattr("hf_specvla.speculative.compiled_decoding_kwargs", eager_backend_compiled_kwargs)
    argv = ["demo", "--train", "--output-dir", untrained_toy.output_dir, "--prompts", "1", "--repeats", "1",
            "--episodes", "1", "--chain-lengths", "2", "--bin-tolerances", "1"]  # fmt: skip
    with transformers_warnings_as_errors():
        assert main(argv + ["--all-tables"] * all_tables) == 0
    out = capsys.readouterr().out
    screen = out[out.index("\nVerdict (") :]
    for role in ("| greedy |", "| compiled greedy |", "| `exact` |", "| draft head |", "| relaxed r=1 |"):
        assert role in screen
    assert "In one sentence: " in screen and screen.rstrip().endswith(f"{untrained_toy.output_dir}/{REPORT_FILE}")
    assert "Accepted drafts by token position" not in out  # the breakdowns are in the file, not on the screen
    report = (Path(untrained_toy.output_dir) / REPORT_FILE).read_text()
    parts = ["## Moving-dot episodes", "Accepted drafts by token position", "## Verdict", "In one sentence: "]
    if all_tables:
        parts += ["## Held-out scenes", "| assisted (transformers) |", "| jacobi r=0:compile |"]
    else:  # the verdict's rows alone: nothing else compiled or timed
        assert "## Held-out scenes" not in report and "| jacobi r=0:compile |" not in report
    for part in parts:
        assert part in report


def test_transformers_assisted_generation_with_the_early_exit_assistant_is_greedy(untrained_toy):
    """The early-exit assistant's generate (settings folded into one config, the target's MinNewTokens processor
    left to the one it builds) drafts as before: transformers' assisted generation still returns greedy's tokens."""
    from hf_specvla.benchmarks.toy import ACTION_DIM, early_exit_assistant, split_scenes, toy_inputs

    target, assistant = untrained_toy.target, early_exit_assistant(untrained_toy.target)
    length = dict(max_new_tokens=ACTION_DIM, min_new_tokens=ACTION_DIM, do_sample=False)
    for scene in split_scenes()[1][:3]:
        inputs = toy_inputs([scene], untrained_toy.tokenizer)
        with transformers_warnings_as_errors():
            assisted = target.generate(**inputs, **length, assistant_model=assistant)
        torch.testing.assert_close(assisted, target.generate(**inputs, **length), rtol=0, atol=0)


@pytest.fixture(scope="module")
def small_policy():
    from hf_specvla import ActionNormalizer
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

    from .policies.test_policy import INSTRUCTIONS, SMALL

    actions = ActionNormalizer(q01=[-1.0, -0.5, -1.0, -1.0], q99=[1.0, 0.5, 0.2, 1.0], mask=[True, True, True, False])
    states = ActionNormalizer(q01=[-0.1, 0.5, 0.05, 0.0], q99=[0.1, 0.9, 0.3, 1.0])
    torch.manual_seed(0)
    return VLAPolicy.build(INSTRUCTIONS, actions, states, VLAPolicyConfig(**SMALL))


def test_the_policys_predict_action_warns_nothing(small_policy, monkeypatch):
    """VLAPolicy.predict_action: greedy, the presets (compiled: a static cache and a CompileConfig), a draft head, the
    prior, and each of them beside a caller's ``generation_config`` (whose settings used to go beside it, which
    transformers deprecates); the actions stay greedy's."""
    from hf_specvla import DraftHead
    from hf_specvla.policies import DecodingMethod

    monkeypatch.setattr("hf_specvla.speculative.compiled_decoding_kwargs", eager_backend_compiled_kwargs)
    policy = small_policy
    torch.manual_seed(1)
    head = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=policy.config.action_dim).eval()
    rng = np.random.default_rng(0)
    image, state = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8), np.array([0.0, 0.6, 0.2, 0.5])
    calls = {
        "greedy": {},
        "greedy:compile": DecodingMethod.parse("greedy:compile").generate_kwargs(draft_head=None),
        "exact": DecodingMethod.parse("exact").generate_kwargs(draft_head=None),
        "prior+jacobi+tree:compile": DecodingMethod.parse("prior+jacobi+tree:compile").generate_kwargs(head),
        "head": dict(assistant_model=head, num_draft_tokens=2),
    }
    with transformers_warnings_as_errors():
        policy.reset()
        greedy = [policy.predict_action(image, "reach the goal", state) for _ in range(2)]
        for name, kwargs in calls.items():
            for config in (None, GenerationConfig(do_sample=False)):
                policy.reset()
                for step in range(2):  # the second step drafts from the first's action
                    given = kwargs if config is None else dict(kwargs, generation_config=config)
                    action = policy.predict_action(image, "reach the goal", state, **given)
                    np.testing.assert_array_equal(action, greedy[step], err_msg=f"{name}, generation_config={config}")
    policy.reset()


def test_the_openvla_ports_predict_action_warns_nothing():
    """OpenVLAForActionPrediction.predict_action, the official call and with a ``generation_config`` beside a
    compiled method's settings and a drafter; the actions stay greedy's."""
    from hf_specvla import ComposedDrafter, JacobiDrafter
    from hf_specvla.openvla import OpenVLAForActionPrediction

    from .openvla.test_openvla import pixel_values, prompt_ids, tiny_config

    torch.manual_seed(0)
    model = OpenVLAForActionPrediction(tiny_config()).eval()
    with torch.no_grad():  # greedy decoding lands on action tokens, as a trained OpenVLA's does (as tiny_openvla)
        model.get_output_embeddings().weight[31744:32000] *= 8.0
    call = dict(input_ids=prompt_ids(), pixel_values=pixel_values(), unnorm_key="tiny_dataset")
    compiled = eager_backend_compiled_kwargs()
    with transformers_warnings_as_errors():
        greedy = model.predict_action(**call, do_sample=False)
        for kwargs in ({}, compiled, dict(compiled, assistant_model=ComposedDrafter([JacobiDrafter()]))):
            action = model.predict_action(**call, generation_config=GenerationConfig(do_sample=False), **kwargs)
            np.testing.assert_array_equal(action, greedy, err_msg=str(kwargs))


def test_our_future_warning_points_at_the_callers_line(tiny_llama, random_draft):
    """``generate(..., draft_head=...)`` is deprecated: its FutureWarning names the caller's file, not
    transformers'."""
    from hf_specvla.speculative import speculative_generate

    with pytest.warns(FutureWarning, match="draft_head") as caught:
        tiny_llama.generate(torch.tensor([[1, 70, 80]]), custom_generate=speculative_generate,
                            draft_head=random_draft, max_new_tokens=3, do_sample=False)  # fmt: skip
    assert [w.filename for w in caught] == [__file__]
