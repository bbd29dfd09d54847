"""The OpenVLA-style policy: loss, predict_action, save/load, bad input, and speculative decoding on it."""

import json

import numpy as np
import pytest
import torch
from transformers import GenerationConfig

from hf_specvla import ActionNormalizer, DraftHead
from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

INSTRUCTIONS = ["reach the goal", "push the puck to the goal"]
SMALL = dict(
    image_size=32,
    patch_size=16,
    vision_hidden_size=32,
    vision_layers=1,
    text_hidden_size=64,
    text_layers=2,
    text_heads=4,
)


@pytest.fixture(scope="module")
def policy():
    actions = ActionNormalizer(q01=[-1.0, -0.5, -1.0, -1.0], q99=[1.0, 0.5, 0.2, 1.0], mask=[True, True, True, False])
    states = ActionNormalizer(q01=[-0.1, 0.5, 0.05, 0.0], q99=[0.1, 0.9, 0.3, 1.0])
    return VLAPolicy.build(INSTRUCTIONS, actions, states, VLAPolicyConfig(**SMALL))


def observation(seed=0):
    rng = np.random.default_rng(seed)
    return rng.integers(0, 256, (32, 32, 3), dtype=np.uint8), rng.uniform([-0.1, 0.5, 0.05, 0], [0.1, 0.9, 0.3, 1])


def test_prompt_layout(policy):
    image, state = observation()
    ids = policy.prompt_ids("Reach the goal.", state)
    tokens = policy.tokenizer.convert_ids_to_tokens(ids)
    assert tokens[0] == "<s>" and tokens[1:5] == ["<image>"] * 4  # (32 / 16) ** 2 image tokens
    assert tokens[-2:] == ["out", ":"] and tokens[-8:-6] == ["state", ":"]
    assert all(policy.action_tokenizer.is_action_token(i) for i in ids[-6:-2])  # the state, as bin tokens


def test_forward_loss_only_on_action_tokens(policy):
    image, state = observation()
    batch = policy.training_batch(image[None].repeat(2, 0), [state, state], [[0.1, 0.2, -0.3, 1.0]] * 2, INSTRUCTIONS)
    assert int((batch["labels"] != -100).sum()) == 2 * 4
    loss = policy.model(**batch).loss
    assert torch.isfinite(loss) and loss.item() > 0


def test_action_loss_is_the_models_loss_and_scene_targets_follow_the_actions(policy):
    """``target_losses`` on a plain policy is transformers' own loss; a policy with scene targets learns
    ``scene_state_dim`` more tokens after the action tokens, and still acts with the action tokens only."""
    from hf_specvla.training.behaviour_cloning import target_losses

    image, state = observation()
    actions = [[0.1, 0.2, -0.3, 1.0], [-0.5, 0.0, 0.1, -1.0]]
    batch = policy.training_batch(image[None].repeat(2, 0), [state, state], actions, INSTRUCTIONS)
    out = policy.model(**batch)
    losses = target_losses(out.logits, batch["labels"], action_dim=4)
    torch.testing.assert_close(losses["action_loss"], out.loss)
    assert int(losses["action_count"]) == 8 and "scene_loss" not in losses

    scene_norm = ActionNormalizer(q01=[-0.2, 0.4, 0.0] * 2, q99=[0.2, 0.9, 0.3] * 2)
    normalizers = (policy.action_normalizer, policy.state_normalizer)
    scene_policy = VLAPolicy.build(INSTRUCTIONS, *normalizers, VLAPolicyConfig(**SMALL, scene_state_dim=6),
                                   scene_normalizer=scene_norm)  # fmt: skip
    scene_states = [[0.0, 0.6, 0.02, 0.1, 0.8, 0.2], [0.1, 0.7, 0.02, -0.1, 0.8, 0.1]]
    batch = scene_policy.training_batch(image[None].repeat(2, 0), [state, state], actions, INSTRUCTIONS, scene_states)
    labelled = batch["labels"] != -100
    assert int(labelled.sum()) == 2 * (4 + 6)
    # the first 4 labelled tokens of a row are its action tokens, the next 6 the scene state's
    np.testing.assert_array_equal(batch["labels"][0][labelled[0]][:4].numpy(), policy.action_token_ids(actions[0]))
    scene_ids = scene_policy.action_tokenizer.encode(scene_norm.normalize(np.asarray(scene_states[0])))
    np.testing.assert_array_equal(batch["labels"][0][labelled[0]][4:].numpy(), scene_ids)
    losses = target_losses(scene_policy.model(**batch).logits, batch["labels"], action_dim=4)
    assert int(losses["action_count"]) == 8 and torch.isfinite(losses["scene_loss"])
    _, output = scene_policy.predict_action(image, "reach the goal", state, return_output=True)
    assert output.sequences.shape[1] == len(scene_policy.prompt_ids("reach the goal", state)) + 4
    with pytest.raises(ValueError, match="pass scene_states"):
        scene_policy.training_batch(image[None], [state], actions[:1], INSTRUCTIONS[:1])
    with pytest.raises(ValueError, match="scene_state_dim=6 needs scene-state statistics.*got 0"):
        VLAPolicy.build(INSTRUCTIONS, *normalizers, VLAPolicyConfig(**SMALL, scene_state_dim=6))


