"""EAGLE-2 expansion in tensors (``drafters/eagle_tree.py``): the tree masks keep siblings apart, the backbone is the
head's greedy chain, the re-ranking keeps what it says, and the compiled static-cache run drafts the same tree as the
eager dynamic-cache run."""

from __future__ import annotations

import copy
from functools import partial

import pytest
import torch
from transformers.cache_utils import DynamicCache, StaticCache

from hf_specvla.speculative.drafters.draft_head import embed_tokens
from hf_specvla.speculative.drafters.eagle_tree import (
    catch_up_and_expand,
    expand_tree,
    num_created_nodes,
    num_head_entries,
)
from hf_specvla.speculative.masks import causal_allowed, causal_mask, to_additive_mask
from hf_specvla.speculative.tree import DraftTree

COMMITTED = 5


@pytest.fixture(scope="module")
def head_and_target(tiny_llama, random_draft):
    """A head whose attention matters (its value / output projections scaled up), so that a mask letting a node see
    its siblings changes its features and, with them, the drafted tokens."""
    head = copy.deepcopy(random_draft)
    with torch.no_grad():
        head.layer.self_attn.v_proj.weight.mul_(40)
        head.layer.self_attn.o_proj.weight.mul_(40)
    handles = head.target_handles(tiny_llama)
    return head, handles, head.scorer(handles.lm_head)


def committed_pairs(hidden_size: int):
    """COMMITTED random (token, hidden, position) pairs, as the target commits them."""
    generator = torch.Generator().manual_seed(7)
    tokens = torch.randint(64, 320, (1, COMMITTED), generator=generator)
    hidden = torch.randn(1, COMMITTED, hidden_size, generator=generator) * 3
    return tokens, hidden, torch.arange(COMMITTED)[None]


def committed_head(head, handles, cache, key_length=None, count=COMMITTED):
    """Feeds the first ``count`` committed pairs; returns the root feature ``[1, 1, H]`` and the root's position."""
    tokens, hidden, positions = (t[:, :count] for t in committed_pairs(head.config.hidden_size))
    allowed = causal_allowed(count, 0, hidden.device)
    if key_length is not None:
        allowed = torch.cat([allowed, allowed.new_zeros(1, count, key_length - count)], dim=-1)
    features = head(embed_tokens(handles, tokens), hidden, positions, to_additive_mask(allowed, hidden.dtype), cache)
    return features[:, -1:].clone(), torch.tensor([[COMMITTED]])


def expand(head_and_target, top_k, depth, total_tokens):
    head, handles, scorer = head_and_target
    cache = DynamicCache()
    with torch.no_grad():
        root, position = committed_head(head, handles, cache)
        return expand_tree(head, partial(embed_tokens, handles), scorer, root, position, cache, COMMITTED, None,
                           top_k, depth, total_tokens)  # fmt: skip


def greedy_chain(head_and_target, depth) -> list[int]:
    """The head's greedy chain, one plain causal forward per token (no tree, no expansion code)."""
    head, handles, scorer = head_and_target
    cache = DynamicCache()
    with torch.no_grad():
        feature, position = committed_head(head, handles, cache)
        tokens = []
        for level in range(depth):
            token = scorer.token_ids(feature[0, -1])
            tokens.append(int(token))
            if level + 1 < depth:
                mask = causal_mask(1, COMMITTED + level, feature.dtype, feature.device)
                positions = position + level
                feature = head(embed_tokens(handles, token.reshape(1, 1)), feature, positions, mask, cache)
    return tokens


@pytest.mark.parametrize("top_k, depth, total_tokens", [(1, 4, 4), (3, 4, 12), (4, 5, 24), (2, 6, 8)])
def test_the_backbone_is_the_heads_greedy_chain(head_and_target, top_k, depth, total_tokens):
    """Siblings fed in one forward never see each other: the greedy path's tokens are the chain's, node by node."""
    token_ids, parents = expand(head_and_target, top_k, depth, total_tokens)
    tree = DraftTree(token_ids, parents)
    assert tree.num_nodes == min(total_tokens, num_created_nodes(top_k, depth))
    chain = greedy_chain(head_and_target, depth)
    assert any(path[:depth] == chain for path in tree.token_paths()), (chain, tree.token_paths())


def test_a_leaking_mask_would_be_caught(head_and_target, monkeypatch):
    """The check above is sharp: a frontier mask that lets every node see every tree entry changes the chain."""
    import hf_specvla.speculative.drafters.eagle_tree as eagle_tree

    real = eagle_tree.frontier_mask
    monkeypatch.setattr(eagle_tree, "frontier_mask", lambda visible, *a: real(torch.ones_like(visible), *a))
    token_ids, parents = expand(head_and_target, 4, 5, 24)
    chain = greedy_chain(head_and_target, 5)
    assert not any(path[:5] == chain for path in DraftTree(token_ids, parents).token_paths())


