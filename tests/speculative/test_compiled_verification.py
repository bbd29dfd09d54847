"""Compiled verification (``speculative.compiled``): on a static cache with a ``CompileConfig`` every verification after
the prefill runs through transformers' compiled model call at a fixed width bucket.

Compiled here with dynamo's ``eager`` backend (it traces, guards and recompiles exactly as inductor would, without
generating code): r=0 gives greedy's tokens for every drafter on Llama, a sliding-window family and a VLM; after a
warm-up, calls with other drafts, accepted lengths and tree shapes compile nothing new; the widths stay in the
buckets; generate's own static cache gets slots for the trees, a user's cache is used as it is.
"""

from __future__ import annotations

import functools
import time

import pytest
import torch
from transformers import AutoConfig, AutoModelForCausalLM, CompileConfig, LlamaForCausalLM
from transformers.cache_utils import StaticCache

from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig, JacobiDrafter, enable_speculation
from hf_specvla.policies import VLAPolicy, VLAPolicyConfig
from hf_specvla.speculative import CACHE_KEY, NODE_BUCKETS, cache_of, verification_width
from hf_specvla.speculative.compiled import (
    SLOT_MULTIPLE,
    buckets_up_to,
    check_buckets,
    graphs_held,
    reset_compilation,
)
from hf_specvla.speculative.decoder import SpeculativeDecoder
from hf_specvla.speculative.drafter import Drafter, DraftSession

from ..conftest import tiny_llama_config
from .test_backbones import TEXT, TEXT_BACKBONES

VOCAB = 320
NEW_TOKENS = 7


def eager_compile_config() -> CompileConfig:
    """dynamo with its ``eager`` backend, on any device (transformers compiles on CUDA only unless told)."""
    config = CompileConfig(backend="eager", fullgraph=True, dynamic=False, mode="default")
    config._compile_all_devices = True
    return config


@pytest.fixture(autouse=True)
def fresh_dynamo():
    reset_compilation()
    torch._dynamo.utils.counters.clear()
    yield
    reset_compilation()


def _model(name: str):
    torch.manual_seed(0)
    if name == "llama":
        return enable_speculation(LlamaForCausalLM(tiny_llama_config()).eval())
    config = AutoConfig.for_model(name, **TEXT, **TEXT_BACKBONES[name])
    return enable_speculation(AutoModelForCausalLM.from_config(config).float().eval())


def greedy(model, input_ids, **kwargs):
    return model.generate(input_ids=input_ids, max_new_tokens=NEW_TOKENS, do_sample=False, **kwargs)


def calls_for(model, input_ids, expected):
    """generate kwargs for every drafter: right / wrong drafts, candidates, head chain, EAGLE-2 tree, composed."""
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    right = expected[:, input_ids.shape[1] : -1]
    wrong = right.clone()
    wrong[:, 2] = (wrong[:, 2] + 1) % VOCAB
    candidates = torch.stack([wrong, (right + 7) % VOCAB], dim=1)
    return [dict(draft_ids=right), dict(draft_ids=wrong), dict(draft_ids=candidates), dict(assistant_model=head),
            dict(assistant_model=tree), dict(draft_ids=wrong, assistant_model=tree),
            dict(assistant_model=JacobiDrafter()), dict(draft_ids=wrong, assistant_model=JacobiDrafter())]  # fmt: skip


@pytest.mark.parametrize("name", ["llama", "gemma2"])
def test_compiled_verification_gives_greedys_tokens_for_every_drafter(name):
    model = _model(name)
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    expected = greedy(model, input_ids)
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    for kwargs in calls_for(model, input_ids, expected):
        out = greedy(model, input_ids, return_dict_in_generate=True, **compiled, **kwargs)
        assert torch.equal(out.sequences, expected), kwargs
        widths = out.speculation.compiled_widths
        assert len(widths) == out.speculation.num_batch_forwards - 1  # every round after the (eager) prefill
        assert set(widths) <= set(NODE_BUCKETS), widths


class RecordingDrafter(Drafter):
    """Proposes what ``inner`` proposes and records every tree (tokens, parents)."""

    def __init__(self, inner: Drafter):
        self.inner, self.name, self.trees = inner, inner.name, []
        self.needs_hidden_states, self.action_layout = inner.needs_hidden_states, inner.action_layout

    def start(self, context):
        session, trees = self.inner.start(context), self.trees

        class Recording(DraftSession):
            def propose(self, draft_round):
                tree = session.propose(draft_round)
                trees.append((tree.token_ids.tolist(), tree.parents.tolist()))
                return tree

            def observe(self, commit):
                session.observe(commit)

        return Recording()


# the chain in the slow tier: the tree's rounds cover the compiled head round
TREE = DraftTreeConfig(top_k=3, depth=4, total_tokens=12)