def test_predict_action_shape_and_range(policy):
    image, state = observation()
    action = policy.predict_action(image, "reach the goal", state)
    norm = policy.action_normalizer
    assert action.shape == (4,)
    assert np.all(action[:3] >= norm.q01[:3] - 1e-6) and np.all(action[:3] <= norm.q99[:3] + 1e-6)
    assert -1.0 <= action[3] <= 1.0


def test_save_load_gives_identical_actions(policy, tmp_path):
    policy.save_pretrained(tmp_path)
    loaded = VLAPolicy.from_pretrained(tmp_path)
    for seed in range(3):
        image, state = observation(seed)
        np.testing.assert_array_equal(
            loaded.predict_action(image, "push the puck to the goal", state),
            policy.predict_action(image, "push the puck to the goal", state),
        )
    assert loaded.config == policy.config


def test_speculative_decoding_on_the_policy_is_lossless(policy):
    draft = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=4, num_draft_tokens=3).eval()
    for seed in range(5):
        image, state = observation(seed)
        plain = policy.predict_action(image, "reach the goal", state)
        spec, out = policy.predict_action(image, "reach the goal", state, return_output=True, assistant_model=draft)
        np.testing.assert_array_equal(plain, spec)
        assert out.speculation.num_new_tokens == 4


def test_a_generation_config_that_samples_is_honoured_and_do_sample_false_still_wins(policy):
    """Issue 64: predict_action's greedy default (do_sample=False) overrode a caller's
    ``generation_config=GenerationConfig(do_sample=True)``, which silently returned greedy's action."""
    sampling = GenerationConfig(do_sample=True, temperature=1.0, top_k=None)
    sampled_differently = 0
    for seed in range(3):
        image, state = observation(seed)
        policy.reset()
        _, greedy = policy.predict_action(image, "reach the goal", state, return_output=True)
        draws = []
        for _ in range(2):  # the same seed, the same draw: sampling is honoured, and reproducible
            torch.manual_seed(seed)
            policy.reset()
            _, out = policy.predict_action(image, "reach the goal", state, return_output=True,
                                           generation_config=sampling)  # fmt: skip
            draws.append(out.sequences[0, -4:].tolist())
        assert draws[0] == draws[1]
        sampled_differently += draws[0] != greedy.sequences[0, -4:].tolist()  # an untrained model: nearly uniform
        # an explicit do_sample=False beside the config decodes greedily
        policy.reset()
        _, out = policy.predict_action(image, "reach the goal", state, return_output=True, generation_config=sampling,
                                       do_sample=False)  # fmt: skip
        assert out.sequences[0, -4:].tolist() == greedy.sequences[0, -4:].tolist()
    assert sampled_differently == 3
    assert sampling.max_new_tokens is None and sampling.do_sample  # the caller's config is left as it was
    with pytest.raises(TypeError, match="generation_config must be a transformers GenerationConfig, got dict"):
        policy.predict_action(image, "reach the goal", state, generation_config={"do_sample": True})
    # the action's length is the policy's: a length given beside it is refused, not obeyed into a wrong action
    with pytest.raises(ValueError, match="decodes the policy's 4 action tokens: drop max_new_tokens=2"):
        policy.predict_action(image, "reach the goal", state, max_new_tokens=2)
    # a generation_config that does not sample is greedy decoding
    image, state = observation(0)
    np.testing.assert_array_equal(
        policy.predict_action(image, "reach the goal", state, generation_config=GenerationConfig(do_sample=False)),
        policy.predict_action(image, "reach the goal", state),
    )
    policy.reset()


