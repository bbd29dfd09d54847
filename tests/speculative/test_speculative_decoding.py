"""The decode loop behind generate(): lossless at r=0 for every drafter and tree, bounded at r>0, exact on
stopping, consistent caches after a non-leftmost path, clear on bad input."""

import pytest
import torch
from transformers import LlamaForCausalLM, StaticCache

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    ComposedDrafter,
    Drafter,
    DraftHead,
    DraftHeadDrafter,
    DraftTree,
    DraftTreeConfig,
    SpeculativeDecoderOnlyOutput,
    disable_speculation,
    enable_speculation,
)
from hf_specvla.speculative import CACHE_KEY, cache_of
from hf_specvla.speculative.drafter import DraftSession
from hf_specvla.speculative.drafters.draft_head import embed_tokens
from hf_specvla.speculative.masks import causal_mask

from ..conftest import llava_prompt, tiny_llama_config


class OracleDrafter(Drafter):
    """Drafts a chain of the greedy continuation itself after the prefill (optionally wrong at one depth)."""

    name = "oracle"

    def __init__(self, continuation: torch.Tensor, length: int, corrupt_at: int | None = None):
        self.continuation, self.length, self.corrupt_at = continuation, length, corrupt_at

    def start(self, context):
        drafter = self

        class Session(DraftSession):
            def propose(self, draft_round):
                if draft_round.at_prefill:
                    return DraftTree.empty()
                start = draft_round.sequence.shape[1]
                drafts = drafter.continuation[0, start : start + min(drafter.length, draft_round.max_depth)].tolist()
                drafts += [7] * (min(drafter.length, draft_round.max_depth) - len(drafts))  # past the reference's end
                if drafter.corrupt_at is not None and drafter.corrupt_at < len(drafts):
                    drafts[drafter.corrupt_at] = (drafts[drafter.corrupt_at] + 1) % 320
                return DraftTree.from_paths([drafts], "oracle")

        return Session()


class FixedTreeDrafter(Drafter):
    """Proposes one hand-built tree at the prefill, nothing afterwards."""

    name = "fixed"

    def __init__(self, tree: DraftTree):
        self.tree = tree

    def start(self, context):
        tree = self.tree

        class Session(DraftSession):
            def propose(self, draft_round):
                return tree if draft_round.at_prefill else DraftTree.empty()

        return Session()


def random_prompts(n: int, seed: int = 0):
    generator = torch.Generator().manual_seed(seed)
    return [
        torch.randint(3, 320, (1, int(torch.randint(2, 12, (1,), generator=generator))), generator=generator)
        for _ in range(n)
    ]


def greedy(model, **inputs):
    return model.generate(**inputs, do_sample=False)


# ------------------------------------------------------------------------------- lossless
def test_r0_equals_greedy_llama_untrained_draft(tiny_llama, random_draft):
    accept_lengths = []
    for input_ids in random_prompts(40):
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=12)
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=12,
            do_sample=False,
            assistant_model=random_draft,
            return_dict_in_generate=True,
        )
        assert torch.equal(out.sequences, expected)
        accept_lengths += out.speculation.accept_lengths
    # an untrained head is (almost) always rejected: about one token per target forward
    assert sum(accept_lengths) / len(accept_lengths) < 1.2


def test_r0_equals_greedy_llava(tiny_llava, random_llava_draft):
    generator = torch.Generator().manual_seed(0)
    for i in range(20):
        prompt = llava_prompt(generator, text_len=2 + i % 5)
        expected = greedy(tiny_llava, **prompt, max_new_tokens=9)
        out = tiny_llava.generate(**prompt, max_new_tokens=9, do_sample=False, assistant_model=random_llava_draft)
        assert torch.equal(out, expected)


def test_perfect_draft_is_fully_accepted(tiny_llama):
    for input_ids in random_prompts(10, seed=1):
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=14)
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=14,
            do_sample=False,
            assistant_model=OracleDrafter(expected, 4),
            return_dict_in_generate=True,
        )
        assert torch.equal(out.sequences, expected)
        # prefill emits 1, then every verification accepts all 4 drafts + 1 bonus (the last one is cut at max length)
        assert out.speculation.accept_lengths == [1, 5, 5, 3]
        assert out.speculation.acceptance_rate_per_position == [1.0, 1.0, 1.0, 1.0]


