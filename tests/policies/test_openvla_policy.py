"""An OpenVLA checkpoint as a policy: the batched ``predict_action`` (prompts of other lengths left-padded, images of
other sizes, each row's dataset) gives each row the port's one-robot action, greedy and speculative at r=0; the loader
tells the kinds of folder apart before loading weights; a checkpoint's own towers load in a fresh process."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from hf_specvla.policies import DecodingMethod, OpenVLAPolicy, VLAPolicy, load_policy
from hf_specvla.policies.loading import policy_kind, read_policy_layout
from tests.openvla.test_openvla import needs_hub_files
from tests.openvla.tiny_checkpoint import write_tiny_checkpoint

ROOT = Path(__file__).resolve().parents[2]
INSTRUCTIONS = ["pick up the red block", "open the drawer and put the cup inside it carefully", "push", "close it"]
KEYS = ["tiny_dataset", "other_dataset", "tiny_dataset", "other_dataset"]

pytestmark = needs_hub_files


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory) -> Path:
    return write_tiny_checkpoint(tmp_path_factory.mktemp("tiny-openvla"))


@pytest.fixture(scope="module")
def policy(checkpoint) -> OpenVLAPolicy:
    return OpenVLAPolicy.from_pretrained(checkpoint, unnorm_key="tiny_dataset")


def _images(count: int, seed: int = 0) -> list[np.ndarray]:
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 256, (side, side + 3, 3), dtype=np.uint8) for side in (28, 64, 224, 100)[:count]]


def _alone(policy: OpenVLAPolicy, image, instruction: str, key: str, **kwargs) -> np.ndarray:
    """The port's own one-robot call: what every row of a batch must equal."""
    return policy.model.predict_action(
        image=image, instruction=instruction, processor=policy.processor, unnorm_key=key, **kwargs
    )


@torch.no_grad()
def test_a_batch_gives_each_row_the_one_robot_action(policy):
    images = _images(4)
    expected = np.stack([_alone(policy, i, t, k) for i, t, k in zip(images, INSTRUCTIONS, KEYS)])
    prompts = [policy.prompt_ids(t) for t in INSTRUCTIONS]
    assert len({len(p) for p in prompts}) > 1, "the prompts are all as long: no row is padded"
    np.testing.assert_array_equal(policy.predict_action(images, INSTRUCTIONS, unnorm_key=KEYS), expected)
    # each row un-normalised with its own dataset's statistics: the same tokens under another key differ
    other = policy.predict_action(images, INSTRUCTIONS, unnorm_key="other_dataset")
    np.testing.assert_array_equal(other[1::2], expected[1::2])
    assert not np.array_equal(other[0::2], expected[0::2])
    np.testing.assert_array_equal(policy.predict_action(images[0], INSTRUCTIONS[0]), expected[0])  # the default key


@torch.no_grad()
@pytest.mark.parametrize("method", ["prior+jacobi", "jacobi"])
def test_speculative_batches_at_r0_equal_greedy_row_by_row(policy, method):
    """Three steps of an episode per row, each drafting from the row's previous actions (its own memory)."""
    plan = DecodingMethod.parse(method, action_dim=7).plan(None, "cpu", action_dim=7)
    memories: list[list[list[int]]] = [[] for _ in INSTRUCTIONS]
    forwards = []
    for step in range(3):
        images = _images(4, seed=step)
        expected = np.stack([_alone(policy, i, t, k) for i, t, k in zip(images, INSTRUCTIONS, KEYS)])
        actions, output = policy.predict_action(
            images, INSTRUCTIONS, unnorm_key=KEYS, previous_action_ids=memories, decoding=plan, return_output=True
        )
        np.testing.assert_array_equal(actions, expected, err_msg=f"{method} step {step}")
        assert all(len(m) == min(step + 1, policy.HISTORY_LENGTH) for m in memories)
        forwards.append(output.speculation.num_batch_forwards if hasattr(output, "speculation") else 7)
    assert forwards[-1] <= 7


def test_unnorm_keys_are_checked_naming_the_valid_ones(policy, checkpoint):
    assert policy.unnorm_keys == ("other_dataset", "tiny_dataset") and policy.default_unnorm_key == "tiny_dataset"
    with pytest.raises(ValueError, match=r"unnorm_key='bridge' is not in this checkpoint's norm_stats; valid keys: "):
        policy.predict_action(_images(1)[0], "push", unnorm_key="bridge")
    with pytest.raises(ValueError, match=r"a batch of 2 images needs 2 unnorm_key rows, got 3"):
        policy.predict_action(_images(2), ["push", "pull"], unnorm_key=KEYS[:3])
    no_default = OpenVLAPolicy(policy.model, policy.processor)  # two datasets, none chosen: each call names one
    with pytest.raises(ValueError, match=r"trained on 2 datasets .* pass unnorm_key, one of \['other_dataset', 'tiny"):
        no_default.predict_action(_images(1)[0], "push")
    with pytest.raises(ValueError, match=r"unnorm_key='bridge' is not in this checkpoint's norm_stats"):
        OpenVLAPolicy.from_pretrained(checkpoint, unnorm_key="bridge")  # before the weights load
    with pytest.raises(ValueError, match="OpenVLA reads no proprio state"):
        policy.predict_action(_images(1)[0], "push", np.zeros(4))