def test_action_prior_remembers_the_episode_and_is_lossless(policy):
    """predict_action keeps the episode's actions (cleared by reset) and, with action_prior=True, drafts the next
    one from them inside the prefill: identical actions at r=0, one target forward when the draft is right."""
    draft = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=4, num_draft_tokens=2).eval()
    policy.reset()
    assert policy.previous_action_ids == []
    one_forward = 0
    for seed in range(4):
        image, state = observation(seed)
        plain, out = policy.predict_action(image, "reach the goal", state, return_output=True)
        greedy_ids = out.sequences[0, -4:].tolist()
        if not all(policy.action_tokenizer.is_action_token(t) for t in greedy_ids):
            assert policy.previous_action_ids == []  # text ids never become drafts
            continue
        assert policy.previous_action_ids[-1] == greedy_ids
        # the same observation again: the previous action is exactly right
        for kwargs in ({}, {"assistant_model": draft}):
            again, out = policy.predict_action(
                image, "reach the goal", state, return_output=True, action_prior=True, **kwargs
            )
            np.testing.assert_array_equal(plain, again)
            assert out.speculation.num_target_forwards == 1 and out.speculation.accepted_by_drafter["prior"] == 3
            one_forward += 1
        # another observation: whatever the prior drafts, r=0 gives greedy's action
        other_image, other_state = observation(seed + 10)
        expected = policy.predict_action(other_image, "reach the goal", other_state)
        policy.previous_action_ids = [greedy_ids]
        np.testing.assert_array_equal(
            expected, policy.predict_action(other_image, "reach the goal", other_state, action_prior=True)
        )
    assert one_forward > 0
    assert len(policy.previous_action_ids) <= VLAPolicy.HISTORY_LENGTH
    policy.reset()
    assert policy.previous_action_ids == []
    # the first step of an episode has nothing to draft from: plain greedy, bin_tolerance is harmless there
    image, state = observation(0)
    np.testing.assert_array_equal(
        policy.predict_action(image, "reach the goal", state, action_prior=True, bin_tolerance=2),
        policy.predict_action(image, "reach the goal", state),
    )


def test_bad_inputs(policy, tmp_path):
    image, state = observation()
    with pytest.raises(ValueError, match=r"shape \[32, 32, 3\]"):
        policy.predict_action(np.zeros((48, 48, 3), np.uint8), "reach the goal", state)
    with pytest.raises(TypeError, match="uint8"):
        policy.predict_action(image.astype(np.float32), "reach the goal", state)
    with pytest.raises(ValueError, match="state=\\[x, y, z, gripper\\]"):
        policy.predict_action(image, "reach the goal")
    with pytest.raises(ValueError, match="4 numbers"):
        policy.predict_action(image, "reach the goal", [0.0, 1.0])
    with pytest.raises(
        ValueError, match=r"state must hold finite numbers, got \[0.1, nan, 0.3, inf\].*dimension\(s\) \[1, 3\]"
    ):
        policy.predict_action(image, "reach the goal", [0.1, np.nan, 0.3, np.inf])
    with pytest.raises(FileNotFoundError, match="does not exist"):
        VLAPolicy.from_pretrained(tmp_path / "nowhere")
    with pytest.raises(FileNotFoundError, match="policy_config.json"):
        VLAPolicy.from_pretrained(tmp_path)
    with pytest.raises(ValueError, match="camera must be a camera name .*got ''"):
        VLAPolicyConfig(camera="")
    # a policy names its camera and knows no simulator: the simulator checks the name when it renders
    from hf_specvla.metaworld.env import EnvConfig

    with pytest.raises(ValueError, match="camera must be one of .*'workspace'.*got 'ceiling'"):
        EnvConfig(camera=VLAPolicyConfig(camera="ceiling").camera)
    with pytest.raises(ValueError, match="vision_hidden_size must be a positive multiple of 4.*got 130"):
        VLAPolicyConfig(vision_hidden_size=130)