def test_reranking_keeps_the_budget_the_backbone_and_every_ancestor(head_and_target):
    top_k, depth = 3, 4
    everything = DraftTree(*expand(head_and_target, top_k, depth, 10_000))
    assert everything.num_nodes == num_created_nodes(top_k, depth)  # 3 + 3 levels x 3 frontier x 3 children
    assert everything.max_depth == depth
    children = torch.bincount(everything.parents + 1)
    assert int(children[0]) == top_k and int(children.max()) == top_k  # the root and each expanded node: k children
    assert int((children[1:] > 0).sum()) == (depth - 1) * top_k  # a frontier of k nodes per level
    only_backbone = DraftTree(*expand(head_and_target, top_k, depth, depth))
    assert only_backbone.is_chain and only_backbone.token_paths() == [greedy_chain(head_and_target, depth)]
    for total in (5, 9, 17):
        tree = DraftTree(*expand(head_and_target, top_k, depth, total))  # DraftTree checks parents come first
        assert tree.num_nodes == total
        kept = set(map(tuple, tree.token_paths()))
        assert all(any(path[: len(p)] == list(p) for path in everything.token_paths()) for p in kept)


@pytest.mark.parametrize("total_tokens", [3, 8, 30])
def test_a_depth_limit_gives_the_shallower_expansions_tree(head_and_target, total_tokens):
    """One graph expanded to depth 5 serves a round that may draft only 2 or 3 levels: with ``depth_limit`` the
    nodes above the limit are ranked exactly as the shallower expansion ranks its own, the deeper ones last."""
    head, handles, scorer = head_and_target
    for limit in (1, 2, 3):
        shallow = DraftTree(*expand(head_and_target, 3, limit, total_tokens))
        cache = DynamicCache()
        with torch.no_grad():
            root, position = committed_head(head, handles, cache)
            deep = expand_tree(head, partial(embed_tokens, handles), scorer, root, position, cache, COMMITTED, None,
                               3, 5, total_tokens, depth_limit=torch.tensor(limit))  # fmt: skip
        limited = DraftTree(*deep).truncate_depth(limit)
        assert limited.token_paths() == shallow.token_paths(), limit
        assert torch.equal(limited.parents, shallow.parents), limit


def test_a_compiled_round_on_a_static_cache_drafts_what_the_eager_run_drafts(head_and_target):
    """The catch-up (padded pairs) and the expansion in one graph (dynamo, eager backend, fullgraph: no graph break)
    draft the eager dynamic-cache run's tree, whatever the number of real pairs; the counts and the committed length
    are tensors, so they reuse the graph."""
    head, handles, scorer = head_and_target
    torch._dynamo.reset()
    compiled = torch.compile(catch_up_and_expand, backend="eager", fullgraph=True, dynamic=False)
    top_k, depth, total, slots, padded = 3, 4, 12, 64, 5
    expected = expand(head_and_target, top_k, depth, total)
    pairs = committed_pairs(head.config.hidden_size)
    for num_new in (1, 3, 4):  # the last num_new pairs fed in the round, padded to 5 (the first fed eagerly)
        static = StaticCache(config=head.config.to_llama_config(), max_cache_len=slots)
        with torch.no_grad(), torch._dynamo.config.patch(error_on_recompile=num_new != 1):
            committed_head(head, handles, static, key_length=slots, count=COMMITTED - num_new)
            new = [t[:, COMMITTED - num_new :] for t in pairs]
            fill = padded - num_new
            round_pairs = (
                torch.cat([new[0], new[0].new_zeros(1, fill)], 1),
                torch.cat([new[1], torch.randn(1, fill, new[1].shape[-1])], 1),  # padding: any values
                torch.cat([new[2], new[2][:, -1:].expand(1, fill)], 1),
            )
            got = compiled(head, partial(embed_tokens, handles), scorer, *round_pairs, torch.tensor(num_new),
                           torch.tensor([[COMMITTED]]), static, static.layers[0].cumulative_length.clone(), slots,
                           top_k, depth, total)  # fmt: skip
        assert torch.equal(got[0], expected[0]) and torch.equal(got[1], expected[1]), num_new
        written = COMMITTED - num_new + padded + num_head_entries(top_k, depth)
        assert int(static.layers[0].cumulative_length) == written
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 1
    torch._dynamo.reset()


@pytest.mark.parametrize("seed", range(6))
def test_a_tree_left_on_the_device_derives_what_its_host_copy_does(seed):
    """A drafter's tree may keep its parents on the device (no read while drafting): its depths, tree mask and cuts
    equal those derived from the host copy, and reading it back gives the same structure."""
    generator = torch.Generator().manual_seed(seed)
    num_nodes = int(torch.randint(1, 20, (1,), generator=generator))
    parents = [-1] + [int(torch.randint(-1, i, (1,), generator=generator)) for i in range(1, num_nodes)]
    tokens = torch.randint(0, 100, (num_nodes,), generator=generator)
    host = DraftTree(tokens, torch.tensor(parents))
    on_device = DraftTree(tokens, torch.tensor(parents), structure_on_device=True, depth_bound=host.max_depth)
    assert not on_device.knows_structure() and not on_device.is_chain  # read nothing yet
    assert torch.equal(on_device.ancestor_or_self, host.ancestor_or_self)
    assert torch.equal(on_device.depths, host.depths)
    for keep in (0, num_nodes // 2, num_nodes):
        cut = on_device.truncate_nodes(keep)
        assert not cut.knows_structure() or keep >= num_nodes
        assert torch.equal(cut.ancestor_or_self, host.truncate_nodes(keep).ancestor_or_self)
    assert on_device.truncate_depth(host.max_depth) is on_device  # within its bound: nothing to cut, nothing read
    assert on_device.parent_list == parents and on_device.knows_structure()  # read back once
    assert on_device.truncate_depth(1).token_paths() == host.truncate_depth(1).token_paths()