@pytest.mark.parametrize("corrupt_at", [0, 2])
def test_wrong_draft_is_rejected_from_that_position(tiny_llama, corrupt_at):
    input_ids = random_prompts(1, seed=2)[0]
    expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=10)
    out = tiny_llama.generate(
        input_ids=input_ids,
        max_new_tokens=10,
        do_sample=False,
        assistant_model=OracleDrafter(expected, 4, corrupt_at),
        return_dict_in_generate=True,
    )
    assert torch.equal(out.sequences, expected)  # caches stay consistent after every rejection
    stats = out.speculation
    assert all(n == corrupt_at + 1 for n in stats.accept_lengths[1:-1])  # accepts corrupt_at drafts + bonus
    assert stats.accepted_per_position[corrupt_at] == 0


def test_stats_add_up(tiny_llama, random_draft):
    out = tiny_llama.generate(
        input_ids=random_prompts(1)[0],
        max_new_tokens=11,
        do_sample=False,
        assistant_model=random_draft,
        return_dict_in_generate=True,
    )
    stats = out.speculation
    assert isinstance(out, SpeculativeDecoderOnlyOutput)
    assert stats.num_new_tokens == 11 == sum(stats.accept_lengths)
    assert stats.num_target_forwards == len(stats.accept_lengths)
    assert stats.num_draft_forwards > 0 and stats.total_seconds >= stats.target_seconds + stats.draft_seconds
    assert all(a <= d for a, d in zip(stats.accepted_per_position, stats.drafted_per_position))


# ------------------------------------------------------------------------------- stopping and processors
def test_eos_and_max_length_stop_where_greedy_stops(tiny_llama, random_draft):
    input_ids = random_prompts(1, seed=3)[0]
    prompt_len = input_ids.shape[1]
    reference = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=10)
    eos = int(reference[0, prompt_len + 3])  # make the 4th generated token the EOS
    expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=10, eos_token_id=eos)
    assert expected.shape[1] <= prompt_len + 4
    out = tiny_llama.generate(  # drafts run past the EOS
        input_ids=input_ids, max_new_tokens=10, do_sample=False, eos_token_id=eos,
        assistant_model=OracleDrafter(reference, 6),
    )  # fmt: skip
    assert torch.equal(out, expected)
    # the same inside the prefill: draft_ids that are right and run past the EOS / past max_length
    out = tiny_llama.generate(
        input_ids=input_ids, max_new_tokens=10, do_sample=False, eos_token_id=eos,
        draft_ids=reference[:, prompt_len:], return_dict_in_generate=True,
    )  # fmt: skip
    assert torch.equal(out.sequences, expected) and out.speculation.num_target_forwards == 1
    out = tiny_llama.generate(
        input_ids=input_ids, max_new_tokens=6, do_sample=False, draft_ids=reference[:, prompt_len:],
        return_dict_in_generate=True,
    )  # fmt: skip
    assert torch.equal(out.sequences, reference[:, : prompt_len + 6]) and out.speculation.accept_lengths == [6]
    one = tiny_llama.generate(input_ids=input_ids, max_new_tokens=1, do_sample=False, assistant_model=random_draft)
    assert torch.equal(one, reference[:, : input_ids.shape[1] + 1])


def test_logits_processors_apply_to_every_verified_position(tiny_llama, random_draft):
    input_ids = random_prompts(1, seed=4)[0]
    kwargs = dict(max_new_tokens=10, repetition_penalty=1.5, suppress_tokens=list(range(100, 200)))
    expected = greedy(tiny_llama, input_ids=input_ids, **kwargs)
    out = tiny_llama.generate(
        input_ids=input_ids, do_sample=False, assistant_model=OracleDrafter(expected, 4), **kwargs
    )
    assert torch.equal(out, expected)
    # a tree inside the prefill: the right continuation on a non-leftmost branch, processors per node
    generated = expected[0, input_ids.shape[1] :].tolist()
    wrong = [generated[0], (generated[1] + 1) % 320, *generated[2:6]]
    candidates = torch.tensor([[wrong, generated[:6]]])
    out = tiny_llama.generate(input_ids=input_ids, do_sample=False, draft_ids=candidates, **kwargs)
    assert torch.equal(out, expected)
    generated = out[0, input_ids.shape[1] :]
    assert not bool(((generated >= 100) & (generated < 200)).any())