def test_dataset_with_other_action_dim_is_refused(policy, tmp_path):
    from hf_specvla.metaworld.demonstrations import Demonstrations
    from hf_specvla.training.behaviour_cloning import VLATrainingConfig, train_vla

    demos = Demonstrations(
        np.zeros((4, 32, 32, 3), np.uint8), np.zeros((4, 4), np.float32), np.zeros((4, 7), np.float32),
        ["reach-v3"] * 4, np.zeros(4, np.int64),
    )  # fmt: skip
    with pytest.raises(ValueError, match="7-dim actions, the policy action_dim=4"):
        train_vla(policy, demos, VLATrainingConfig(str(tmp_path / "out"), max_steps=1))
    scene_norm = ActionNormalizer(q01=[-1.0] * 6, q99=[1.0] * 6)
    config = VLAPolicyConfig(**SMALL, scene_state_dim=6)
    scene_policy = VLAPolicy.build(INSTRUCTIONS, policy.action_normalizer, policy.state_normalizer, config,
                                   scene_normalizer=scene_norm)  # fmt: skip
    demos.actions = np.zeros((4, 4), np.float32)  # no scene states: collected before the column existed
    with pytest.raises(ValueError, match="scene_state_dim=6 scene targets but the demonstrations have no"):
        train_vla(scene_policy, demos, VLATrainingConfig(str(tmp_path / "out"), max_steps=1))


def test_freeze_vision_trains_everything_but_the_vision_tower(tmp_path):
    from hf_specvla.metaworld.demonstrations import Demonstrations
    from hf_specvla.training.behaviour_cloning import VLATrainingConfig, train_vla

    actions = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4)
    policy = VLAPolicy.build(INSTRUCTIONS, actions, actions, VLAPolicyConfig(**SMALL))
    rng = np.random.default_rng(0)
    demos = Demonstrations(
        rng.integers(0, 255, (8, 32, 32, 3), dtype=np.uint8), rng.uniform(-1, 1, (8, 4)).astype(np.float32),
        rng.uniform(-1, 1, (8, 4)).astype(np.float32), ["reach-v3"] * 8, np.repeat(np.arange(2), 4),
    )  # fmt: skip
    before = {name: p.detach().clone() for name, p in policy.model.named_parameters()}
    config = VLATrainingConfig(str(tmp_path / "out"), max_steps=2, batch_size=4, val_episodes=0, warmup_steps=0,
                               eval_every=0, save_every=0, freeze_vision=True)  # fmt: skip
    train_vla(policy, demos, config, progress=False)
    moved = {name for name, p in policy.model.named_parameters() if not torch.equal(p, before[name])}
    tower = {name for name in before if ".vision_tower." in f".{name}"}
    assert tower and not moved & tower
    assert any("language_model" in name for name in moved) and any("projector" in name for name in moved)
    record = json.loads((tmp_path / "out" / "run.json").read_text())
    assert record["settings"]["freeze_vision"] is True  # the folder records it


