"""One speculation setting passed whole (engine v6 item 1): ``generate(speculation=SpeculationConfig(...))`` gives the
tokens the same settings as loose keywords give (and the ``custom_generate`` form), the setting is frozen, hashable and
equal for equal settings, and each refusal names its field."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from transformers import LlamaForCausalLM

from hf_specvla import DraftHeadDrafter, DraftTreeConfig, JacobiDrafter, SpeculationConfig
from hf_specvla.speculative import ComposedDrafter, NoDrafter, speculative_generate

from ..conftest import tiny_llama_config

NEW_TOKENS = 7


def prompt(seed: int, batch: int = 1) -> torch.Tensor:
    return torch.randint(6, 64, (batch, 9), generator=torch.Generator().manual_seed(seed))


@pytest.mark.parametrize("drafter", ["jacobi", "head", "tree", "composed", "none"])
def test_a_setting_passed_whole_gives_the_loose_keywords_tokens(tiny_llama, random_draft, action_tokenizer, drafter):
    from hf_specvla import ActionLayout

    assistant = {
        "jacobi": JacobiDrafter(),
        "head": random_draft,
        "tree": DraftHeadDrafter(random_draft, tree=DraftTreeConfig(top_k=2, depth=3, total_tokens=5)),
        "composed": ComposedDrafter([JacobiDrafter(fill=False), DraftHeadDrafter(random_draft)]),
        "none": NoDrafter(),
    }[drafter]
    layout = ActionLayout(action_tokenizer, 7)
    plain = LlamaForCausalLM(tiny_llama_config()).eval()
    plain.load_state_dict(tiny_llama.state_dict())
    for seed in range(2):
        input_ids = prompt(seed, batch=2)
        common = dict(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False, return_dict_in_generate=True)
        greedy = tiny_llama.generate(**{k: v for k, v in common.items() if k != "return_dict_in_generate"})
        loose = tiny_llama.generate(**common, assistant_model=assistant, bin_tolerance=0, action_layout=layout)
        whole = tiny_llama.generate(**common, speculation=SpeculationConfig(drafter=assistant, action_layout=layout))
        assert torch.equal(whole.sequences, loose.sequences) and torch.equal(whole.sequences, greedy)
        assert whole.speculation.num_target_forwards == loose.speculation.num_target_forwards
        # the call's drafter beside a setting without one (a robot's, made each call); draft_ids beside either
        drafts = greedy[:, 9:12]
        beside = tiny_llama.generate(**common, assistant_model=assistant, draft_ids=drafts,
                                     speculation=SpeculationConfig(action_layout=layout))  # fmt: skip
        assert torch.equal(beside.sequences, greedy)
        # transformers' hook on a model without the mixin takes the setting whole
        hooked = plain.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False,
                                custom_generate=speculative_generate,
                                speculation=SpeculationConfig(drafter=assistant))  # fmt: skip
        assert torch.equal(hooked, greedy)


def test_a_setting_is_frozen_hashable_and_equal_for_equal_settings(random_draft):
    def make():
        tree = DraftHeadDrafter(random_draft, tree=DraftTreeConfig(top_k=2, depth=3, total_tokens=5))
        return SpeculationConfig(drafter=ComposedDrafter([JacobiDrafter(fill=False), tree]), bin_tolerance=[2, 2, 0],
                                 max_relaxed_per_action=1)  # fmt: skip

    first, second = make(), make()
    assert first == second and hash(first) == hash(second) and len({first, second}) == 1
    assert first != dataclasses.replace(first, bin_tolerance=[2, 2, 1])
    assert first != dataclasses.replace(first, drafter=JacobiDrafter())
    assert SpeculationConfig(drafter=random_draft) != SpeculationConfig(drafter=random_draft, num_draft_tokens=2)
    with pytest.raises(dataclasses.FrozenInstanceError):
        first.bin_tolerance = 4


def test_each_refusal_names_its_field(tiny_llama, random_draft):
    input_ids = prompt(3)
    with pytest.raises(TypeError, match="SpeculationConfig.drafter .* must be a hf_specvla DraftHead or Drafter.*str"):
        SpeculationConfig(drafter="gpt2")
    with pytest.raises(ValueError, match="num_draft_tokens applies to a bare DraftHead"):
        SpeculationConfig(drafter=JacobiDrafter(), num_draft_tokens=3)
    with pytest.raises(TypeError, match="max_new_tokens"):
        SpeculationConfig(max_new_tokens=2)  # the action's length is generate's
    with pytest.raises(TypeError, match="do_sample"):
        SpeculationConfig(do_sample=True)  # sampling is generate's (its generation config)
    with pytest.raises(ValueError, match="confidence_gate"):
        SpeculationConfig(confidence_gate=0.0)
    with pytest.raises(ValueError, match=r"speculation=SpeculationConfig\(\.\.\.\) and bin_tolerance"):
        tiny_llama.generate(input_ids, speculation=SpeculationConfig(drafter=JacobiDrafter()), bin_tolerance=1)
    with pytest.raises(ValueError, match=r"speculation=SpeculationConfig\(\.\.\.\) and drafter"):
        tiny_llama.generate(input_ids, speculation=SpeculationConfig(drafter=JacobiDrafter()),
                            assistant_model=random_draft)  # fmt: skip
    with pytest.raises(TypeError, match="speculation must be a hf_specvla SpeculationConfig.*dict"):
        tiny_llama.generate(input_ids, speculation={"bin_tolerance": 1}, assistant_model=random_draft)
    with pytest.raises(ValueError, match="needs something to draft with"):
        tiny_llama.generate(input_ids, speculation=SpeculationConfig(), max_new_tokens=3)


def test_the_acceptance_rule_is_built_once_per_layout_and_shared_by_a_sessions_calls(action_tokenizer):
    """Engine v6 item 1, "the acceptance rule built once": a setting builds its rule once per layout, and a setting
    folded from it by adding a call's drafter (a robot's call through a session) uses the same rule."""
    from hf_specvla import ActionLayout

    layouts = [ActionLayout(action_tokenizer, 7), ActionLayout(action_tokenizer, 4)]
    settings = SpeculationConfig(bin_tolerance=2, max_relaxed_per_action=1)
    rule = settings.acceptance_rule(layouts[0])
    assert settings.acceptance_rule(layouts[0]) is rule and not rule.is_lossless
    assert settings.acceptance_rule(layouts[1]) is not rule  # another layout, another rule
    for _ in range(2):  # each call's drafter folded in: the rule is the session setting's
        call = SpeculationConfig.fold(settings, {"drafter": JacobiDrafter()})
        assert call.acceptance_rule(layouts[0]) is rule and call == dataclasses.replace(settings, drafter=call.drafter)
    other = dataclasses.replace(settings, bin_tolerance=1)  # other acceptance: its own rules
    assert other.acceptance_rule(layouts[0]) is not rule