def test_left_padded_prompt(tiny_llama, random_draft):
    input_ids = torch.cat([torch.zeros(1, 3, dtype=torch.long), random_prompts(1, seed=5)[0]], dim=1)
    attention_mask = (input_ids != 0).long()
    attention_mask[:, 3:] = 1
    expected = greedy(tiny_llama, input_ids=input_ids, attention_mask=attention_mask, max_new_tokens=8)
    out = tiny_llama.generate(
        input_ids=input_ids,
        attention_mask=attention_mask,
        max_new_tokens=8,
        do_sample=False,
        assistant_model=random_draft,
    )
    assert torch.equal(out, expected)


def test_left_padded_prompt_with_drafts_in_the_prefill(tiny_llama):
    input_ids = torch.cat([torch.zeros(1, 3, dtype=torch.long), random_prompts(1, seed=9)[0]], dim=1)
    attention_mask = torch.ones_like(input_ids)
    attention_mask[:, :3] = 0
    expected = greedy(tiny_llama, input_ids=input_ids, attention_mask=attention_mask, max_new_tokens=8)
    generated = expected[0, input_ids.shape[1] :].tolist()
    wrong = [generated[0], (generated[1] + 1) % 320, *generated[2:5]]
    candidates = torch.tensor([[wrong, generated[:5]]])  # the right one second
    out = tiny_llama.generate(
        input_ids=input_ids, attention_mask=attention_mask, max_new_tokens=8, do_sample=False,
        draft_ids=candidates, return_dict_in_generate=True,
    )  # fmt: skip
    assert torch.equal(out.sequences, expected) and out.speculation.accept_lengths[0] == 6


# ------------------------------------------------------------------------------- relaxed acceptance
def assert_within_tolerance(model, prompt: dict, sequence: torch.Tensor, tolerance: list[int], action_tokenizer):
    """Every generated action token is within tolerance[dim] bins of the target's greedy token given the same
    prefix; every non-action token equals it."""
    prompt_len = prompt["input_ids"].shape[1]
    logits = model(**dict(prompt, input_ids=sequence)).logits[0]  # [L, V]
    action_count = 0
    for position in range(prompt_len, sequence.shape[1]):
        token, target = int(sequence[0, position]), int(logits[position - 1].argmax())
        if action_tokenizer.is_action_token(token) and action_tokenizer.is_action_token(target):
            assert abs(token - target) <= tolerance[action_count % len(tolerance)]
        else:
            assert token == target
        action_count += int(action_tokenizer.is_action_token(token))


@pytest.mark.parametrize("bin_tolerance", [3, 40, [40, 0, 40, 0, 40, 0, 0]])
def test_relaxed_tokens_stay_within_tolerance(tiny_llama, random_draft, action_tokenizer, bin_tolerance):
    tolerance = bin_tolerance if isinstance(bin_tolerance, list) else [bin_tolerance] * 7
    relaxed_accepts = 0
    for input_ids in random_prompts(25, seed=6):
        out = tiny_llama.generate(
            input_ids=input_ids,
            max_new_tokens=14,
            min_new_tokens=14,
            do_sample=False,
            assistant_model=random_draft,
            bin_tolerance=bin_tolerance,
            return_dict_in_generate=True,
        )
        assert_within_tolerance(tiny_llama, {"input_ids": input_ids}, out.sequences, tolerance, action_tokenizer)
        relaxed_accepts += sum(out.speculation.accepted_per_position)
    if max(tolerance) >= 40:
        assert relaxed_accepts > 0  # the invariant was exercised on accepted drafts, not only on bonus tokens


# ------------------------------------------------------------------------------- bad input
def test_sampling_and_beams_are_rejected(tiny_llama, random_draft):
    batch = torch.randint(3, 320, (2, 5))
    with pytest.raises(ValueError, match="greedy only"):  # sampling is verified losslessly, but never relaxed
        tiny_llama.generate(input_ids=batch[:1], max_new_tokens=3, do_sample=True, assistant_model=random_draft,
                            bin_tolerance=2)  # fmt: skip
    with pytest.raises(ValueError, match="num_beams=1"):
        tiny_llama.generate(input_ids=batch[:1], max_new_tokens=3, num_beams=2, assistant_model=random_draft)


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(bin_tolerance=-1), ValueError, ">= 0"),
        (dict(bin_tolerance=0.5), TypeError, "non-negative int"),
        (dict(bin_tolerance=[1, 2, 3]), ValueError, "7 dimensions"),
        (dict(num_draft_tokens=0), ValueError, "num_draft_tokens"),
    ],
)
def test_bad_speculation_settings(tiny_llama, random_draft, kwargs, error, match):
    with pytest.raises(error, match=match):
        tiny_llama.generate(input_ids=random_prompts(1)[0], max_new_tokens=3, assistant_model=random_draft, **kwargs)