def test_scene_readout_reads_where_the_first_action_token_is_decoded(policy):
    """The readout sees the prompt only: the actions after it (teacher-forced) cannot move it, the image does; it
    reads the position whose logits decode the first action token."""
    from hf_specvla.training.behaviour_cloning import PolicyWithSceneReadout, _forward

    scene_norm = ActionNormalizer(q01=[-1.0] * 6, q99=[1.0] * 6)
    config = VLAPolicyConfig(**SMALL, scene_state_dim=6)
    scene_policy = VLAPolicy.build(INSTRUCTIONS, policy.action_normalizer, policy.state_normalizer, config,
                                   scene_normalizer=scene_norm)  # fmt: skip
    model = PolicyWithSceneReadout(scene_policy.model, 6).eval()
    image, state = observation()
    scenes = np.full((2, 6), 0.25)
    seen = []
    for actions, picture in [([[0.1, 0.2, -0.3, 1.0]] * 2, image), ([[-0.9, 0.4, 0.2, -1.0]] * 2, image),
                             ([[0.1, 0.2, -0.3, 1.0]] * 2, 255 - image)]:  # fmt: skip
        with torch.no_grad():
            losses = _forward(scene_policy, model, picture[None].repeat(2, 0), [state, state], actions,
                              INSTRUCTIONS, scenes, readout=True)  # fmt: skip
        seen.append(losses["scene_readout_loss"].item())
        assert losses["scene_readout_object_m"] > 0 and losses["action_count"] == 8
    assert seen[0] == seen[1] and seen[0] != seen[2]
    batch = scene_policy.training_batch(image[None], [state], [[0.1, 0.2, -0.3, 1.0]], INSTRUCTIONS[:1], scenes[:1])
    position = len(scene_policy.prompt_ids(INSTRUCTIONS[0], state)) - 1
    assert int((batch["labels"][0] != -100).int().argmax()) - 1 == position  # the readout's position
    from hf_specvla.metaworld.demonstrations import Demonstrations
    from hf_specvla.training.behaviour_cloning import VLATrainingConfig, train_vla

    demos = Demonstrations(np.zeros((4, 32, 32, 3), np.uint8), np.zeros((4, 4), np.float32),
                           np.zeros((4, 4), np.float32), ["reach-v3"] * 4, np.zeros(4, np.int64))  # fmt: skip
    with pytest.raises(ValueError, match="scene_readout_weight=1.0 reads the scene state.*--scene-targets"):
        train_vla(policy, demos, VLATrainingConfig("unused", max_steps=1, scene_readout_weight=1.0))


# ----------------------------------------------------------------------------- a batch of observations
def batch_of_observations(n):
    images, states = zip(*(observation(seed) for seed in range(n)))
    instructions = [INSTRUCTIONS[i % 2] for i in range(n)]  # two prompt lengths: the batch is left-padded
    return np.stack(images), instructions, np.stack(states)


def test_a_batch_gives_each_row_its_own_action(policy):
    images, instructions, states = batch_of_observations(5)
    expected = np.stack([policy.predict_action(i, t, s) for i, t, s in zip(images, instructions, states)])
    np.testing.assert_array_equal(policy.predict_action(images, instructions, states), expected)
    draft = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=4, num_draft_tokens=3).eval()
    actions, out = policy.predict_action(images, instructions, states, return_output=True, assistant_model=draft)
    np.testing.assert_array_equal(actions, expected)
    assert len(out.speculation.rows) == 5 and all(row.num_new_tokens == 4 for row in out.speculation.rows)


def test_a_batch_with_per_row_action_priors_is_lossless_and_keeps_each_rows_memory(policy):
    images, instructions, states = batch_of_observations(4)
    memories = [[] for _ in range(4)]
    first = policy.predict_action(images, instructions, states, previous_action_ids=memories, action_prior=True)
    if not all(memories):
        pytest.skip("the untrained policy emitted text ids for some row: no memory to draft from")
    assert [m[-1] for m in memories] == policy.action_token_ids(first).tolist()
    memories[1] = [[int(t) + 5 for t in memories[1][-1]]]  # row 1's memory is wrong, the others right
    for kwargs in ({}, {"assistant_model": DraftHead.from_target(policy.model, policy.action_tokenizer, 4).eval()}):
        again, out = policy.predict_action(
            images, instructions, states, previous_action_ids=[list(m) for m in memories], action_prior=True,
            return_output=True, **kwargs,
        )  # fmt: skip
        np.testing.assert_array_equal(again, first)
        forwards = [row.num_target_forwards for row in out.speculation.rows]
        assert forwards[0] == forwards[2] == forwards[3] == 1 and forwards[1] > 1  # right memories: one forward


