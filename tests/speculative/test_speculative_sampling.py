"""Lossless speculative sampling (``do_sample=True``): whatever the drafter, the generated tokens are distributed
exactly as the target's own sampling. Checked against the exact distribution of the first 3 tokens (enumerated from
the target's processed scores) with a chi-square test over 8,000 samples per drafter and temperature (twice the 4,000
on which the same check rejects each wrong sampler below with p < 1e-6), and at a temperature near 0 against greedy
decoding. The check is shown to fail on wrong samplers (plain sampling at another temperature, a speculative sampler
that accepts every draft, one that samples the bonus token without removing the rejected draft), and every drafter's
cases must have had drafts accepted (a drafter never accepted would test only the target's own sampling)."""

from __future__ import annotations

import itertools

import pytest
import torch
from transformers import LlamaForCausalLM, LogitsProcessorList
from transformers.generation.logits_process import (
    SuppressTokensLogitsProcessor,
    TemperatureLogitsWarper,
    TopPLogitsWarper,
)

from hf_specvla import (
    ActionLayout,
    ActionPriorDrafter,
    ComposedDrafter,
    DraftHead,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
    enable_speculation,
)
from hf_specvla.speculative import AcceptedPath, rounds
from hf_specvla.training.draft_head import DraftTrainingConfig, build_distillation_dataset, train_draft_head

from ..conftest import tiny_llama_config

NEW_TOKENS, ACTION_DIM, TOP_P = 3, 3, 0.9
SAMPLES, ROWS = 8_000, 4_000  # samples per drafter and temperature, rows per batched call
PROMPT = [5, 17, 42, 99]


@pytest.fixture(scope="module")
def peaked():
    """A random tiny Llama whose next-token distributions are peaked (a handful of likely tokens), so that the
    distribution of 3 tokens has few outcomes and every drafter's drafts are accepted often enough to matter."""
    torch.manual_seed(7)
    model = LlamaForCausalLM(tiny_llama_config()).eval()
    with torch.no_grad():
        model.lm_head.weight.mul_(30)
    return enable_speculation(model)


@pytest.fixture(scope="module")
def head(peaked, action_tokenizer):
    """A random head: its drafts are (almost) never accepted at T=0.7 (0 of 60,000), only the residual path."""
    torch.manual_seed(8)
    return DraftHead.from_target(peaked, action_tokenizer, action_dim=ACTION_DIM, draft_action_tokens_only=False).eval()


@pytest.fixture(scope="module")
def distilled_head(peaked, action_tokenizer, tmp_path_factory):
    """A head distilled from the target for a moment (200 steps, about a second) on the prompt followed by each of
    its likely 1- and 2-token prefixes: its drafts are accepted about once per sample and rejected about as often,
    so both branches of the rejection sampling run."""
    likely = sorted(exact_distribution(peaked, action_tokenizer, 1.0).items(), key=lambda item: -item[1])[:40]
    prefixes = sorted({outcome[:length] for outcome, _ in likely for length in (1, 2)})
    prompts = [{"input_ids": torch.tensor([PROMPT + list(prefix)])} for prefix in prefixes]
    dataset = build_distillation_dataset(peaked, prompts, NEW_TOKENS, action_tokenizer, progress=False)
    torch.manual_seed(8)
    head = DraftHead.from_target(peaked, action_tokenizer, action_dim=ACTION_DIM, draft_action_tokens_only=False)
    config = DraftTrainingConfig(str(tmp_path_factory.mktemp("distilled")), max_steps=200, learning_rate=1e-3,
                                 feature_noise=0.0)  # fmt: skip
    return train_draft_head(head, peaked, dataset, config, progress=False)


def _processors(action_tokenizer, temperature: float) -> LogitsProcessorList:
    """What ``generate`` applies for the sampling settings of these tests (processors, then warpers, in its order)."""
    return LogitsProcessorList([
        SuppressTokensLogitsProcessor(list(range(action_tokenizer.action_token_begin))),
        TemperatureLogitsWarper(temperature),
        TopPLogitsWarper(TOP_P),
    ])  # fmt: skip