def test_mismatched_draft_is_rejected(tiny_llama):
    other = LlamaForCausalLM(tiny_llama_config(hidden_size=32, num_attention_heads=2, num_key_value_heads=1))
    draft = DraftHead.from_target(other)
    with pytest.raises(ValueError, match="does not fit"):
        tiny_llama.generate(input_ids=random_prompts(1)[0], max_new_tokens=3, assistant_model=draft)


def test_other_assistants_fall_through_to_transformers(tiny_llama):
    input_ids = random_prompts(1, seed=7)[0]
    expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=6)
    assistant = LlamaForCausalLM(tiny_llama_config(num_hidden_layers=1)).eval()
    out = tiny_llama.generate(input_ids=input_ids, max_new_tokens=6, do_sample=False, assistant_model=assistant)
    assert torch.equal(out, expected)  # transformers' own assisted decoding is lossless too
    with pytest.raises(ValueError, match="bin_tolerance only apply"):
        tiny_llama.generate(input_ids=input_ids, max_new_tokens=6, assistant_model=assistant, bin_tolerance=2)


def test_enable_disable_keeps_the_model_class(tmp_path):
    model = LlamaForCausalLM(tiny_llama_config())
    enable_speculation(model)
    assert type(model).__name__ == "LlamaForCausalLM" and isinstance(model, LlamaForCausalLM)
    model.save_pretrained(tmp_path)
    assert '"LlamaForCausalLM"' in (tmp_path / "config.json").read_text()
    assert type(enable_speculation(model)) is type(model)  # idempotent
    disable_speculation(model)
    assert type(model) is LlamaForCausalLM
    with pytest.raises(TypeError, match="PreTrainedModel"):
        enable_speculation(torch.nn.Linear(2, 2))


def test_custom_generate_callable_without_the_mixin(random_draft, tiny_llama):
    from hf_specvla import speculative_generate

    plain = LlamaForCausalLM(tiny_llama_config())
    plain.load_state_dict(tiny_llama.state_dict())
    input_ids = random_prompts(1, seed=8)[0]
    expected = greedy(plain.eval(), input_ids=input_ids, max_new_tokens=5)
    out = plain.generate(
        input_ids=input_ids,
        max_new_tokens=5,
        do_sample=False,
        custom_generate=speculative_generate,
        draft_head=random_draft,
    )
    assert torch.equal(out, expected)


# ------------------------------------------------------------------------------- engine v2: trees, prefill drafts
def greedy_continuation(model, prompt: dict, n: int) -> list[int]:
    out = model.generate(**prompt, max_new_tokens=n, min_new_tokens=n, do_sample=False)
    return out[0, prompt["input_ids"].shape[1] :].tolist()


@pytest.mark.parametrize("kind", ["right", "wrong_at_2", "random"])
def test_prior_drafts_at_r0_equal_greedy(tiny_llava, action_tokenizer, kind):
    """ActionPriorDrafter candidates (right, wrong at a known position, random) verified in the prefill."""
    layout = ActionLayout(action_tokenizer, 7)
    generator = torch.Generator().manual_seed(11)
    for i in range(6):
        prompt = llava_prompt(generator, text_len=2 + i % 3)
        expected = greedy_continuation(tiny_llava, prompt, 7)
        right = [t if action_tokenizer.is_action_token(t) else 64 for t in expected]
        previous = {
            "right": [right],
            "wrong_at_2": [right[:2] + [64 + (right[2] - 64 + 128) % 256] + right[3:]],  # far: no alternative fixes it
            "random": [torch.randint(64, 320, (7,), generator=generator).tolist() for _ in range(2)],
        }[kind]
        out = tiny_llava.generate(
            **prompt, max_new_tokens=7, min_new_tokens=7, do_sample=False, return_dict_in_generate=True,
            assistant_model=ActionPriorDrafter(previous, layout),
        )  # fmt: skip
        assert out.sequences[0, -7:].tolist() == expected
        if kind == "right" and right == expected:
            assert out.speculation.num_target_forwards == 1  # all right at the prefill: one target forward
        if kind == "wrong_at_2" and right == expected:
            assert out.speculation.accept_lengths[0] == 3  # 2 drafts accepted + the target's own 3rd token


