"""A decoding plan is checked as its loose options are, once, when it is made (reliability-6 item 2), and a policy's
decoder session follows a changed generation config (item 1, through ``predict_action(decoding=...)``)."""

from __future__ import annotations

import inspect

import numpy as np
import pytest
import torch

from hf_specvla import ActionNormalizer
from hf_specvla.policies import DecodingMethod, VLAPolicy, VLAPolicyConfig
from hf_specvla.policies.decoding_methods import COMPILE_SETTINGS, DecodingPlan


@pytest.mark.parametrize(
    "fields, error, words",
    [
        (dict(compile={"max_new_tokens": 2}), ValueError, r"DecodingPlan.compile holds 'max_new_tokens'.*policy's own"),
        (dict(acceptance={"max_new_tokens": 2}), ValueError, r"DecodingPlan.acceptance holds 'max_new_tokens'"),
        (dict(acceptance={"do_sample": True}), ValueError, r"acceptance holds 'do_sample'.*generation_config="),
        (dict(compile={"do_sample": True}), ValueError, r"DecodingPlan.compile holds 'do_sample'"),
        (dict(acceptance={"compile_config": None}), ValueError, r"'compile_config'.*belongs in DecodingPlan.compile"),
        (dict(compile={"bin_tolerance": 2}), ValueError, r"'bin_tolerance'.*belongs in DecodingPlan.acceptance"),
        (dict(acceptance=None), TypeError, r"DecodingPlan.acceptance must be a mapping.*got NoneType"),
        (dict(compile=["static"]), TypeError, r"DecodingPlan.compile must be a mapping.*got list"),
        (dict(compile="static"), TypeError, r"DecodingPlan.compile must be a mapping.*got str"),
        (
            dict(compile={"compile_config": "default"}),
            TypeError,
            r"compile_config must be a transformers CompileConfig",
        ),
        (dict(acceptance={"confidence_gate": 2.0}), ValueError, r"confidence_gate=2.0"),
        (dict(num_draft_tokens=0), ValueError, r"num_draft_tokens must be an int >= 1"),
        (dict(action_prior="yes"), TypeError, r"DecodingPlan.action_prior must be True or False"),
        (dict(assistant_model="gpt2"), TypeError, r"DecodingPlan.assistant_model must be a hf_specvla Drafter"),
    ],
)
def test_a_plan_refuses_what_is_not_its_fields_own_when_it_is_made(fields, error, words):
    with pytest.raises(error, match=words):
        DecodingPlan(**fields)


def test_a_plan_is_hashable_equal_for_equal_settings_and_read_only():
    from hf_specvla.speculative import RULE_ARGUMENTS, make_acceptance_rule

    plans = [DecodingMethod.parse("prior+jacobi:r=4/4/4/0,m=1:compile").plan(None, action_dim=4) for _ in range(2)]
    assert plans[0] == plans[1] and hash(plans[0]) == hash(plans[1]) and len({plans[0], plans[1]}) == 1
    assert plans[0] != DecodingMethod.parse("prior+jacobi:r=3/4/4/0,m=1:compile").plan(None, action_dim=4)
    assert dict(plans[0].acceptance) == {"bin_tolerance": [4, 4, 4, 0], "max_relaxed_per_action": 1}
    with pytest.raises(TypeError):
        plans[0].acceptance["bin_tolerance"] = 0  # read-only
    tolerance = [1, 1, 1, 0]
    plan = DecodingPlan(acceptance={"bin_tolerance": tolerance})
    tolerance[0] = 9  # the caller's list changed afterwards: the plan holds its own
    assert plan.acceptance["bin_tolerance"] == [1, 1, 1, 0]
    # the settings the plan checks are the engine's, named once (no torch at the CLI's import: a test keeps them equal)
    assert RULE_ARGUMENTS == tuple(
        p for p in inspect.signature(make_acceptance_rule).parameters if p != "action_layout"
    )
    assert set(COMPILE_SETTINGS) == set(__import__("hf_specvla.speculative", fromlist=["x"]).compiled_decoding_kwargs())


@pytest.fixture(scope="module")
def policy():
    actions = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4)
    states = ActionNormalizer(q01=[-0.5, 0.3, 0.0, 0.0], q99=[0.5, 1.0, 0.4, 1.0])
    config = VLAPolicyConfig(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1,
                             text_hidden_size=64, text_layers=2, text_heads=4)  # fmt: skip
    return VLAPolicy.build(["reach the goal"], actions, states, config, seed=5)


@pytest.mark.parametrize("method", ["exact", "none"])
def test_predict_action_through_its_session_follows_suppressed_tokens_set_between_calls(policy, method, monkeypatch):
    """``model.generation_config.suppress_tokens`` set between two calls of an episode: the policy's decoder session
    (its default) returns the action plain greedy decoding returns after the change, not the old one. Compiled with
    dynamo's ``eager`` backend (the session's logic is this test's; inductor's graphs of a policy are test_policy's)."""
    from ..cli.test_cli import eager_backend_compiled_kwargs

    monkeypatch.setattr("hf_specvla.speculative.compiled_decoding_kwargs", eager_backend_compiled_kwargs)
    rng = np.random.default_rng(0)
    image, state = rng.integers(0, 256, (32, 32, 3), dtype=np.uint8), np.array([0.0, 0.6, 0.2, 1.0])
    plan = DecodingMethod.parse(method, action_dim=4).plan(None, action_dim=4)
    policy.model.generation_config.suppress_tokens = None
    try:
        before = policy.predict_action(image, "reach the goal", state)
        policy.reset()
        for _ in range(2):  # the session keeps the shape; the prior's drafts are right the second time
            assert np.array_equal(policy.predict_action(image, "reach the goal", state, decoding=plan), before)
        _, out = policy.predict_action(image, "reach the goal", state, return_output=True)
        first_token = int(out.sequences[0, -policy.config.action_tokens])
        policy.model.generation_config.suppress_tokens = [first_token]
        after = policy.predict_action(image, "reach the goal", state)  # plain greedy after the change
        assert not np.array_equal(after, before)
        assert np.array_equal(policy.predict_action(image, "reach the goal", state, decoding=plan), after)
    finally:
        policy.model.generation_config.suppress_tokens = None
    assert np.array_equal(policy.predict_action(image, "reach the goal", state, decoding=plan), before)
    assert torch.is_grad_enabled()
