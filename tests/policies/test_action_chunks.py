"""Policies that predict a chunk of H actions per call: layout, training targets, and speculative decoding on
chunks (r=0 gives greedy's tokens for every drafter; relaxed tokens stay within r bins given their prefix)."""

import numpy as np
import pytest
import torch

from hf_specvla import (
    ActionLayout,
    ActionNormalizer,
    ActionPriorDrafter,
    ComposedDrafter,
    DraftHead,
    DraftHeadDrafter,
    DraftTreeConfig,
    JacobiDrafter,
)
from hf_specvla.policies import VLAPolicy, VLAPolicyConfig
from hf_specvla.speculative import DraftContext, DraftRound, with_action_prior
from hf_specvla.training.behaviour_cloning import action_chunk_indices, decoder_layer_map, grow_from

INSTRUCTIONS = ["reach the goal", "push the puck to the goal"]
SMALL = dict(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1, text_hidden_size=64,
             text_layers=2, text_heads=4)  # fmt: skip
CHUNK = 2
ACTIONS = ActionNormalizer(q01=[-1.0, -0.5, -1.0, -1.0], q99=[1.0, 0.5, 0.2, 1.0], mask=[True, True, True, False])
STATES = ActionNormalizer(q01=[-0.1, 0.5, 0.05, 0.0], q99=[0.1, 0.9, 0.3, 1.0])


def action_only(policy: VLAPolicy) -> VLAPolicy:
    """A random policy whose greedy tokens are action tokens (text rows of the lm_head zeroed), so that its
    actions can be drafted from."""
    with torch.no_grad():
        policy.model.lm_head.weight[: policy.action_tokenizer.action_token_begin] = 0
    return policy


@pytest.fixture(scope="module")
def chunked():
    torch.manual_seed(0)
    return action_only(VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**SMALL, chunk_length=CHUNK)))


def observation(seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (32, 32, 3), dtype=np.uint8), rng.uniform([-0.1, 0.5, 0.05, 0], [0.1, 0.9, 0.3, 1])


def test_chunk_indices_follow_the_episode_and_hold_its_last_action():
    episodes = np.array([7, 7, 7, 9, 9, 4])
    np.testing.assert_array_equal(
        action_chunk_indices(episodes, 3), [[0, 1, 2], [1, 2, 2], [2, 2, 2], [3, 4, 4], [4, 4, 4], [5, 5, 5]]
    )
    np.testing.assert_array_equal(action_chunk_indices(episodes, 1), np.arange(6)[:, None])


def test_predict_action_returns_the_chunk_and_it_round_trips(chunked):
    image, state = observation()
    actions, out = chunked.predict_action(image, "reach the goal", state, return_output=True)
    assert actions.shape == (CHUNK, 4)
    ids = out.sequences[0, -CHUNK * 4 :]
    assert out.sequences.shape[1] == len(chunked.prompt_ids("reach the goal", state)) + CHUNK * 4
    # tokens -> actions -> tokens: the chunk's actions are bin centers, so they encode back to the same ids
    np.testing.assert_array_equal(chunked.action_token_ids(actions).reshape(-1), ids.numpy())
    np.testing.assert_allclose(
        actions, ACTIONS.unnormalize(chunked.action_tokenizer.decode(ids.reshape(CHUNK, 4).numpy()))
    )
    # the episode memory keeps the chunk's actions in order
    assert chunked.previous_action_ids[-CHUNK:] == ids.reshape(CHUNK, 4).tolist()
    batch, _ = chunked.predict_action(np.stack([image, image]), "reach the goal", np.stack([state, state]),
                                      return_output=True)  # fmt: skip
    assert batch.shape == (2, CHUNK, 4)
    np.testing.assert_array_equal(batch[0], actions)