def test_draft_ids_several_candidates_and_one_forward(tiny_llama):
    for input_ids in random_prompts(8, seed=12):
        prompt_len = input_ids.shape[1]
        expected = greedy(tiny_llama, input_ids=input_ids, max_new_tokens=6)
        right = expected[:, prompt_len:]
        noise = torch.randint(3, 320, (1, 3, 6), generator=torch.Generator().manual_seed(prompt_len))
        candidates = torch.cat([noise, right[:, None]], dim=1)  # [1, 4, 6], the right one last
        out = tiny_llama.generate(
            input_ids=input_ids, max_new_tokens=6, do_sample=False, draft_ids=candidates, return_dict_in_generate=True
        )
        assert torch.equal(out.sequences, expected)
        assert out.speculation.num_target_forwards == 1 and out.speculation.accept_lengths == [6]
        assert out.speculation.accepted_by_drafter["draft_ids"] == 5  # 5 drafts + the target's 6th token


def test_hand_built_tree_accepts_the_known_branch(tiny_llama):
    input_ids = random_prompts(1, seed=13)[0]
    g = greedy_continuation(tiny_llama, {"input_ids": input_ids}, 8)
    off = lambda t: (t + 1) % 320  # noqa: E731
    # three branches: wrong at depth 0; right for 2 then wrong; right for 4 (the last, deepest passing one)
    tree = DraftTree.from_paths([[off(g[0]), g[1]], [g[0], g[1], off(g[2])], [g[0], g[1], g[2], g[3]]], "hand")
    out = tiny_llama.generate(
        input_ids=input_ids, max_new_tokens=8, do_sample=False, return_dict_in_generate=True,
        assistant_model=FixedTreeDrafter(tree),
    )  # fmt: skip
    assert out.sequences[0, input_ids.shape[1] :].tolist() == g
    assert out.speculation.accept_lengths[0] == 5  # 4 drafted tokens on the third branch + 1 bonus
    assert out.speculation.tree_sizes[0] == tree.num_nodes == 7


@pytest.mark.parametrize("model_name", ["tiny_llama", "tiny_llava"])
def test_eagle2_tree_r0_equals_greedy(request, model_name, action_tokenizer):
    model = request.getfixturevalue(model_name)
    torch.manual_seed(5)
    head = DraftHead.from_target(model, action_tokenizer, action_dim=7, draft_action_tokens_only=False).eval()
    drafter = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=10))
    generator = torch.Generator().manual_seed(14)
    for i in range(6):
        prompt = (
            llava_prompt(generator, 2 + i % 3)
            if model_name == "tiny_llava"
            else {"input_ids": torch.randint(3, 320, (1, 3 + i), generator=generator)}
        )
        expected = model.generate(**prompt, max_new_tokens=9, do_sample=False)
        out = model.generate(**prompt, max_new_tokens=9, do_sample=False, assistant_model=drafter,
                             return_dict_in_generate=True)  # fmt: skip
        assert torch.equal(out.sequences, expected)
        assert max(out.speculation.tree_sizes) <= 10 and out.speculation.num_draft_forwards > 0


def test_prior_then_head_r0_equals_greedy(tiny_llava, random_llava_draft, action_tokenizer):
    layout = ActionLayout(action_tokenizer, 7)
    tree = DraftHeadDrafter(random_llava_draft, tree=DraftTreeConfig(top_k=2, depth=3, total_tokens=6))
    generator = torch.Generator().manual_seed(15)
    for _ in range(4):
        prompt = llava_prompt(generator, 3)
        expected = greedy_continuation(tiny_llava, prompt, 7)
        previous = [[t if action_tokenizer.is_action_token(t) else 64 for t in expected[:3]] + [64] * 4]
        drafter = ComposedDrafter([ActionPriorDrafter(previous, layout), tree])
        out = tiny_llava.generate(**prompt, max_new_tokens=7, min_new_tokens=7, do_sample=False,
                                  assistant_model=drafter, return_dict_in_generate=True)  # fmt: skip
        assert out.sequences[0, -7:].tolist() == expected


