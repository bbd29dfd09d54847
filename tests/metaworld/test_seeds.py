"""Seed ranges are defined once and never overlap: no evaluated seed was collected, trained or distilled on."""

from hf_specvla.metaworld import seeds


def test_seed_ranges_are_ordered_and_distinct():
    starts = list(seeds.SEED_RANGES.values())
    assert starts == sorted(starts) and len(set(starts)) == len(starts)
    assert list(seeds.SEED_RANGES) == ["collect", "eval", "fidelity", "bench", "draft"]


def test_every_consumer_takes_its_range_from_the_one_definition():
    from hf_specvla.metaworld import comparison, evaluation
    from hf_specvla.training import policy_draft

    assert evaluation.EVAL_SEED_START is seeds.EVAL_SEED_START
    assert comparison.CompareConfig().seed_start == seeds.EVAL_SEED_START
    assert policy_draft.DraftDataConfig().rollout_seed_start == seeds.DRAFT_SEED_START


def test_cli_defaults_are_the_ranges(capsys):
    import pytest

    from hf_specvla.cli import main

    for command, start in (("bench-episodes", seeds.BENCH_SEED_START), ("eval", seeds.EVAL_SEED_START),
                           ("compare", seeds.EVAL_SEED_START), ("train-draft", seeds.DRAFT_SEED_START)):  # fmt: skip
        with pytest.raises(SystemExit):
            main([command, "--help"])
        assert f"(default: {start})" in capsys.readouterr().out.replace("\n", " ").replace("  ", " "), command
