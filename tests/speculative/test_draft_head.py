"""DraftHead / DraftHeadConfig: building for a target, compatibility checks, save/load round trips."""

import pytest
import torch
from transformers import AutoConfig, AutoModel, LlamaForCausalLM

from hf_specvla import ActionTokenizer, DraftHead, DraftHeadConfig

from ..conftest import VOCAB, tiny_llama_config


def test_from_target_records_what_it_was_built_for(tiny_llava, action_tokenizer):
    head = DraftHead.from_target(tiny_llava, action_tokenizer, action_dim=7, num_draft_tokens=4)
    config = head.config
    assert config.hidden_size == 64 and config.vocab_size == VOCAB
    assert (config.action_vocab_size, config.n_action_bins, config.action_dim) == (VOCAB, 256, 7)
    assert config.target_model_type == "llava" and config.num_draft_tokens == 4
    assert config.action_tokenizer() == action_tokenizer


def test_save_load_round_trip(tmp_path, tiny_llama, random_draft):
    random_draft.save_pretrained(tmp_path)
    state_keys = set(random_draft.state_dict())
    assert not any("lm_head" in k or "embed" in k for k in state_keys)  # the target's modules are not stored
    assert (tmp_path / "model.safetensors").exists()
    loaded = DraftHead.from_pretrained(tmp_path)
    auto_loaded = AutoModel.from_pretrained(tmp_path)
    assert isinstance(auto_loaded, DraftHead) and isinstance(AutoConfig.from_pretrained(tmp_path), DraftHeadConfig)

    def settings(model):
        return {k: v for k, v in model.config.to_dict().items() if k != "_name_or_path"}

    assert settings(loaded) == settings(random_draft)
    torch.manual_seed(0)
    embeds, hidden = torch.randn(1, 5, 64), torch.randn(1, 5, 64)
    positions = torch.arange(5)[None]
    with torch.no_grad():
        expected = random_draft(embeds, hidden, positions)
        for model in (loaded, auto_loaded):
            torch.testing.assert_close(model(embeds, hidden, positions), expected, rtol=0, atol=0)


def test_mismatched_target_is_rejected(random_draft):
    other = LlamaForCausalLM(tiny_llama_config(hidden_size=32, num_attention_heads=2, num_key_value_heads=1))
    with pytest.raises(ValueError, match="hidden_size: draft 64, target 32"):
        random_draft.target_handles(other)
    wider_vocab = LlamaForCausalLM(tiny_llama_config(vocab_size=400))
    with pytest.raises(ValueError, match="lm_head vocabulary: draft 320, target 400"):
        random_draft.target_handles(wider_vocab)


@pytest.mark.parametrize(
    "overrides, match",
    [
        (dict(action_vocab_size=500, vocab_size=320), "exceeds vocab_size"),
        (dict(num_draft_tokens=0), "num_draft_tokens"),
        (dict(hidden_size=-4), "hidden_size"),
        (dict(action_vocab_size=100, n_action_bins=256), "larger than n_bins"),
    ],
)
def test_config_validation(overrides, match):
    with pytest.raises(ValueError, match=match):
        DraftHeadConfig(**overrides)


def test_action_only_scorer_drafts_only_actions_and_eos(tiny_llama):
    head = DraftHead.from_target(tiny_llama, ActionTokenizer(VOCAB), draft_action_tokens_only=True)
    scorer = head.scorer(tiny_llama.get_output_embeddings(), eos_token_ids=[2])
    assert scorer.weight.shape == (257, 64)
    ids = scorer.token_ids(torch.randn(50, 64))
    assert bool(((ids >= 64) | (ids == 2)).all())


@pytest.mark.parametrize("kind", ["missing relative", "missing absolute", "not a draft head", "no config"])
def test_from_pretrained_checks_a_local_folder_and_never_asks_the_hub(tmp_path, monkeypatch, tiny_llama, kind):
    """Regression (reliability issue, case 4): a wrong local path fails at once, naming the path and what is wrong;
    a path like the --help example ``runs/draft`` is local (its first component is a local folder)."""
    monkeypatch.chdir(tmp_path)
    (tmp_path / "runs").mkdir()
    tiny_llama.save_pretrained(tmp_path / "runs" / "target")  # a model folder, but not a draft head
    (tmp_path / "runs" / "empty").mkdir()
    path, error, match = {
        "missing relative": ("runs/draft", FileNotFoundError, "'runs/draft' does not exist .*not looked up on the hub"),
        "missing absolute": (str(tmp_path / "nowhere"), FileNotFoundError, "does not exist"),
        "not a draft head": ("runs/target", ValueError, "'runs/target' holds a 'llama' model, not a hf_specvla draft"),
        "no config": ("runs/empty", FileNotFoundError, "'runs/empty' has no config.json"),
    }[kind]
    with pytest.raises(error, match=match):
        DraftHead.from_pretrained(path)


def test_a_hf_specvla_assistant_on_a_target_without_speculation_says_how_to_enable_it(random_draft):
    """Regression (reliability issue, case 10): transformers' assisted generation probes the assistant; the error
    says to call enable_speculation instead of a bare AttributeError."""
    from hf_specvla import DraftHeadDrafter

    plain = LlamaForCausalLM(tiny_llama_config()).eval()
    for assistant in (random_draft, DraftHeadDrafter(random_draft)):
        with pytest.raises(AttributeError, match="enable_speculation"):
            plain.generate(input_ids=torch.tensor([[1, 5, 6]]), max_new_tokens=2, assistant_model=assistant)


def test_a_truncated_weights_file_and_a_missing_folder_are_named(tmp_path, random_draft, monkeypatch):
    folder = tmp_path / "head"
    random_draft.save_pretrained(folder)
    (folder / "model.safetensors").write_bytes(b"")  # an interrupted save
    with pytest.raises(OSError, match=r"could not read the draft head's weights '.*model.safetensors' \(0 bytes\).*"
                                      r"damaged or truncated"):  # fmt: skip
        DraftHead.from_pretrained(folder)
    # a path that reads as a hub id (no local folder 'runs' here): the error says that no such folder exists
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    with pytest.raises(OSError, match=r"no local folder 'runs/no-such-head' exists, so it was taken for a hub repo id, "
                                      r"and the hub could not provide it"):  # fmt: skip
        DraftHead.from_pretrained("runs/no-such-head")
