"""Host syncs per round (issue 54, item 2): the engine reads the device once per verification (the accepted paths,
bonus tokens, the target's tokens and the trees' structure, packed), answers generate's stopping criteria on the host
and drafts without reading the device (a draft head's tree keeps its structure there until that read). Counted through
a ``TorchFunctionMode`` ([`HostSyncCounter`]) on eager calls on a ``DynamicCache`` and compiled calls on a static
cache (its length counted on the host).

Before this work (85f94e7): prior+Jacobi 112 reads per 5-round call, a head chain or tree 105 per 8 rounds; now one a
round, and a few per call."""

from __future__ import annotations

import pytest
import torch

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    ComposedDrafter,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
)
from hf_specvla.speculative.syncs import HostSyncCounter

#: reads once per call, whatever the rounds: transformers' own generate around our loop (input preparation, 4), the
#: EOS ids for the host's stopping criteria, the Jacobi drafter's statistics at the end
PER_CALL = 6


def _count(model, input_ids, **kwargs) -> tuple[int, int, HostSyncCounter]:
    """(host syncs, target forwards = rounds, the counter) of one eager call after a warm one."""
    model.generate(input_ids=input_ids, max_new_tokens=8, do_sample=False, **kwargs)
    with HostSyncCounter() as counter:
        out = model.generate(input_ids=input_ids, max_new_tokens=8, do_sample=False, return_dict_in_generate=True,
                             **kwargs)  # fmt: skip
    return counter.count, out.speculation.num_target_forwards, counter


def test_model_free_drafters_read_the_device_once_a_round(tiny_llama, action_tokenizer):
    layout = ActionLayout(action_tokenizer, 4)
    input_ids = torch.tensor([[5, 17, 42, 99, 7]])
    actions_only = list(range(action_tokenizer.action_token_begin))
    greedy = tiny_llama.generate(input_ids=input_ids, max_new_tokens=8, do_sample=False, suppress_tokens=actions_only)
    history = [greedy[0, 5:9].tolist(), [t + 1 for t in greedy[0, 9:13].tolist()]]  # the second action wrong
    for drafter in (JacobiDrafter(), ComposedDrafter([ActionPriorDrafter(history, layout, chunk_length=2),
                                                     JacobiDrafter()])):  # fmt: skip
        syncs, rounds, counter = _count(tiny_llama, input_ids, assistant_model=drafter, action_layout=layout,
                                        suppress_tokens=actions_only)  # fmt: skip
        accept_reads = sum(n for site, n in counter.sites.items() if site.startswith("speculative/acceptance.py"))
        assert accept_reads == rounds and syncs <= rounds + PER_CALL, (rounds, counter.sites.most_common())


@pytest.mark.parametrize("tree", [None, DraftTreeConfig(top_k=2, depth=3, total_tokens=6)])
def test_a_draft_head_drafts_without_reading_the_device(tiny_llama, random_draft, tree):
    """A head's chain or tree is drafted on the device and read back with the verification (its structure too)."""
    drafter = random_draft if tree is None else DraftHeadDrafter(random_draft, tree=tree)
    syncs, rounds, counter = _count(tiny_llama, torch.tensor([[5, 17, 42, 99, 7]]), assistant_model=drafter)
    drafting = sum(n for site, n in counter.sites.items() if "drafters/" in site or site.startswith("speculative/tree"))
    assert drafting == 0 and syncs <= rounds + PER_CALL, (rounds, counter.sites.most_common())


def test_the_counter_counts_what_waits_for_the_device():
    x = torch.arange(4)
    with HostSyncCounter() as counter:
        x.tolist()
        int(x[0])
        bool(x.any())
        x.nonzero()
        x + 1  # no read
    assert counter.count == 4 and counter.sites["elsewhere"] == 4


@pytest.mark.slow  # ~110 s: inductor compiles the call's graphs (a host-read bound, not a lossless guard)
def test_a_compiled_call_counts_its_static_cache_on_the_host(tiny_llama, action_tokenizer, monkeypatch):
    """On a static cache (compiled verification), the cache's length is counted on the host: no read of its device
    counter per round (the check the tests turn on, which reads it, is off here)."""
    from hf_specvla.speculative import cache, compiled_decoding_kwargs

    monkeypatch.setattr(cache, "CHECK_HOST_LENGTH", False)
    input_ids = torch.tensor([[5, 17, 42, 99, 7]])
    syncs, rounds, counter = _count(tiny_llama, input_ids, assistant_model=JacobiDrafter(),
                                    **compiled_decoding_kwargs("cpu"))  # fmt: skip
    reads_of_the_counter = sum(n for site, n in counter.sites.items() if site.startswith("speculative/cache.py"))
    assert reads_of_the_counter <= 2, counter.sites  # per call: the entries before it, and where the count starts
    assert syncs <= rounds + PER_CALL + 3, (rounds, counter.sites.most_common())  # + the counter twice, the inputs


@pytest.mark.slow  # ~100 s: inductor compiles the head's and the target's graphs
def test_a_compiled_draft_head_tree_reads_once_a_round(tiny_llama, random_draft, monkeypatch):
    from hf_specvla.speculative import cache, compiled_decoding_kwargs

    monkeypatch.setattr(cache, "CHECK_HOST_LENGTH", False)
    drafter = DraftHeadDrafter(random_draft, tree=DraftTreeConfig(top_k=2, depth=3, total_tokens=6))
    syncs, rounds, counter = _count(tiny_llama, torch.tensor([[5, 17, 42, 99, 7]]), assistant_model=drafter,
                                    **compiled_decoding_kwargs("cpu"))  # fmt: skip
    # the call's last rounds, shallower than its compiled graph, cut the tree by depth on the host (one read each)
    shallower = sum(
        n for site, n in counter.sites.items() if "drafters/" in site or site.startswith("speculative/tree")
    )
    assert shallower <= 2 and syncs <= rounds + PER_CALL + 3 + shallower, (rounds, counter.sites.most_common())