@torch.no_grad()
def exact_distribution(model, action_tokenizer, temperature: float) -> dict[tuple[int, ...], float]:
    """P(first 3 generated tokens) under the target's sampling, enumerated over every prefix with mass."""
    processors = _processors(action_tokenizer, temperature)
    outcomes = {(): 1.0}
    for _ in range(NEW_TOKENS):
        grown = {}
        for prefix, mass in outcomes.items():
            ids = torch.tensor([PROMPT + list(prefix)])
            probs = processors(ids, model(input_ids=ids).logits[:, -1].float()).softmax(-1)[0]
            for token in torch.nonzero(probs > 0).flatten().tolist():
                grown[prefix + (token,)] = mass * float(probs[token])
        outcomes = grown
    return outcomes


def chi_square_p_value(counts: dict, expected: dict[tuple, float], total: int) -> tuple[float, int]:
    """Pearson's test of ``counts`` against the probabilities ``expected`` (outcomes expected fewer than 5 times
    pooled into one cell); returns (p-value, cells)."""
    big = [k for k, p in expected.items() if p * total >= 5]
    observed = [counts.get(k, 0) for k in big] + [total - sum(counts.get(k, 0) for k in big)]
    wanted = [expected[k] * total for k in big] + [total * (1 - sum(expected[k] for k in big))]
    if wanted[-1] < 5:  # nothing to pool: the big cells hold (almost) all the mass
        observed[-2] += observed.pop()
        wanted[-2] += wanted.pop()
    statistic = sum((o - w) ** 2 / w for o, w in zip(observed, wanted))
    dof = len(wanted) - 1
    p_value = float(torch.special.gammaincc(torch.tensor(dof / 2, dtype=torch.float64),
                                            torch.tensor(statistic / 2, dtype=torch.float64)))  # fmt: skip
    return p_value, len(wanted)


def _drafter(kind: str, head, layout: ActionLayout, likely: list[tuple[int, ...]]) -> dict:
    """``generate`` arguments drafting with each kind of drafter. The prior's history is the most likely action with
    its last token moved (right, then wrong: both branches of the rejection sampling); ``candidates`` drafts the four
    most likely 3-token outcomes as one tree in the prefill (accepts and rejections at every depth)."""
    history = [list(likely[0][:-1]) + [likely[0][-1] + 1]]
    tree = DraftTreeConfig(top_k=2, depth=3, total_tokens=6)
    if kind == "candidates":
        return {"draft_ids": torch.tensor([likely[:4]] * ROWS)}  # [B, C, k]
    drafter = {
        "chain": lambda: head,  # the distilled head's chain
        "tree": lambda: DraftHeadDrafter(head, tree=tree),
        "prior": lambda: ActionPriorDrafter(history, layout),
        "jacobi": lambda: JacobiDrafter(),
        "composed": lambda: ComposedDrafter(
            [ActionPriorDrafter(history, layout), JacobiDrafter(), DraftHeadDrafter(head, tree=tree)]
        ),  # fmt: skip
    }[kind]()
    return {"assistant_model": drafter}


SLOW = pytest.mark.slow  # 15-45 s each for 8,000 samples on one CPU thread (a drafter session per row)
CASES = [("candidates", 0.7), ("candidates", 1.0), ("prior", 0.7)] + [
    pytest.param(kind, temperature, marks=SLOW)
    for kind, temperature in [("prior", 1.0), ("jacobi", 0.7), ("jacobi", 1.0), ("chain", 0.7), ("chain", 1.0),
                              ("tree", 0.7), ("tree", 1.0), ("composed", 0.7), ("composed", 1.0)]
]  # fmt: skip