class SpyDrafter(DraftHeadDrafter):
    """A DraftHeadDrafter that records, at every proposal after a catch-up, the sequence and the root feature."""

    def start(self, context):
        session = super().start(context)
        self.records = []
        inner_propose = session.propose

        def propose(draft_round):
            tree = inner_propose(draft_round)
            if session.root_feature is not None:
                self.records.append((draft_round.sequence.clone(), session.root_feature.clone()))
            return tree

        session.propose = propose
        return session


@pytest.mark.parametrize("static", [False, True])
def test_caches_after_a_non_leftmost_path_match_a_fresh_prefill(tiny_llava, random_llava_draft, static):
    generator = torch.Generator().manual_seed(16)
    prompt = llava_prompt(generator, 3)
    g = greedy_continuation(tiny_llava, prompt, 8)
    tree = DraftTree.from_paths([[g[0], (g[1] + 1) % 320], [g[0], g[1], g[2]]], "hand")  # right branch not leftmost
    spy = SpyDrafter(random_llava_draft, num_draft_tokens=2)
    cache = StaticCache(config=tiny_llava.config, max_cache_len=32) if static else None  # room for one more step
    assistant = ComposedDrafter([FixedTreeDrafter(tree), spy])
    out = tiny_llava.generate(**prompt, max_new_tokens=8, do_sample=False, return_dict_in_generate=True,
                              assistant_model=assistant, **{CACHE_KEY: cache})  # fmt: skip
    assert out.sequences[0, -8:].tolist() == g and out.speculation.accept_lengths[0] == 4
    # target: the kept cache gives the next-token logits of a fresh prefill over the emitted sequence
    sequence = out.sequences
    position = torch.tensor([[sequence.shape[1] - 1]])
    cache = cache_of(out)
    assert int(cache.get_seq_length()) == sequence.shape[1] - 1  # the last token is emitted, not fed
    step = tiny_llava(input_ids=sequence[:, -1:], position_ids=position, **{CACHE_KEY: cache})
    fresh = tiny_llava(input_ids=sequence, pixel_values=prompt["pixel_values"], use_cache=True)
    torch.testing.assert_close(step.logits[0, -1], fresh.logits[0, -1], atol=1e-4, rtol=1e-4)
    # every kept entry equals the fresh prefill's (a static cache's accepted path was compacted into its first slots)
    for layer, fresh_layer in zip(cache.layers, cache_of(fresh).layers):
        torch.testing.assert_close(layer.keys[..., : sequence.shape[1], :], fresh_layer.keys, atol=1e-5, rtol=1e-5)
        torch.testing.assert_close(layer.values[..., : sequence.shape[1], :], fresh_layer.values, atol=1e-5, rtol=1e-5)
    # draft head: its root feature after the catch-up equals a fresh run over every (token, true hidden) pair
    seen_sequence, root_feature = spy.records[0]
    length = seen_sequence.shape[1]
    hidden = tiny_llava(input_ids=seen_sequence[:, :-1], pixel_values=prompt["pixel_values"],
                        output_hidden_states=True).hidden_states[-1]  # fmt: skip
    handles = random_llava_draft.target_handles(tiny_llava)
    features = random_llava_draft(
        embed_tokens(handles, seen_sequence[:, 1:]), hidden, torch.arange(length - 1)[None],
        causal_mask(length - 1, 0, hidden.dtype, hidden.device),
    )  # fmt: skip
    torch.testing.assert_close(root_feature[0, -1], features[0, -1], atol=1e-4, rtol=1e-4)


def test_relaxation_fires_and_stays_within_tolerance(tiny_llama, action_tokenizer):
    layout = ActionLayout(action_tokenizer, 7)
    fired = 0
    for input_ids in random_prompts(10, seed=17):
        g = greedy_continuation(tiny_llama, {"input_ids": input_ids}, 7)
        if not all(action_tokenizer.is_action_token(t) for t in g[:3]):
            continue
        nudged = [t + 1 if t < 319 else t - 1 for t in g[:3]]  # every draft one bin off greedy
        out = tiny_llama.generate(
            input_ids=input_ids, max_new_tokens=7, min_new_tokens=7, do_sample=False, return_dict_in_generate=True,
            draft_ids=torch.tensor([nudged]), bin_tolerance=1, action_layout=layout,
        )  # fmt: skip
        assert_within_tolerance(tiny_llama, {"input_ids": input_ids}, out.sequences, [1] * 7, action_tokenizer)
        if out.speculation.accept_lengths[0] > 1:  # the first draft is 1 bin off its greedy token: relaxed accept
            fired += 1
            assert out.sequences[0, input_ids.shape[1]].item() == nudged[0]
            assert 1 in out.speculation.action_bin_distances
    assert fired > 0