@pytest.mark.parametrize("tree", [pytest.param(None, marks=pytest.mark.slow), TREE], ids=["chain", "tree"])
def test_the_compiled_head_drafts_the_eager_heads_trees_round_after_round(tree):
    """The head's compiled rounds (static cache, catch-up + expansion in one graph, the prompt's pairs fed eagerly but
    for the last ones) propose exactly the eager head's trees at every round, so it accepts what it would eagerly."""
    model = _model("llama")
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    for seed in range(3):
        input_ids = torch.randint(6, 64, (1, 6 + 3 * seed), generator=torch.Generator().manual_seed(seed))
        runs = []
        for kwargs in ({}, compiled):
            drafter = RecordingDrafter(DraftHeadDrafter(head, tree=tree))
            out = greedy(model, input_ids, assistant_model=drafter, return_dict_in_generate=True, **kwargs)
            runs.append((drafter.trees, out.sequences))
        (eager_trees, eager_tokens), (compiled_trees, compiled_tokens) = runs
        assert len(eager_trees) >= 3  # several rounds after the prefill: the catch-up and its padding are exercised
        assert compiled_trees == eager_trees, seed
        assert torch.equal(compiled_tokens, eager_tokens)


def test_no_recompilation_after_warm_up(graphs_in_memory):
    """Other prompts' drafts, accepted lengths and tree shapes reuse the graphs compiled during the warm-up."""
    model = _model("llama")
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    prompts = [torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(s)) for s in range(4)]
    plans = []
    for input_ids in prompts:
        expected = greedy(model, input_ids)
        plans += [(input_ids, expected, kwargs) for kwargs in calls_for(model, input_ids, expected)]
    warm_up, steady = plans[:6], plans[6:]  # one prompt's calls, then three other prompts'
    widths, compile_seconds = set(), []
    for input_ids, _, kwargs in warm_up:
        out = greedy(model, input_ids, return_dict_in_generate=True, **compiled, **kwargs)
        widths |= set(out.speculation.compiled_widths)
        compile_seconds.append(out.speculation.compile_seconds)
    # every width up to the drafter's largest tree is compiled up front, before the first compiled round: the right
    # drafts (6 nodes) widths 0-8 without hidden states, the candidates (12) width 16 too, the head chain (3) widths
    # 0-4 with hidden states and its round, the tree (12) width 8-16 and its round, drafts + tree (18) width 32
    assert [s > 0 for s in compile_seconds] == [True, False, True, True, True, True], compile_seconds
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    # the round's widths (on the CPU width 0 and one graph for the widths from 2 nodes) without hidden states and with
    # them, one round graph for the chain and one for the tree (shallower rounds pass their depth as data), and one
    # prefill graph for every prompt length and draft count, without hidden states and with them
    assert graphs == 2 + 2 + 1 + 1 + 2
    with torch._dynamo.config.patch(error_on_recompile=True):
        for input_ids, expected, kwargs in steady:
            out = greedy(model, input_ids, return_dict_in_generate=True, **compiled, **kwargs)
            assert torch.equal(out.sequences, expected), kwargs
            assert set(out.speculation.compiled_widths) <= widths  # only widths the warm-up met
            assert out.speculation.compile_seconds == 0
            assert out.speculation.compiled_prefills == 1  # other prompt lengths, other drafts: the same graph
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs  # nothing compiled after the warm-up
    assert len(widths) > 1  # several buckets were met (the test is not vacuous)


def test_only_the_widths_a_drafter_can_fill_are_compiled(graphs_in_memory):
    """A drafter's largest tree bounds the widths compiled up front (and met): Jacobi tails of at most 3 nodes need
    widths 0, 2 and 4, and nothing else compiles."""
    model = _model("llama")
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    assert JacobiDrafter(max_tokens=3).max_tree_nodes(NEW_TOKENS - 1) == 3
    out = greedy(model, input_ids, assistant_model=JacobiDrafter(max_tokens=3), return_dict_in_generate=True,
                 **compiled)  # fmt: skip
    assert torch.equal(out.sequences, greedy(model, input_ids))
    assert set(out.speculation.compiled_widths) <= {0, 2, 4} and out.speculation.compile_seconds > 0
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 2 + 1  # width 0, one for 2 and 4, the prefill


@pytest.mark.parametrize("asked", [None, "1", "0"])
def test_a_rounds_widths_from_two_nodes_share_one_graph_on_the_cpu(monkeypatch, graphs_in_memory, asked):
    """On the CPU (``HF_SPECVLA_DYNAMIC_WIDTHS`` unset, or 1) a compiled round's widths of 2, 4 and 8 nodes run one
    graph whose node count is a dynamic dimension, width 0 (a plain decoding step) its own: 2 graphs where a graph per
    width is 4 (``HF_SPECVLA_DYNAMIC_WIDTHS=0``). Either way every call gives greedy's tokens, several widths are met,
    and after the first call nothing compiles."""
    if asked is None:
        monkeypatch.delenv("HF_SPECVLA_DYNAMIC_WIDTHS", raising=False)
    else:
        monkeypatch.setenv("HF_SPECVLA_DYNAMIC_WIDTHS", asked)
    model = _model("llama")
    config = eager_compile_config()
    drafter = JacobiDrafter(max_tokens=6)
    assert buckets_up_to(drafter.max_tree_nodes(NEW_TOKENS - 1)) == (0, 2, 4, 8)
    widths = set()
    for seed, length in enumerate((6, 9, 5, 12)):
        input_ids = torch.randint(6, 64, (1, length), generator=torch.Generator().manual_seed(seed))
        expected = greedy(model, input_ids)
        with torch._dynamo.config.patch(error_on_recompile=seed > 0):
            out = greedy(model, input_ids, assistant_model=drafter, return_dict_in_generate=True,
                         cache_implementation="static", compile_config=config)  # fmt: skip
        assert torch.equal(out.sequences, expected), length
        widths |= set(out.speculation.compiled_widths)
    (accepting,) = SpeculativeDecoder.of(model).graphs(config).accepting.values()
    assert graphs_held(accepting) == (4 if asked == "0" else 2)
    assert len(widths & {2, 4, 8}) > 1, widths  # the one graph served several widths (the test is not vacuous)


