"""ActionTokenizer / ActionNormalizer against values computed by hand from OpenVLA's action_tokenizer.py."""

import numpy as np
import pytest
import torch

from hf_specvla import ActionNormalizer, ActionTokenizer


@pytest.fixture
def openvla():
    return ActionTokenizer(32000)


def test_layout_matches_openvla(openvla):
    # bins = linspace(-1, 1, 256); action ids are 32000 - digitize(a) = 31744..31999
    assert openvla.action_token_begin == 31744
    assert list(openvla.action_token_ids)[:2] == [31744, 31745] and openvla.action_token_ids[-1] == 31999
    assert len(openvla.bin_centers) == 255
    assert openvla.is_action_token(31743) == False  # noqa: E712 - last text id
    assert openvla.is_action_token(31744) and openvla.is_action_token(31999)
    assert openvla.is_action_token(32000) == False  # noqa: E712 - padded logit, never an action


def test_encode_hand_computed(openvla):
    # 1.0 -> digitize = 256 -> 31744; -1.0 -> 1 -> 31999; 0.0 sits between bins[127] and bins[128] -> 128 -> 31872
    assert openvla.encode([1.0, -1.0, 0.0]).tolist() == [31744, 31999, 31872]
    # values beyond [-1, 1] are clipped first
    assert openvla.encode([7.0, -3.0]).tolist() == [31744, 31999]
    # a higher value never gets a higher id
    ids = openvla.encode(np.linspace(-1, 1, 1000))
    assert np.all(np.diff(ids) <= 0)


def test_decode_hand_computed(openvla):
    # 31872: d = 128 -> centers[127] = (bins[127] + bins[128]) / 2 = 0
    # 31999: d = 1 -> centers[0] = -1 + 1/255; 31744: d = 256 -> index clipped to 254 -> 1 - 1/255
    decoded = openvla.decode(np.array([31872, 31999, 31744]))
    np.testing.assert_allclose(decoded, [0.0, -1 + 1 / 255, 1 - 1 / 255], atol=1e-12)
    # torch input works and round trip stays within one bin width
    actions = np.random.default_rng(0).uniform(-1, 1, 100)
    back = openvla.decode(torch.as_tensor(openvla.encode(actions)))
    assert np.max(np.abs(back - actions)) <= 2 / 255 + 1e-9


def test_bins_and_distances(openvla):
    assert openvla.token_to_bin(31999) == 0 and openvla.token_to_bin(31744) == 255
    assert openvla.bin_distance(31750, 31747) == 3
    assert openvla.bin_distance(torch.tensor([31750, 31744]), torch.tensor([31747, 31744])).tolist() == [3, 0]


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(vocab_size=100, n_bins=256), "larger than n_bins"),
        (dict(vocab_size=1000, n_bins=1), "n_bins"),
        (dict(vocab_size=1000.0), "vocab_size"),
    ],
)
def test_bad_layout(kwargs, match):
    with pytest.raises((ValueError, TypeError), match=match):
        ActionTokenizer(**kwargs)


def test_normalizer_bounds_q99():
    norm = ActionNormalizer(q01=[0.0, -2.0], q99=[10.0, 2.0], mask=[True, False])
    # 2 (5 - 0) / 10 - 1 = 0; the unmasked dim passes through
    np.testing.assert_allclose(norm.normalize([5.0, 1.5]), [0.0, 1.5], atol=1e-6)
    np.testing.assert_allclose(norm.normalize([20.0, 0.0]), [1.0, 0.0])  # clipped
    np.testing.assert_allclose(norm.unnormalize(norm.normalize([2.5, -1.0])), [2.5, -1.0], atol=1e-6)
    assert ActionNormalizer.from_dict(norm.to_dict()).to_dict() == norm.to_dict()
    with pytest.raises(ValueError, match="dimensions"):
        norm.normalize([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="q99 must be >= q01"):
        ActionNormalizer(q01=[1.0], q99=[0.0])