def _sample(peaked, action_tokenizer, kind: str, temperature: float, head, expected,
            samples: int = SAMPLES) -> tuple[dict, int]:  # fmt: skip
    """``samples`` samples of the first 3 tokens drafted by ``kind``: (count per outcome, drafts accepted)."""
    layout = ActionLayout(action_tokenizer, ACTION_DIM)
    likely = sorted(expected, key=expected.get, reverse=True)
    counts: dict[tuple, int] = {}
    accepted = 0
    torch.manual_seed(100)
    for _ in range(samples // ROWS):
        out = peaked.generate(
            input_ids=torch.tensor([PROMPT] * ROWS), max_new_tokens=NEW_TOKENS, do_sample=True, temperature=temperature,
            top_p=TOP_P, top_k=0, suppress_tokens=list(range(action_tokenizer.action_token_begin)),
            action_layout=layout, return_dict_in_generate=True, **_drafter(kind, head, layout, likely),
        )  # fmt: skip
        for row in out.sequences[:, len(PROMPT) :].tolist():
            counts[tuple(row)] = counts.get(tuple(row), 0) + 1
        accepted += sum(out.speculation.accepted_per_position)
    return counts, accepted


@pytest.mark.parametrize("kind, temperature", CASES)
def test_speculative_sampling_keeps_the_targets_distribution(peaked, action_tokenizer, request, kind, temperature):
    expected = exact_distribution(peaked, action_tokenizer, temperature)
    head = request.getfixturevalue("distilled_head") if kind in ("chain", "tree", "composed") else None
    counts, accepted = _sample(peaked, action_tokenizer, kind, temperature, head, expected)
    p_value, cells = chi_square_p_value(counts, expected, SAMPLES)
    print(f"{kind} T={temperature}: chi-square p={p_value:.3f} over {cells} cells, {accepted} drafts accepted")
    assert cells >= 5 and p_value > 0.01, (kind, temperature, p_value, cells)
    # drafts were accepted: the speculative path was tested, not only the target's sampling (Jacobi's rarely: it
    # guesses only past a rejection)
    assert accepted > SAMPLES // (100 if kind == "jacobi" else 10), accepted


def test_the_test_detects_a_wrong_distribution(peaked, action_tokenizer):
    """The chi-square check rejects plain sampling at another temperature (the test is not vacuous)."""
    expected = exact_distribution(peaked, action_tokenizer, 0.7)
    torch.manual_seed(101)
    out = peaked.generate(input_ids=torch.tensor([PROMPT] * SAMPLES), max_new_tokens=NEW_TOKENS, do_sample=True,
                          temperature=0.8, top_p=TOP_P, top_k=0,
                          suppress_tokens=list(range(action_tokenizer.action_token_begin)))  # fmt: skip
    counts: dict[tuple, int] = {}
    for row in out[:, len(PROMPT) :].tolist():
        counts[tuple(row)] = counts.get(tuple(row), 0) + 1
    assert chi_square_p_value(counts, expected, SAMPLES)[0] < 1e-6


def wrong_sampler(accept_every_draft: bool = False, remove_rejected: bool = True):
    """A deliberately wrong ``sample_trees`` (the engine's, with one mistake): ``accept_every_draft`` takes each
    node's first child whatever the target's probability of it; ``remove_rejected=False`` samples the bonus token
    from the target's distribution without taking the rejected drafts out (the draft is then emitted more often than
    the target samples it)."""

    def sample_trees(trees, scores, generator=None) -> list[AcceptedPath]:
        probs = scores.float().softmax(dim=-1).cpu()  # [B, 1 + N, V]
        paths = []
        for b, tree in enumerate(trees.trees):
            children: dict[int, list[int]] = {}
            for node, parent in enumerate(tree.parent_list):
                children.setdefault(parent, []).append(node)
            nodes, at = [], -1
            while True:
                p, chosen = probs[b, at + 1].clone(), None
                for child in children.get(at, []):
                    token = tree.host_tokens[child]
                    if accept_every_draft or float(torch.rand((), generator=generator)) < float(p[token]):
                        chosen = child
                        break
                    if remove_rejected:
                        p[token] = 0.0
                        p /= p.sum()
                if chosen is None:
                    bonus = int(torch.multinomial(p, 1, generator=generator))
                    break
                nodes.append(chosen)
                at = chosen
            paths.append(AcceptedPath(nodes, bonus, [0] * len(nodes), None))
        return paths

    return sample_trees


@pytest.mark.parametrize(
    "mistake, settings",
    [("accepts every draft", dict(accept_every_draft=True)), ("keeps the rejected draft", dict(remove_rejected=False)),
     ("none", {})],
)  # fmt: skip
def test_the_test_detects_a_wrong_speculative_sampler(peaked, action_tokenizer, monkeypatch, mistake, settings):
    """The same check, on the prior's drafts at T=0.7 (a case above; here on one batch of 4,000 samples, fewer than
    there, so a rejection here is one there too), rejects a speculative sampler with one mistake, which still accepts
    drafts; the same sampler without the mistake passes it (the mistake is what fails)."""
    expected = exact_distribution(peaked, action_tokenizer, 0.7)
    monkeypatch.setattr(rounds, "sample_trees", wrong_sampler(**settings))  # what the rounds sample with
    counts, accepted = _sample(peaked, action_tokenizer, "prior", 0.7, None, expected, samples=ROWS)
    assert accepted > ROWS // 10, accepted  # the sampler ran on drafts
    p_value, cells = chi_square_p_value(counts, expected, ROWS)
    print(f"{mistake}: chi-square p={p_value:.3g} over {cells} cells, {accepted} drafts accepted")
    if mistake == "none":
        assert p_value > 0.01, (p_value, cells)
    else:
        assert p_value < 1e-6, (mistake, p_value, cells)


def test_near_zero_temperature_is_greedy(peaked, head, action_tokenizer):
    layout = ActionLayout(action_tokenizer, ACTION_DIM)
    actions_only = dict(suppress_tokens=list(range(action_tokenizer.action_token_begin)))
    for prompt in ([5, 17, 42, 99], [3, 8], [200, 150, 64, 70, 9]):
        ids = torch.tensor([prompt] * 4)
        greedy = peaked.generate(input_ids=ids, max_new_tokens=6, do_sample=False, **actions_only)
        for drafter in (head, JacobiDrafter(), ActionPriorDrafter([greedy[0, -6:-3].tolist()], layout)):
            sampled = peaked.generate(input_ids=ids, max_new_tokens=6, do_sample=True, temperature=1e-3, top_k=0,
                                      assistant_model=drafter, action_layout=layout, **actions_only)  # fmt: skip
            assert torch.equal(sampled, greedy)


def test_a_seed_gives_the_same_samples(peaked, head):
    runs = []
    for _ in range(2):
        torch.manual_seed(5)
        runs.append(peaked.generate(input_ids=torch.tensor([PROMPT] * 8), max_new_tokens=5, do_sample=True,
                                    assistant_model=head))  # fmt: skip
    assert torch.equal(*runs)
    assert len({tuple(r) for r in runs[0].tolist()}) > 1  # rows sampled apart


def test_relaxed_acceptance_is_greedy_only(peaked, head):
    with pytest.raises(ValueError, match="relaxed acceptance .* is greedy only: with do_sample=True"):
        peaked.generate(input_ids=torch.tensor([PROMPT]), max_new_tokens=3, do_sample=True, assistant_model=head,
                        bin_tolerance=2)  # fmt: skip
    # r = 0 with any gate or budget is exact acceptance: sampling is allowed
    peaked.generate(input_ids=torch.tensor([PROMPT]), max_new_tokens=3, do_sample=True, assistant_model=head,
                    bin_tolerance=0, confidence_gate=0.5)  # fmt: skip


def test_every_outcome_of_the_enumeration_sums_to_one(peaked, action_tokenizer):
    for temperature in (0.7, 1.0):
        expected = exact_distribution(peaked, action_tokenizer, temperature)
        assert sum(expected.values()) == pytest.approx(1.0, abs=1e-5)
        assert all(len(k) == NEW_TOKENS for k in expected) and len(expected) > 5
        assert all(t >= action_tokenizer.action_token_begin for k in expected for t in itertools.chain(k))