def test_a_dynamic_widths_setting_that_is_not_0_or_1_is_refused(monkeypatch):
    from hf_specvla.speculative.compiled import dynamic_widths

    monkeypatch.setenv("HF_SPECVLA_DYNAMIC_WIDTHS", "yes")
    with pytest.raises(ValueError, match=r"HF_SPECVLA_DYNAMIC_WIDTHS='yes': expected 1 .* 0 .* or unset"):
        dynamic_widths("cpu")


def test_one_compiled_prefill_serves_every_prompt_length_and_draft_count(graphs_in_memory):
    """A call site's first prefill runs eagerly and compiles the prefill graph; every later prefill (other prompt
    lengths, with or without drafts verified inside it) runs through that one graph and gives greedy's tokens.
    (Dynamo's graph count is read: graphs in memory, as graph files an earlier test saved would be loaded uncounted
    in the warm-up.)"""
    model = _model("llama")
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())

    def calls(length: int, seed: int):
        input_ids = torch.randint(6, 64, (1, length), generator=torch.Generator().manual_seed(seed))
        expected = greedy(model, input_ids)
        right = expected[:, length:-1]
        wrong = torch.cat([right[:, :2], (right[:, 2:] + 1) % VOCAB], dim=1)
        return [(input_ids, expected, kwargs) for kwargs in (dict(), dict(draft_ids=right), dict(draft_ids=wrong))]

    prefills = []
    for input_ids, expected, kwargs in calls(6, 0):  # the warm-up: one prompt length, each kind of call
        out = greedy(model, input_ids, assistant_model=JacobiDrafter(), return_dict_in_generate=True, **compiled,
                     **kwargs)  # fmt: skip
        assert torch.equal(out.sequences, expected), kwargs
        prefills.append(out.speculation.compiled_prefills)
    assert prefills == [0, 1, 1]  # the first prefill eagerly (it compiles the graph), then compiled
    graphs = torch._dynamo.utils.counters["stats"]["unique_graphs"]
    with torch._dynamo.config.patch(error_on_recompile=True):
        for seed, length in enumerate((4, 9, 13), start=1):
            for input_ids, expected, kwargs in calls(length, seed):
                out = greedy(model, input_ids, assistant_model=JacobiDrafter(), return_dict_in_generate=True,
                             **compiled, **kwargs)  # fmt: skip
                assert torch.equal(out.sequences, expected), (length, kwargs)
                assert out.speculation.compiled_prefills == 1, (length, kwargs)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == graphs


def test_a_forward_that_does_not_compile_over_the_prompt_keeps_an_eager_prefill(caplog):
    """A model whose forward breaks the graph over the prompt (here: whenever kept logits are chosen by an index
    tensor, as only the compiled prefill does) is told once and keeps an eager prefill; decoding stays exact."""
    model = _model("llama")
    forward = model.forward

    def breaking_forward(*args, **kwargs):
        if isinstance(kwargs.get("logits_to_keep"), torch.Tensor):
            torch._dynamo.graph_break()
        return forward(*args, **kwargs)

    model.forward = breaking_forward
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(0))
    expected = greedy(model, input_ids)
    with caplog.at_level("WARNING", logger="hf_specvla.speculative.compiled"):
        runs = [greedy(model, input_ids, draft_ids=expected[:, 6:9], return_dict_in_generate=True, **compiled)
                for _ in range(3)]  # fmt: skip
    assert [r.speculation.compiled_prefills for r in runs] == [0, 0, 0]
    assert all(torch.equal(r.sequences, expected) for r in runs)
    assert sum("stays eager" in record.getMessage() for record in caplog.records) == 1


def test_preserved_entries_empties_the_cache_for_the_block_and_puts_every_entry_back():
    from hf_specvla.speculative.cache import cache_length, preserved_entries

    model = _model("llama")
    cache = StaticCache(config=model.config, max_cache_len=32)
    with torch.no_grad():
        model(input_ids=torch.tensor([[1, 7, 9, 11, 13]]), use_cache=True, **{CACHE_KEY: cache})
    keys = [layer.keys for layer in cache.layers]
    before = [(layer.keys[..., :5, :].clone(), layer.values[..., :5, :].clone()) for layer in cache.layers]
    with preserved_entries(cache):
        assert cache_length(cache) == 0
        with torch.no_grad():  # a throw-away forward over other tokens, written from slot 0
            model(input_ids=torch.tensor([[3, 4, 5, 6, 8, 10, 12]]), use_cache=True, **{CACHE_KEY: cache})
        assert cache_length(cache) == 7
    assert cache_length(cache) == 5
    for layer, key_buffer, (saved_keys, saved_values) in zip(cache.layers, keys, before):
        assert layer.keys is key_buffer  # in place: compiled graphs hold the buffers' addresses
        assert torch.equal(layer.keys[..., :5, :], saved_keys) and torch.equal(layer.values[..., :5, :], saved_values)