def test_training_targets_are_the_chunk_then_the_scene(chunked):
    image, state = observation()
    chunk = np.array([[[0.1, 0.2, -0.3, 1.0], [0.2, 0.1, -0.2, -1.0]]] * 2)  # [B, H, A]
    batch = chunked.training_batch(image[None].repeat(2, 0), [state, state], chunk, INSTRUCTIONS)
    labelled = batch["labels"] != -100
    assert int(labelled.sum()) == 2 * CHUNK * 4
    np.testing.assert_array_equal(batch["labels"][0][labelled[0]].numpy(), chunked.action_token_ids(chunk[0]).ravel())
    assert torch.isfinite(chunked.model(**batch).loss)


def test_a_chunk_or_layout_the_config_does_not_have_is_refused(chunked):
    image, state = observation()
    with pytest.raises(ValueError, match=r"chunk_length=2 actions of action_dim=4.*\[B, 2, 4\].*got \[2, 4\]"):
        chunked.training_batch(image[None].repeat(2, 0), [state, state], [[0.1, 0.2, -0.3, 1.0]] * 2, INSTRUCTIONS)
    with pytest.raises(ValueError, match=r"got \[1, 3, 4\]"):
        chunked.training_batch(image[None], [state], np.zeros((1, 3, 4)), INSTRUCTIONS[:1])
    with pytest.raises(ValueError, match=r"got \[1, 2, 3\]"):
        chunked.training_batch(image[None], [state], np.zeros((1, 2, 3)), INSTRUCTIONS[:1])
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match=rf"VLAPolicyConfig.chunk_length must be (an integer )?>= 1, got {bad!r}"):
            VLAPolicyConfig(**SMALL, chunk_length=bad)


def drafters(policy: VLAPolicy) -> dict:
    torch.manual_seed(1)
    head = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=4, num_draft_tokens=3).eval()
    tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=10))
    jacobi_tree = ComposedDrafter([JacobiDrafter(fill=False), tree])
    return {"head": dict(assistant_model=head), "tree": dict(assistant_model=tree), "prior": dict(action_prior=True),
            "prior+tree": dict(action_prior=True, assistant_model=tree),
            "jacobi": dict(assistant_model=JacobiDrafter()),
            "prior+jacobi": dict(action_prior=True, assistant_model=JacobiDrafter()),
            "prior+jacobi+tree": dict(action_prior=True, assistant_model=jacobi_tree)}  # fmt: skip


@pytest.mark.parametrize("cache", ["dynamic", "static"])
@pytest.mark.parametrize(
    "method", ["head", "tree", "prior", "prior+tree", "jacobi", "prior+jacobi", "prior+jacobi+tree"]
)
def test_r0_gives_greedys_chunk_for_every_drafter(chunked, method, cache):
    """Against plain greedy on the default cache; ``predict_action`` passes ``cache_implementation`` through."""
    kwargs = dict(drafters(chunked)[method])
    if cache == "static":
        kwargs["cache_implementation"] = "static"
    for seed in range(4):
        image, state = observation(seed)
        history = [chunked.action_token_ids(np.random.default_rng(seed).uniform(-1, 1, 4)).tolist()] * 2
        chunked.previous_action_ids = list(history)
        plain, plain_out = chunked.predict_action(image, "reach the goal", state, return_output=True)
        chunked.previous_action_ids = list(history)
        spec, spec_out = chunked.predict_action(image, "reach the goal", state, return_output=True, **kwargs)
        assert torch.equal(plain_out.sequences, spec_out.sequences)
        np.testing.assert_array_equal(plain, spec)
        assert spec_out.speculation.num_new_tokens == CHUNK * 4


def test_the_prior_drafts_a_whole_chunk_inside_the_prefill(chunked):
    """With the same observation again, holding the chunk's last action is right wherever the chunk holds still;
    with r = 255 every drafted action token is accepted: the whole chunk costs one target forward."""
    image, state = observation(3)
    chunked.reset()
    chunked.predict_action(image, "reach the goal", state)
    _, out = chunked.predict_action(image, "reach the goal", state, return_output=True, action_prior=True,
                                    bin_tolerance=255)  # fmt: skip
    assert out.speculation.num_target_forwards == 1 and out.speculation.num_new_tokens == CHUNK * 4
    assert out.speculation.accepted_by_drafter["prior"] == CHUNK * 4 - 1