def test_the_loader_tells_the_kinds_apart_before_loading(checkpoint, tmp_path):
    assert policy_kind(checkpoint) == "openvla" and policy_kind(ROOT / "policies" / "mt10_vla3") == "vla"
    assert policy_kind("openvla/openvla-7b") == "openvla"  # a hub id (not fetched here)
    assert read_policy_layout(checkpoint).action_dim == 7
    assert read_policy_layout(ROOT / "policies" / "mt10_vla3").action_dim == 4
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "config.json").write_text(json.dumps({"model_type": "llama"}))
    with pytest.raises(FileNotFoundError, match=r"holds neither policy_config.json .* config.json says 'llama'"):
        load_policy(tmp_path / "other")
    with pytest.raises(FileNotFoundError, match="no such folder"):
        load_policy(tmp_path / "missing")
    with pytest.raises(ValueError, match="is a Meta-World policy with one set of action statistics"):
        load_policy(ROOT / "policies" / "mt10_vla3", unnorm_key="bridge_orig")
    assert isinstance(load_policy(checkpoint, "other_dataset"), OpenVLAPolicy)
    assert isinstance(load_policy(ROOT / "policies" / "mt10_vla3"), VLAPolicy)


def test_a_checkpoints_own_towers_load_in_a_fresh_process(checkpoint, policy):
    """The tiny towers are registered in this process only (by the tests); a fresh one builds them from the specs
    the folder's config.json carries, and gives the same action."""
    config = json.loads((checkpoint / "config.json").read_text())
    assert set(config["vision_towers"]) == set(config["timm_model_ids"])
    image = np.full((32, 32, 3), 7, dtype=np.uint8)
    expected = policy.predict_action(image, "push the block")
    script = (
        "import sys, numpy as np\n"
        "from hf_specvla.openvla import VISION_TOWERS\n"
        "from hf_specvla.policies import load_policy\n"
        "assert not any(name.startswith('test-tiny') for name in VISION_TOWERS)\n"
        "policy = load_policy(sys.argv[1], 'tiny_dataset')\n"
        "print(repr(policy.predict_action(np.full((32, 32, 3), 7, dtype=np.uint8), 'push the block').tolist()))\n"
    )
    done = subprocess.run([sys.executable, "-c", script, str(checkpoint)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    np.testing.assert_array_equal(np.array(eval(done.stdout.strip().splitlines()[-1])), expected)


def test_vision_tower_specs_in_a_config_are_checked_naming_the_field():
    from hf_specvla.openvla import OpenVLAConfig

    towers = {"my-vit": {"embed_dim": 32, "depth": 2, "num_heads": 2, "mlp_hidden_size": 64, "patch_size": 14}}
    config = OpenVLAConfig(
        timm_model_ids=["my-vit"],
        image_sizes=[28],
        vision_backbone_id="custom",
        use_fused_vision_backbone=False,
        arch_specifier="no-align+gelu-mlp",
        vision_towers=towers,
    )
    assert config.tower_specs()["my-vit"].embed_dim == 32
    assert OpenVLAConfig.from_dict(config.to_dict()).vision_towers == config.vision_towers  # round trip
    for bad, message in (
        ({"my-vit": {**towers["my-vit"], "width": 3}}, r"vision_towers\['my-vit'\] has fields \['width'\]"),
        ({"my-vit": {"embed_dim": 32}}, r"vision_towers\['my-vit'\] needs \['depth', 'num_heads'"),
        ({"my-vit": {**towers["my-vit"], "depth": 0}}, r"vision_towers\['my-vit'\].depth must be an int >= 1, got 0"),
        ({"my-vit": {**towers["my-vit"], "class_token": 1}}, r"class_token must be true or false, got 1"),
    ):
        with pytest.raises(ValueError, match=message):
            OpenVLAConfig(
                timm_model_ids=["my-vit"],
                image_sizes=[28],
                vision_backbone_id="custom",
                use_fused_vision_backbone=False,
                arch_specifier="no-align+gelu-mlp",
                vision_towers=bad,
            )
    with pytest.raises(ValueError, match=r"vision tower 'my-vit' is not supported .* config.json's vision_towers"):
        OpenVLAConfig(
            timm_model_ids=["my-vit"],
            image_sizes=[28],
            vision_backbone_id="custom",
            use_fused_vision_backbone=False,
            arch_specifier="no-align+gelu-mlp",
        )