def test_compiled_verification_in_a_chunked_policy():
    """``predict_action`` passes ``cache_implementation`` and ``compile_config`` through; r=0 is greedy's chunk."""
    from ..policies.test_action_chunks import ACTIONS, CHUNK, INSTRUCTIONS, SMALL, STATES, action_only, drafters
    from ..policies.test_action_chunks import observation as chunk_observation

    torch.manual_seed(0)
    policy = action_only(VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**SMALL, chunk_length=CHUNK)))
    methods = drafters(policy)
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    history = [[200, 210, 220, 230]] * 2
    for seed in range(3):
        image, state = chunk_observation(seed)
        policy.previous_action_ids = list(history)
        _, plain = policy.predict_action(image, "reach the goal", state, return_output=True)
        for name in ("tree", "prior", "prior+tree", "prior+jacobi", "prior+jacobi+tree"):
            policy.previous_action_ids = list(history)
            _, out = policy.predict_action(image, "reach the goal", state, return_output=True, **compiled,
                                           **methods[name])  # fmt: skip
            assert torch.equal(out.sequences, plain.sequences), name
            assert out.speculation.compiled_widths or out.speculation.num_batch_forwards == 1, name


def test_without_compile_all_devices_the_cpu_verifies_eagerly(tiny_llama):
    input_ids = torch.tensor([[1, 7, 9, 11]])
    config = CompileConfig(backend="eager", mode="default")  # no _compile_all_devices: transformers would not compile
    out = greedy(tiny_llama, input_ids, draft_ids=torch.tensor([[70, 71, 72]]), cache_implementation="static",
                 compile_config=config, return_dict_in_generate=True)  # fmt: skip
    assert out.speculation.compiled_widths == []
    assert torch.equal(out.sequences, greedy(tiny_llama, input_ids))