@pytest.mark.parametrize(
    "kwargs, error, match",
    [
        (dict(draft_ids=torch.tensor([[5, 70]]), bin_tolerance=2), ValueError, "non-action token ids \\[5\\]"),
        (dict(draft_ids=torch.tensor([70, 71])), ValueError, "shape \\[B, k\\]"),
        (dict(draft_ids=torch.tensor([[70], [71]])), ValueError, "batch size 2"),
        (dict(draft_ids=torch.tensor([[1000]])), ValueError, "token ids in 0..319"),
        (dict(draft_ids=torch.tensor([[1.5]])), TypeError, "integer token ids"),
        (dict(draft_ids=torch.tensor([[70]]), bin_tolerance=2, action_layout="x"), TypeError, "ActionLayout"),
        (dict(draft_ids=torch.tensor([[70]]), bin_tolerance=2), ValueError, "action_layout=ActionLayout"),
        (dict(assistant_model=torch.nn.Linear(2, 2)), TypeError, "DraftHead or Drafter"),
    ],
)
def test_bad_draft_input(tiny_llama, action_tokenizer, kwargs, error, match):
    if "action_layout" not in kwargs and "non-action" in match:
        kwargs = dict(kwargs, action_layout=ActionLayout(action_tokenizer, 7))
    with pytest.raises(error, match=match):
        tiny_llama.generate(input_ids=random_prompts(1)[0], max_new_tokens=3, do_sample=False, **kwargs)


@pytest.mark.parametrize(
    "settings, match",
    [(dict(top_k=0), "top_k"), (dict(depth=-1), "depth"), (dict(total_tokens=2, depth=4), "total_tokens")],
)
def test_bad_tree_settings(settings, match):
    with pytest.raises(ValueError, match=match):
        DraftTreeConfig(**settings)


def test_bad_drafter_settings(random_draft, action_tokenizer):
    with pytest.raises(ValueError, match="not both"):
        DraftHeadDrafter(random_draft, num_draft_tokens=2, tree=DraftTreeConfig())
    with pytest.raises(TypeError, match="DraftHead"):
        DraftHeadDrafter(torch.nn.Linear(2, 2))
    with pytest.raises(ValueError, match="not 7 action token ids"):
        ActionPriorDrafter([[70, 71]], ActionLayout(action_tokenizer, 7))
    with pytest.raises(TypeError, match="Drafters"):
        ComposedDrafter([random_draft])


def test_prefix_allowed_tokens_fn_sees_batch_row_0_for_every_node(tiny_llama):
    input_ids = random_prompts(1, seed=18)[0]

    def allowed(batch_id, prefix):  # a batch of 1: anything but row 0 would be a bug, and would allow nothing
        return list(range(64, 320)) if batch_id == 0 else []

    kwargs = dict(max_new_tokens=6, prefix_allowed_tokens_fn=allowed)
    expected = greedy(tiny_llama, input_ids=input_ids, **kwargs)
    generated = expected[0, input_ids.shape[1] :].tolist()
    candidates = torch.tensor([[[generated[0], 64, 65], generated[:3], [generated[0], generated[1], 70]]])
    out = tiny_llama.generate(input_ids=input_ids, do_sample=False, draft_ids=candidates, **kwargs)
    assert torch.equal(out, expected)


def test_accepted_positions_follow_the_accept_lengths():
    from hf_specvla.speculative import SpeculationStats

    accepted, own = True, False
    positions = SpeculationStats(accept_lengths=[3, 1, 4]).accepted_positions()
    assert positions == [accepted, accepted, own, own, accepted, accepted, accepted, own]
    assert SpeculationStats(accept_lengths=[8]).accepted_positions() == [accepted] * 7 + [own]  # one forward
    assert SpeculationStats(accept_lengths=[1] * 8).accepted_positions() == [own] * 8  # nothing accepted
    assert SpeculationStats(accept_lengths=[2, 1]).accepted_positions(5) == [accepted, own, own, own, own]