def test_prior_candidates_span_the_chunk():
    layout = ActionLayout(VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**SMALL)).action_tokenizer, 4)
    last, older = [100, 110, 120, 130], [102, 110, 118, 130]
    prior = ActionPriorDrafter([older, last], layout, neighbour_bins=0, chunk_length=3)
    paths = prior.candidate_paths()
    assert all(len(path) == 12 for path in paths)
    assert paths[0] == last * 3  # hold
    assert paths[1] == [98, 110, 122, 130, 96, 110, 124, 130, 94, 110, 126, 130]  # constant velocity
    assert paths[2] == older * 3
    one = ActionPriorDrafter([older, last], layout, neighbour_bins=0).candidate_paths()
    assert [p[:4] for p in paths] == one  # the chunk's first action: exactly the one-action prior's candidates


def test_the_prior_drafts_later_rounds_alone_and_only_the_prefill_before_another_drafter(chunked):
    """Alone, the prior proposes its candidates' remaining parts after a partial acceptance; composed
    (``with_action_prior``) it drafts in the prefill only and the other drafter continues."""
    layout = ActionLayout(chunked.action_tokenizer, 4)
    history = [[100, 110, 120, 130], [102, 110, 118, 130]]
    alone = with_action_prior(None, history, layout, chunk_length=CHUNK)
    composed = with_action_prior(JacobiDrafter(), history, layout, chunk_length=CHUNK)
    assert alone.later_rounds and not composed.drafters[0].later_rounds
    assert composed.drafters[0].max_nodes == CHUNK * 4  # the held action alone: a chain
    context = DraftContext(chunked.model, layout, [], None)
    sequence, position = torch.tensor([[5, 6, 100, 110]]), torch.tensor([[3]])
    for at_prefill, drafted_alone, drafted_composed in ((True, True, True), (False, True, False)):
        draft_round = DraftRound(sequence, 2, 6, at_prefill, position)
        assert (alone.start(context).propose(draft_round).num_nodes > 0) == drafted_alone
        assert (composed.drafters[0].start(context).propose(draft_round).num_nodes > 0) == drafted_composed
    with pytest.raises(TypeError, match="later_rounds must be True or False, got 'no'"):
        ActionPriorDrafter(history, layout, later_rounds="no")
    # a flat list of ids is one action: the error says to wrap it (not "'int' object is not iterable")
    with pytest.raises(TypeError, match=r"each a list of 4 action token ids.*a flat list of ids is one action"):
        ActionPriorDrafter(history[0], layout)
    assert ActionPriorDrafter(np.array(history), layout).previous_actions == history  # an array of actions works


@pytest.mark.parametrize("bin_tolerance", [2, 30])
def test_relaxed_chunk_tokens_stay_within_r_bins_of_greedy_given_their_prefix(chunked, bin_tolerance):
    tokenizer = chunked.action_tokenizer
    kwargs = drafters(chunked)["prior+tree"]
    relaxed = 0
    for seed in range(6):
        image, state = observation(seed)
        chunked.previous_action_ids = [chunked.action_token_ids(np.random.default_rng(seed).uniform(-1, 1, 4)).tolist()]
        _, out = chunked.predict_action(image, "reach the goal", state, return_output=True,
                                        bin_tolerance=bin_tolerance, **kwargs)  # fmt: skip
        prompt = torch.tensor([chunked.prompt_ids("reach the goal", state)])
        with torch.no_grad():
            logits = chunked.model(input_ids=out.sequences, pixel_values=chunked.preprocess_images(image)).logits[0]
        for position in range(prompt.shape[1], out.sequences.shape[1]):  # every dimension of every chunk step
            token, greedy = int(out.sequences[0, position]), int(logits[position - 1].argmax())
            assert tokenizer.is_action_token(token) and abs(token - greedy) <= bin_tolerance
            relaxed += token != greedy
    assert relaxed > 0  # the bound was exercised, not only exact matches