def test_generates_own_static_cache_gets_slots_for_the_trees_a_users_cache_is_kept(tiny_llama):
    input_ids = torch.tensor([[1, 7, 9, 11]])
    out = greedy(tiny_llama, input_ids, draft_ids=torch.tensor([[70]]), cache_implementation="static",
                 return_dict_in_generate=True)  # fmt: skip
    # generate sizes its cache for greedy's tokens (prompt + new - 1); the loop adds the largest bucket's slots, and
    # rounds up (prompts of other lengths share the compiled graphs)
    slots = input_ids.shape[1] + NEW_TOKENS - 1 + NODE_BUCKETS[-1]
    assert cache_of(out).layers[0].max_cache_len == -(-slots // SLOT_MULTIPLE) * SLOT_MULTIPLE  # rounded up
    # the next call reuses that cache, emptied (its buffers keep their addresses), and decodes the same
    keys = cache_of(out).layers[0].keys
    again = greedy(tiny_llama, input_ids, draft_ids=torch.tensor([[70]]), cache_implementation="static",
                   return_dict_in_generate=True)  # fmt: skip
    assert cache_of(again) is cache_of(out) and cache_of(again).layers[0].keys is keys
    assert torch.equal(again.sequences, out.sequences) and torch.equal(out.sequences, greedy(tiny_llama, input_ids))
    users = StaticCache(config=tiny_llama.config, max_cache_len=input_ids.shape[1] + NEW_TOKENS)
    out = greedy(tiny_llama, input_ids, draft_ids=torch.tensor([[70]]), return_dict_in_generate=True,
                 **{CACHE_KEY: users})  # fmt: skip
    assert cache_of(out) is users and users.layers[0].max_cache_len == input_ids.shape[1] + NEW_TOKENS


def test_each_drafter_bounds_its_trees_and_the_buckets_follow(tiny_llama):
    from hf_specvla import ActionLayout, ActionPriorDrafter, ActionTokenizer, CandidateDrafter, ComposedDrafter

    torch.manual_seed(1)
    head = DraftHead.from_target(tiny_llama, num_draft_tokens=3).eval()
    layout = ActionLayout(ActionTokenizer(VOCAB), 2)
    prior = ActionPriorDrafter([[100, 101]], layout, max_nodes=12, chunk_length=3)
    held = ActionPriorDrafter([[100, 101]], layout, later_rounds=False)
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
    bounds = {"chain": (DraftHeadDrafter(head), 3), "tree": (tree, 12), "prior": (prior, 12), "held": (held, 0),
              "jacobi": (JacobiDrafter(), 6), "jacobi k=2": (JacobiDrafter(max_tokens=2), 2),
              "draft_ids": (CandidateDrafter([[1, 2, 3], [4] * 9]), 3 + 6),
              "held+jacobi+tree": (ComposedDrafter([held, JacobiDrafter(), tree]), 18)}  # fmt: skip
    for name, (drafter, bound) in bounds.items():
        assert drafter.max_tree_nodes(6) == bound, name
    assert Drafter().max_tree_nodes(6) is None  # unknown: every width
    assert buckets_up_to(None) == NODE_BUCKETS and buckets_up_to(0) == (0,) and buckets_up_to(6) == (0, 2, 4, 8)
    assert buckets_up_to(18) == NODE_BUCKETS and buckets_up_to(99) == NODE_BUCKETS  # past the largest: all of them


@pytest.mark.parametrize(
    "num_nodes, free, width",
    [(0, 50, 0), (1, 50, 2), (3, 50, 4), (12, 50, 16), (24, 50, 32), (40, 50, 32), (24, 20, 16), (5, 1, 0)],
)
def test_verification_width_pads_up_to_a_bucket_or_cuts_to_the_largest_that_fits(num_nodes, free, width):
    assert verification_width(num_nodes, free) == width


@pytest.mark.parametrize("buckets", [(), (2, 4), (0, 4, 2), (0, 2, 2), (0, -1), (0, 2.5)])
def test_bad_buckets_are_refused(buckets):
    with pytest.raises(ValueError, match="node buckets"):
        check_buckets(buckets)


def test_widths_are_compiled_once_per_model_even_when_the_compiled_call_is_wrapped():
    """A wrapper around ``get_compiled_call`` (the benchmarks' clock returns a new closure per call) does not make the
    engine compile the widths again: what is compiled is keyed on the model, the settings, the slots."""
    model = _model("llama")
    original = model.get_compiled_call
    model.get_compiled_call = lambda config: lambda *args, **kwargs: original(config)(*args, **kwargs)
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    input_ids = torch.tensor([[1, 7, 9, 11]])
    seconds = [
        greedy(
            model, input_ids, draft_ids=torch.tensor([[70, 71]]), return_dict_in_generate=True, **compiled
        ).speculation.compile_seconds
        for _ in range(3)
    ]
    assert seconds[0] > 0 and seconds[1:] == [0.0, 0.0]


# ----------------------------------------------------------------------------- batches on a static cache
def _left_padded_batch(generator_seed: int = 3):
    """Four prompts of 6, 4, 6 and 5 tokens, left-padded: ``input_ids`` and ``attention_mask`` ``[4, 6]``."""
    input_ids = torch.randint(6, 64, (4, 6), generator=torch.Generator().manual_seed(generator_seed))
    attention_mask = torch.ones_like(input_ids)
    for row, padding in ((1, 2), (3, 1)):
        input_ids[row, :padding], attention_mask[row, :padding] = 0, 0
    return input_ids, attention_mask


def _eos_that_stops_one_row_early(model, inputs) -> int:
    """A token batched greedy decoding emits third in row 1 and nowhere else earlier: as EOS, row 1 stops early and
    the other rows go on (a static cache then keeps row 1 as an idle row)."""
    plain = greedy(model, inputs["input_ids"], attention_mask=inputs["attention_mask"], eos_token_id=None)
    new = plain[:, inputs["input_ids"].shape[1] :]
    token = int(new[1, 2])
    assert all(token not in new[b, :3].tolist() for b in (0, 2, 3)), "pick another prompt seed"
    return token


# gemma2's batch in the slow tier (~50 s): its sliding window is compiled at B = 1 in the fast tier
@pytest.mark.parametrize("name", ["llama", pytest.param("gemma2", marks=pytest.mark.slow)])
def test_a_batch_on_a_static_cache_gives_batched_greedys_tokens_for_every_drafter(name):
    """Left-padded rows that accept different lengths and stop at different times, on generate's static cache, eager
    and compiled: every drafter gives batched greedy decoding's tokens (on the default cache)."""
    model = _model(name)
    input_ids, attention_mask = _left_padded_batch()
    eos = _eos_that_stops_one_row_early(model, {"input_ids": input_ids, "attention_mask": attention_mask})
    expected = greedy(model, input_ids, attention_mask=attention_mask, eos_token_id=eos, pad_token_id=0)
    assert int((expected[1] == 0).sum()) > 2  # row 1 stopped early (right-padded)
    for kwargs in calls_for(model, input_ids, expected[:, :-1]):
        for compiled in ({}, {"compile_config": eager_compile_config()}):
            out = greedy(model, input_ids, attention_mask=attention_mask, eos_token_id=eos, pad_token_id=0,
                         cache_implementation="static", return_dict_in_generate=True, **compiled, **kwargs)  # fmt: skip
            assert torch.equal(out.sequences, expected), (kwargs, compiled)
            assert bool(compiled) == bool(out.speculation.compiled_widths)


# 17 slots in the fast tier; 12 and 14 (the other compactions) in the slow one
@pytest.mark.parametrize("slots", [pytest.param(n, marks=pytest.mark.slow) for n in (12, 14)] + [17])
def test_a_batch_fills_a_tight_static_cache_by_compacting_its_rows(slots):
    """A user's static cache with barely the slots greedy needs (11: prompt 6 + 6 fed tokens - 1): rows that accept
    different lengths leave invalid slots behind, which are compacted away when the trees need room; the tokens stay
    batched greedy's (without compaction the free slots run out and the call fails)."""
    model = _model("llama")
    input_ids, attention_mask = _left_padded_batch()
    expected = greedy(model, input_ids, attention_mask=attention_mask)
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    wrong = expected[:, input_ids.shape[1] : -1].clone()
    wrong[0, 0], wrong[2, 3] = (wrong[0, 0] + 1) % VOCAB, (wrong[2, 3] + 1) % VOCAB
    drafters = [dict(assistant_model=DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))),
                dict(draft_ids=wrong, assistant_model=JacobiDrafter())]  # fmt: skip
    for kwargs in drafters:
        for compiled in ({}, {"compile_config": eager_compile_config()}):
            cache = StaticCache(config=model.config, max_cache_len=slots)
            out = greedy(model, input_ids, attention_mask=attention_mask, return_dict_in_generate=True,
                         **{CACHE_KEY: cache}, **compiled, **kwargs)  # fmt: skip
            assert torch.equal(out.sequences, expected), (slots, kwargs, compiled)