def test_a_truncated_weights_file_is_named(policy, tmp_path):
    policy.save_pretrained(tmp_path / "policy")
    weights = tmp_path / "policy" / "model.safetensors"
    weights.write_bytes(weights.read_bytes()[:100])
    with pytest.raises(OSError, match=r"could not read the policy's weights '.*model.safetensors' \(100 bytes\)"):
        VLAPolicy.from_pretrained(tmp_path / "policy")


def test_bad_batches(policy):
    images, instructions, states = batch_of_observations(3)
    with pytest.raises(ValueError, match="a batch of 3 images needs 3 instruction rows, got 2"):
        policy.predict_action(images, instructions[:2], states)
    with pytest.raises(ValueError, match="a batch of 3 images needs 3 state rows, got 1"):
        policy.predict_action(images, instructions, states[:1])
    with pytest.raises(ValueError, match="needs 3 previous_action_ids rows, got 2"):
        policy.predict_action(images, instructions, states, previous_action_ids=[[], []])
    with pytest.raises(ValueError, match=r"\[B, 32, 32, 3\]\), got \(3, 16, 16, 3\)"):
        policy.predict_action(images[:, :16, :16], instructions, states)
    with pytest.raises(ValueError, match="previous_action_ids is for a batch"):
        policy.predict_action(images[0], instructions[0], states[0], previous_action_ids=[[]])


@pytest.mark.parametrize("method", ["exact", "prior+jacobi:r=2", "none:compile", "greedy"])
def test_a_decoding_plan_decodes_as_its_loose_options_and_the_session_as_generate(policy, method):
    """``predict_action(decoding=plan)`` (a method made concrete, typed) decodes what the same method as loose
    options does, and the policy's decoder session (its default for speculative calls) what ``model.generate`` does,
    call after call of one episode; a plan beside loose options that say the same is refused, naming them."""
    from hf_specvla.policies.decoding_methods import DecodingMethod

    decoding = DecodingMethod.parse(method, action_dim=4)
    plan = decoding.plan(None, action_dim=4)
    loose = decoding.generate_kwargs(None, action_dim=4)
    runs = {}
    for name, sessions, options in (("plan", True, {"decoding": plan}), ("loose", True, loose),
                                    ("generate", False, {"decoding": plan})):  # fmt: skip
        policy.reset()
        policy.decoder_sessions = sessions
        runs[name] = []
        for seed in range(4):
            image, state = observation(seed % 2)  # the same observations again: the prior's drafts are right
            action, out = policy.predict_action(image, "reach the goal", state, return_output=True, **options)
            forwards = getattr(out, "speculation", None)
            runs[name].append((action.tolist(), None if forwards is None else forwards.num_target_forwards))
    policy.decoder_sessions = True
    assert runs["plan"] == runs["loose"] == runs["generate"]
    if plan.speculates:
        from hf_specvla.speculative import SpeculativeDecoder

        assert any(session.direct_calls for session in SpeculativeDecoder.of(policy.model).sessions.values())
        with pytest.raises(ValueError, match=r"decoding=DecodingPlan\(\.\.\.\) and bin_tolerance, action_prior"):
            policy.predict_action(*observation(0)[:1], "reach the goal", observation(0)[1], decoding=plan,
                                  action_prior=True, bin_tolerance=1)  # fmt: skip
    with pytest.raises(TypeError, match=r"predict_action got decoding=dict: decoding= takes a DecodingPlan"):
        policy.predict_action(*observation(0)[:1], "reach the goal", observation(0)[1], decoding=loose)