def test_a_grown_policy_computes_its_sources_function():
    torch.manual_seed(0)
    source = action_only(VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**SMALL)))
    grown = VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**{**SMALL, "text_layers": 5}), seed=3)
    assert grow_from(grown, source) == {0: 0, 1: 2} == decoder_layer_map(2, 5)
    image, state = observation()
    pixel_values = source.preprocess_images(image)
    input_ids = torch.tensor([source.prompt_ids("reach the goal", state)])
    with torch.no_grad():
        torch.testing.assert_close(grown.model(input_ids=input_ids, pixel_values=pixel_values).logits,
                                   source.model(input_ids=input_ids, pixel_values=pixel_values).logits)  # fmt: skip
    with pytest.raises(ValueError, match="can only be grown"):
        decoder_layer_map(3, 2)
    wider = VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**{**SMALL, "text_hidden_size": 128}))
    with pytest.raises(ValueError, match="text_hidden_size=64.*128"):
        grow_from(wider, source)


def test_a_policy_grown_to_a_finer_image_computes_its_sources_function_on_the_upsampled_image():
    """64 px in 16 px patches -> 128 px in 32 px patches (here 32 -> 64): the same token grid; on an image upsampled
    by 2 (nearest), the grown policy computes its source's function."""
    torch.manual_seed(0)
    source = action_only(VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**SMALL)))
    finer_config = VLAPolicyConfig(**{**SMALL, "image_size": 64, "patch_size": 32, "text_layers": 3})
    finer = VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, finer_config)
    grow_from(finer, source)
    image, state = observation()
    upsampled = image.repeat(2, axis=0).repeat(2, axis=1)  # [64, 64, 3]
    input_ids = torch.tensor([source.prompt_ids("reach the goal", state)])
    with torch.no_grad():
        torch.testing.assert_close(
            finer.model(input_ids=input_ids, pixel_values=finer.preprocess_images(upsampled)).logits,
            source.model(input_ids=input_ids, pixel_values=source.preprocess_images(image)).logits,
            atol=2e-5,
            rtol=1e-4,
        )
    other_grid = VLAPolicy.build(INSTRUCTIONS, ACTIONS, STATES, VLAPolicyConfig(**{**SMALL, "image_size": 64}))
    with pytest.raises(ValueError, match="32 px images in 16 px patches, the new one 64 px in 16 px patches"):
        grow_from(other_grid, source)  # 16 image tokens, not 4: a finer image needs larger patches


def test_the_episode_benchmark_replays_a_chunked_policy_with_the_prior(chunked):
    """bench-episodes remembers whole calls; the prior reads them back as actions: r=0 never moves from greedy, and
    after the first call the prior drafts (fewer forwards than greedy's 8 per call on a repeated observation)."""
    from hf_specvla.benchmarks.speed import (
        EpisodeMethod,
        ForwardClock,
        format_episode_report,
        policy_actor,
        run_episode_benchmark,
    )

    image, state = observation()
    episode = [{"image": image, "instruction": "reach the goal", "state": state}] * 4
    methods = [EpisodeMethod("greedy"), EpisodeMethod("prior r=0", dict(bin_tolerance=0), action_prior=True)]
    results = run_episode_benchmark(policy_actor(chunked), [episode], methods, chunked.config.action_tokens,
                                    warmup=1, progress=False, clock=ForwardClock(chunked.model))  # fmt: skip
    greedy, prior = results
    assert prior.bin_distances and max(prior.bin_distances) == 0
    assert greedy.target_forwards == [8] * 4 and min(prior.target_forwards[1:]) < 8
    assert set(prior.split_seconds) == {"vision", "prefill", "later forwards", "drafting", "rest"}
    # acceptance by token position: greedy never drafts; the prior's accepted drafts are its tokens per forward - 1
    assert greedy.accepted_by_position == [0] * 8 and prior.accepted_by_position[-1] == 0
    assert sum(prior.accepted_by_position) == sum(prior.new_tokens) - sum(prior.target_forwards)
    assert "Accepted drafts by token position" in format_episode_report(results)