def test_compact_rows_moves_each_rows_valid_entries_to_the_front_in_order():
    """Static and dynamic layers alike: row b's valid entries, in order, then nothing; the static layer's buffers keep
    their addresses and its counter is the longest row's count."""
    from transformers.cache_utils import DynamicCache

    from hf_specvla.speculative.cache import cache_length, compact_rows

    torch.manual_seed(0)
    keys, values = torch.randn(3, 2, 7, 4), torch.randn(3, 2, 7, 4)
    valid = torch.tensor([[1, 1, 0, 1, 0, 0, 1], [0, 0, 1, 1, 1, 1, 1], [1, 0, 0, 0, 0, 0, 1]]).bool()
    config = tiny_llama_config(num_hidden_layers=1)
    static = StaticCache(config=config, max_cache_len=9)
    static.update(keys, values, 0)
    address = static.layers[0].keys.data_ptr()
    dynamic = DynamicCache()
    dynamic.update(keys, values, 0)
    for cache in (static, dynamic):
        compacted = compact_rows(cache, valid)
        assert compacted.tolist() == [[True] * 4 + [False], [True] * 5, [True] * 2 + [False] * 3]
        assert cache_length(cache) == 5
        for b in range(3):
            count = int(valid[b].sum())
            assert torch.equal(cache.layers[0].keys[b, :, :count], keys[b][:, valid[b]])
            assert torch.equal(cache.layers[0].values[b, :, :count], values[b][:, valid[b]])
    assert static.layers[0].keys.data_ptr() == address


def test_a_thread_that_did_not_compile_the_graphs_decodes_compiled_greedy_and_speculation(
    monkeypatch, graphs_in_memory
):
    """dynamo's recompile limit is per thread: graphs compiled in one thread (more than the default limit of 8 on the
    model's forward) must not make another thread's next compile fail (a server's worker decoding what its main
    thread warmed up): compiled greedy and compiled verification there equal greedy. (A graph per round width, so
    that the warm-up compiles more graphs than the default limit.)"""
    import threading

    monkeypatch.setenv("HF_SPECVLA_DYNAMIC_WIDTHS", "0")
    model = _model("llama")
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(3))
    expected = greedy(model, input_ids)
    for kwargs in calls_for(model, input_ids, expected)[:6]:  # the warm-up of test_no_recompilation_after_warm_up
        greedy(model, input_ids, **compiled, **kwargs)
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] > 8
    longer = torch.randint(6, 64, (1, 9), generator=torch.Generator().manual_seed(4))  # a new prompt length
    results, errors = {}, []

    def worker():
        try:
            results["greedy"] = greedy(model, longer, **compiled)  # transformers' compiled greedy: a new graph
            results["jacobi"] = greedy(model, longer, assistant_model=JacobiDrafter(), **compiled)
        except Exception as error:  # noqa: BLE001 (asserted below)
            errors.append(error)

    thread = threading.Thread(target=worker)
    thread.start()
    thread.join()
    assert errors == []
    expected_longer = greedy(model, longer)
    assert torch.equal(results["greedy"], expected_longer) and torch.equal(results["jacobi"], expected_longer)


def test_the_compiled_path_is_chosen_by_device_with_cuda_graphs_on_cuda(monkeypatch):
    """A target on CUDA verifies through the compiled call when a static cache and a CompileConfig are given, as
    transformers' compiled greedy does, with CUDA graphs (``mode="reduce-overhead"``); on the CPU only when told
    (``_compile_all_devices``, inductor's default mode). The capture itself needs a GPU (gpu_openvla.py)."""
    from hf_specvla.speculative import call_compile_config, compiled_decoding_kwargs

    model = _model("llama")
    on_cuda = compiled_decoding_kwargs("cuda")["compile_config"]
    on_cpu = compiled_decoding_kwargs("cpu")["compile_config"]
    assert on_cuda.mode == "reduce-overhead" and on_cpu.mode == "default"
    assert call_compile_config(model, on_cuda, False, True) is None  # a CPU model, not told
    assert call_compile_config(model, on_cpu, False, True) is on_cpu
    assert call_compile_config(model, on_cpu, True, True) is None  # disable_compile
    monkeypatch.setattr(type(model), "device", property(lambda self: torch.device("cuda")))
    assert call_compile_config(model, on_cuda, False, True) is on_cuda
    assert call_compile_config(model, on_cuda, False, False) is None  # no static cache


def test_one_decision_compiles_a_gpu_call_without_a_compile_config_as_transformers_does(monkeypatch):
    """On a GPU transformers compiles a static-cache call without a ``compile_config`` (its model's default one):
    so does the engine, with that config (it once took None and crashed making the graphs' key), and the same
    decision is read from ``generate``'s keyword arguments (the image encoder, the thread's graph allowance) as from
    the prepared call (the rounds); offloaded layers and ``disable_compile`` keep it eager."""
    from transformers import GenerationConfig

    from hf_specvla.speculative import call_compile_config
    from hf_specvla.speculative.compiled import compile_settings, compiled_call_config

    model = _model("llama")
    monkeypatch.setattr(type(model), "device", property(lambda self: torch.device("cuda")))
    config = call_compile_config(model, None, False, True)
    assert config is not None and compile_settings(config) == compile_settings(model._default_compile_config())
    cache = StaticCache(config=model.config, max_cache_len=64)
    for kwargs in ({"cache_implementation": "static"}, {"past_key_values": cache},
                   {"generation_config": GenerationConfig(cache_implementation="static")}):  # fmt: skip
        assert compile_settings(compiled_call_config(model, kwargs)) == compile_settings(config), kwargs
    assert compiled_call_config(model, {}) is None  # a dynamic cache
    assert compiled_call_config(model, {"cache_implementation": "static", "disable_compile": True}) is None
    model.hf_device_map = {"model.layers.0": 0, "model.layers.1": "cpu"}  # a layer offloaded to the CPU
    assert call_compile_config(model, None, False, True) is None


def test_the_graph_budget_is_what_dynamo_holds_and_reset_forgets_every_verifier(graphs_in_memory):
    """The recompile limit is raised from dynamo's own count of a code object's graphs (every caller's, not a count of
    ours), and ``reset_compilation`` drops them and makes every model's verifier anew."""
    from hf_specvla.speculative.compiled import graphs_held
    from hf_specvla.speculative.decoder import allow_graphs_held

    def double(x):
        return 2 * x

    compiled = torch.compile(double, backend="eager", dynamic=False)
    for n in (1, 2, 3):
        compiled(torch.ones(n))
    assert graphs_held(double) == 3
    model = _model("llama")
    config = eager_compile_config()
    verifier = SpeculativeDecoder.of(model).graphs(config)
    assert SpeculativeDecoder.of(model).graphs(config) is verifier
    greedy(model, torch.randint(6, 64, (1, 6)), cache_implementation="static", compile_config=config,
           draft_ids=torch.randint(6, 64, (1, 3)))  # fmt: skip
    held = graphs_held(type(model).forward)
    (accepting,) = verifier.accepting.values()  # the rounds' forward with their acceptance
    assert held >= 1 and graphs_held(accepting) >= 2  # the prefill's graph; the widths of 3 drafts (0; 2 and 4)
    with torch._dynamo.config.patch(recompile_limit=1):
        allow_graphs_held(model)  # a thread that did not compile: its limit holds every graph and transformers'
        assert torch._dynamo.config.recompile_limit >= max(held, graphs_held(accepting)) + 8
    reset_compilation()
    assert graphs_held(double) == 0 and graphs_held(type(model).forward) == 0 and graphs_held(accepting) == 0
    assert SpeculativeDecoder.of(model).graphs(config) is not verifier


def test_every_compiled_round_of_a_width_is_fed_the_same_input_tensors(monkeypatch, graphs_in_memory):
    """The engine's own input buffers per (batch size, width): every compiled verification of one shape, round after
    round and call after call, reads its ids, positions and mask from the same tensors (what a CUDA graph needs to
    copy nothing in), and the tokens stay greedy's."""
    from hf_specvla.speculative.compiled import CALL_WRAPPER_ATTRIBUTE

    model = _model("llama")
    config = eager_compile_config()
    fed: dict[tuple, set] = {}

    def spied_round(call):  # the rounds' compiled call, its acceptance in its graph (``speculative.fused``)
        def spy(inputs, *tensors):
            fed_tensors = [inputs[name] for name in ("input_ids", "position_ids", "attention_mask")]
            fed.setdefault(tuple(inputs["input_ids"].shape), set()).add(tuple(t.data_ptr() for t in fed_tensors))
            return call(inputs, *tensors)

        return spy

    monkeypatch.setattr(model, CALL_WRAPPER_ATTRIBUTE, spied_round, raising=False)
    rounds = []
    for seed in range(3):
        input_ids = torch.randint(6, 64, (1, 6), generator=torch.Generator().manual_seed(seed))
        expected = greedy(model, input_ids)
        out = greedy(model, input_ids, cache_implementation="static", compile_config=config,
                     assistant_model=JacobiDrafter(), return_dict_in_generate=True)  # fmt: skip
        assert torch.equal(out.sequences, expected)
        rounds.append(len(out.speculation.compiled_widths))
    assert sum(rounds) >= 6 and max(len(v) for v in fed.values()) == 1, fed  # not vacuous: many rounds, one set each
    verifier = SpeculativeDecoder.of(model).graphs(config)
    owned = {tuple(t.data_ptr() for t in b.tensors()) for b in verifier.buffers.values()}
    assert set().union(*fed.values()) <= owned  # the verifier's own buffers


@pytest.mark.parametrize("graphs", ["files", "in memory"])
def test_a_compiled_speculative_call_encodes_its_images_with_the_compiled_encoder(tiny_llava, monkeypatch, graphs):
    """A compiled speculative call of a VLM hands ``generate`` its images encoded by the verifier's compiled
    ``get_image_features`` (one graph per batch size: with graph files exported whole and saved, in memory traced by
    dynamo with its breaks), with greedy's tokens; greedy calls and eager speculative calls leave the encoding to
    transformers (its eager ``get_image_features``, counted here)."""
    from transformers.models.llava.modeling_llava import LlavaModel

    from hf_specvla.speculative import graph_files
    from hf_specvla.speculative.compiled import reset_compilation

    if graphs == "in memory":
        monkeypatch.setenv(graph_files.FOLDER_ENV, "off")
    reset_compilation()  # the model's graphs made anew, where ``graphs`` says

    from ..conftest import llava_prompt

    config = eager_compile_config()
    compiled = dict(cache_implementation="static", compile_config=config)
    eager_encodings = []
    original = LlavaModel.get_image_features

    @functools.wraps(original)  # its signature: what transformers hands the encoder
    def counted(self, *args, **kwargs):
        if not torch.compiler.is_compiling():
            eager_encodings.append(1)
        return original(self, *args, **kwargs)

    monkeypatch.setattr(LlavaModel, "get_image_features", counted)
    generator = torch.Generator().manual_seed(4)
    for batch_size in (1, 2, 1):
        prompts = [llava_prompt(generator, text_len=3) for _ in range(batch_size)]
        prompt = {name: torch.cat([p[name] for p in prompts]) for name in prompts[0]}
        expected = greedy(tiny_llava, **prompt)  # eager greedy: transformers encodes, once
        assert len(eager_encodings) == 1
        eager_encodings.clear()
        drafts = expected[:, prompt["input_ids"].shape[1] : -1]
        out = greedy(tiny_llava, **prompt, draft_ids=drafts, return_dict_in_generate=True, **compiled)
        assert torch.equal(out.sequences, expected) and out.speculation.num_batch_forwards == 1
        assert eager_encodings == []  # the compiled encoder's call, not transformers' eager one
        assert torch.equal(greedy(tiny_llava, **prompt, **compiled), expected)  # compiled greedy: transformers'
        assert torch.equal(greedy(tiny_llava, **prompt, draft_ids=drafts), expected)  # eager speculation: the same
        assert len(eager_encodings) == 2
        eager_encodings.clear()
    verifier = SpeculativeDecoder.of(tiny_llava).graphs(config)
    assert verifier.image_batch_sizes == {1, 2} and (verifier.store is None) == (graphs == "in memory")
    if graphs == "files":  # exported as one graph per batch size, compiled as a file
        assert len(verifier.image_encoders) == 2 and None not in verifier.image_encoders.values()
    else:  # dynamo's graphs of get_image_features, with breaks
        assert verifier.image_encoders == {} and graphs_held(tiny_llava.base_model.get_image_features) >= 1
    reset_compilation()  # (the next test's graphs: by the folder it sets)


@pytest.mark.slow  # ~16 s: a timing utility, not a lossless guard
def test_a_clock_times_the_compiled_image_encoder_as_vision():
    """``ForwardClock`` times the engine's compiled image encoder from outside (``ENCODER_WRAPPER_ATTRIBUTE``), once
    per call: its vision time is one encoder call's, not zero (the compiled graph runs no hooks) and not the hooks'
    on top (a graph break may run them)."""
    from hf_specvla.benchmarks.speed import ForwardClock

    from ..policies.test_action_chunks import ACTIONS, INSTRUCTIONS, SMALL, STATES, action_only
    from ..policies.test_action_chunks import observation as chunk_observation

    torch.manual_seed(0)
    policy = action_only(VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**SMALL)))
    clock = ForwardClock(policy.model)
    timed = []
    original = policy.model.__dict__["_hf_specvla_wrap_compiled_encoder"]

    def counting(encoder):
        def encode(*args, **kwargs):
            start = time.perf_counter()
            output = encoder(*args, **kwargs)
            timed.append(time.perf_counter() - start)
            return output

        return original(encode)

    policy.model._hf_specvla_wrap_compiled_encoder = counting
    compiled = dict(cache_implementation="static", compile_config=eager_compile_config())
    image, state = chunk_observation(0)
    for _ in range(2):
        clock.reset()
        policy.previous_action_ids = [[200, 210, 220, 230]]
        policy.predict_action(image, "reach the goal", state, action_prior=True, bin_tolerance=0, **compiled)
        assert len(timed) == 1 and 0 < clock.vision_seconds < 1.5 * timed[0]
        timed.clear()
