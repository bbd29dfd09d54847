"""`hf-specvla compare`: paired side-by-side of decoding methods; its statistics on hand-made outcomes; bad input."""

import json
import re

import numpy as np
import pytest

from hf_specvla.metaworld.comparison import (
    DRAFTER_CHOICES,
    PRESETS,
    DecodingMethod,
    format_comparison,
    paired_difference,
    paired_speedup,
    parse_methods,
    per_call_latencies,
    summarize_comparison,
)


def test_paired_difference_known_answers():
    same = paired_difference([True, False] * 10, [True, False] * 10)
    assert (same["difference"], same["ci_low"], same["ci_high"]) == (0.0, 0.0, 0.0)
    assert (same["greedy_only"], same["method_only"], same["pairs"]) == (0, 0, 20)
    better = paired_difference([True] * 5, [False] * 5)
    assert (better["difference"], better["ci_low"], better["ci_high"], better["method_only"]) == (1.0, 1.0, 1.0, 5)
    # 100 pairs, 10 won by the method only: d = 0.10, sd(d) = 0.30 -> about 0.10 +- 1.96 * 0.030
    won = paired_difference([True] * 10 + [False] * 90, [False] * 100)
    assert won["difference"] == pytest.approx(0.10)
    assert 0.04 <= won["ci_low"] <= 0.06 and 0.15 <= won["ci_high"] <= 0.17
    # 20 won, 10 lost, 70 tied: d = 0.10, var(d) = 0.30 - 0.01 -> se 0.054: the interval includes 0
    method = [True] * 20 + [False] * 10 + [True] * 35 + [False] * 35
    greedy = [False] * 20 + [True] * 10 + [True] * 35 + [False] * 35
    mixed = paired_difference(method, greedy)
    assert mixed["difference"] == pytest.approx(0.10) and (mixed["greedy_only"], mixed["method_only"]) == (10, 20)
    assert -0.02 <= mixed["ci_low"] <= 0.01 and 0.19 <= mixed["ci_high"] <= 0.22
    with pytest.raises(ValueError, match="equally long"):
        paired_difference([True], [True, False])


def test_paired_speedup_is_the_ratio_of_total_time_per_call():
    greedy = [[10.0, 12.0, 14.0], [20.0, 20.0], [9.0]]  # 6 calls, 85 ms
    method = [[5.0, 6.0, 7.0], [10.0, 12.0], [3.0]]  # 6 calls, 43 ms
    result = paired_speedup(greedy, method)
    assert result["speedup"] == pytest.approx(85 / 43) and result["pairs"] == 3
    assert result["ci_low"] <= result["speedup"] <= result["ci_high"]
    # calls may differ (a relaxed episode can end elsewhere): the ratio of the mean ms per call
    relaxed = [[5.0, 6.0], [10.0, 12.0, 8.0, 9.0], [3.0]]  # 7 calls, 53 ms
    assert paired_speedup(greedy, relaxed)["speedup"] == pytest.approx((85 / 6) / (53 / 7))
    # identical timings: 1.0 with a degenerate interval; twice as fast on every call: 2.0, degenerate too
    same = paired_speedup(greedy, greedy)
    assert (same["speedup"], same["ci_low"], same["ci_high"]) == (1.0, 1.0, 1.0)
    twice = paired_speedup(greedy, [[x / 2 for x in episode] for episode in greedy])
    assert (twice["speedup"], twice["ci_low"], twice["ci_high"]) == (2.0, 2.0, 2.0)
    # not the median of per-episode ratios: one slow episode moves the total, not the median
    rng = np.random.default_rng(0)
    base = [list(rng.uniform(90, 110, 50)) for _ in range(40)]
    fast = [[x / 1.5 for x in episode] for episode in base]
    fast[0] = [x * 20 for x in fast[0]]  # one episode 20x slower
    result = paired_speedup(base, fast)  # 4000 ms against 39 x 66.7 + 1333 ms: ~1.02x (the median ratio: 1.5x)
    assert 1.0 < result["speedup"] < 1.05 and result["ci_low"] <= result["speedup"] <= result["ci_high"]
    assert result == paired_speedup(base, fast)  # a fixed seed: the same interval every time
    for bad, message in [(([[1.0]], [[1.0], [1.0]]), "equally long"), (([], []), "non-empty"),
                         (([[1.0]], [[]]), "at least one timed call")]:  # fmt: skip
        with pytest.raises(ValueError, match=message):
            paired_speedup(*bad)


def _record(task, seed, method, latencies, success=True, timing=None):
    """A comparison log record with the fields the statistics read (4 tokens per call, greedy's forwards)."""
    record = {"task": task, "seed": seed, "method": method, "success": success, "length": len(latencies),
              "latencies_ms": latencies, "target_forwards": 4 * len(latencies), "new_tokens": 4 * len(latencies),
              "accept_length_counts": {"1": 4 * len(latencies)}, "bin_distance_sum": 0, "bin_distance_count": 0,
              "bin_distance_max": 0, "actions_digest": f"{task}{seed}"}  # fmt: skip
    return record if timing is None else {**record, "timing": timing}


def test_summary_keeps_per_call_times_and_times_only_episodes_of_the_folders_conditions():
    rng = np.random.default_rng(1)
    records = []
    for seed in range(6):
        greedy = [round(float(x), 3) for x in rng.uniform(90, 110, 20)]
        records.append(_record("reach-v3", seed, "greedy", greedy, timing="old" if seed < 2 else "new"))
        method = [round(x / 2, 3) for x in greedy] if seed >= 2 else [round(x * 5, 3) for x in greedy]
        records.append(_record("reach-v3", seed, "prior", method, timing="old" if seed < 2 else "new"))
    methods = ["greedy", "prior"]
    summary = summarize_comparison(records, methods, timed=lambda r: r["timing"] == "new")
    row = summary["methods"]["prior"]
    # speed from the 4 seeds timed under the folder's conditions only; success from all 6
    assert row["episodes"] == 6 and row["timed_episodes"] == 4 and row["vs_greedy"]["pairs"] == 6
    assert row["speedup_total"]["pairs"] == 4 and row["speedup_total"]["speedup"] == pytest.approx(2.0, rel=1e-4)
    assert row["speedup"] == pytest.approx(2.0, rel=1e-3) and row["speedup_vs_greedy_compile"] is None
    assert row["speedup_total_vs_greedy_compile"] is None
    everything = summarize_comparison(records, methods)["methods"]["prior"]
    assert everything["speedup_total"]["pairs"] == 6 and everything["speedup_total"]["speedup"] < 1.0
    # the per-call times kept in the summary recompute the statistic (to their 0.01 ms rounding)
    kept = per_call_latencies(json.loads(json.dumps(summary)))
    assert sorted(kept["prior"]) == [("reach-v3", s) for s in range(2, 6)]
    assert kept["greedy"]["reach-v3", 2] == pytest.approx(records[4]["latencies_ms"], abs=0.005)
    keys = sorted(kept["prior"])
    again = paired_speedup([kept["greedy"][k] for k in keys], [kept["prior"][k] for k in keys])
    assert again["speedup"] == pytest.approx(row["speedup_total"]["speedup"], rel=1e-4)
    table = format_comparison(summary)
    assert "speed-up, mean per call (95% CI)" in table and "speed-up, median of ratios" in table
    assert f"| {row['speedup_total']['speedup']:.2f}x [" in table and "(4 pairs)" in table
    # against compiled greedy too, when it ran
    compiled = [_record(r["task"], r["seed"], "greedy:compile", [x / 2 for x in r["latencies_ms"]])
                for r in records if r["method"] == "greedy"]  # fmt: skip
    row = summarize_comparison(records + compiled, ["greedy", "greedy:compile", "prior"])["methods"]["prior"]
    assert row["speedup_total_vs_greedy_compile"]["speedup"] == pytest.approx(
        row["speedup_total"]["speedup"] / 2, rel=1e-6
    )


def test_deviation_by_phase_splits_by_the_size_of_greedys_action():
    """Tokens whose greedy value is >= the threshold count as large motions, the others as small; per dimension the
    mean bins, the units (bins x width), the share changed and the largest; a method without the fields has none."""
    relaxed = "prior:rho=0.1/0.1/0.1/0"
    records = [_record("reach-v3", 0, "greedy", [10.0, 10.0]), _record("reach-v3", 0, relaxed, [5.0, 5.0])]
    # 2 calls x 1 action of 4 dims: x large (0.9, 0.5) and small (0.1); the gripper always 1.0 and never changed
    records[1].update(bin_distances=[4, 0, 1, 0, 2, 0, 0, 0], reference_magnitudes=[0.9, 0.1, 0.5, 1.0,
                      0.5, 0.2, 0.05, 1.0], bin_widths=[0.01, 0.01, 0.02, 0.5], bin_distance_count=8)  # fmt: skip
    row = summarize_comparison(records, ["greedy", relaxed], motion_threshold=0.4)["methods"][relaxed]
    assert row["relaxed"] and row["bin_tolerance"] == 0
    phases = row["deviation_by_phase"]
    assert phases["threshold"] == 0.4
    assert phases["large"]["tokens_per_dim"] == [2, 0, 1, 2] and phases["small"]["tokens_per_dim"] == [0, 2, 1, 0]
    assert phases["large"]["mean_bins_per_dim"] == [3.0, 0.0, 1.0, 0.0]
    assert phases["large"]["mean_units_per_dim"] == pytest.approx([0.03, 0.0, 0.02, 0.0])
    assert phases["large"]["changed_per_dim"] == [1.0, 0.0, 1.0, 0.0] and phases["large"]["max_bins_per_dim"][0] == 4
    assert phases["small"]["mean_bins_per_dim"] == [0.0, 0.0, 0.0, 0.0]
    table = format_comparison(summarize_comparison(records, ["greedy", relaxed], motion_threshold=0.4))
    assert "large: |value| >= 0.4" in table and f"| {relaxed} | large | 3.00 (100%) / 0.00 (0%)" in table
    greedy_row = summarize_comparison(records, ["greedy", relaxed])["methods"]["greedy"]
    assert greedy_row["deviation_by_phase"] == {} and not greedy_row["relaxed"]


def test_jacobi_methods_build_their_drafters(random_draft):
    from hf_specvla import ComposedDrafter, DraftHeadDrafter, JacobiDrafter

    assert DecodingMethod.parse("prior+jacobi+tree:r=4:compile").name == "prior+jacobi+tree:r=4:compile"
    alone = DecodingMethod.parse("jacobi").generate_kwargs(None)["assistant_model"]
    assert isinstance(alone, JacobiDrafter) and alone.fill  # it fills the rounds nothing else drafts
    kwargs = DecodingMethod.parse("prior+jacobi").generate_kwargs(None)
    assert kwargs["action_prior"] and isinstance(kwargs["assistant_model"], JacobiDrafter)
    kwargs = DecodingMethod.parse("prior+jacobi+tree:r=2").generate_kwargs(random_draft)
    composed = kwargs["assistant_model"]
    assert isinstance(composed, ComposedDrafter) and kwargs["action_prior"] and kwargs["bin_tolerance"] == 2
    jacobi, tree = composed.drafters
    assert isinstance(jacobi, JacobiDrafter) and not jacobi.fill  # beside a tree, the tree drafts every round
    assert isinstance(tree, DraftHeadDrafter) and tree.tree_config is not None
    with pytest.raises(ValueError, match="needs a draft head"):
        DecodingMethod.parse("jacobi+tree").generate_kwargs(None)


def test_the_oracle_bound_runs_in_compare_only(policy_dir, tmp_path, capsys):
    """``oracle`` drafts greedy's own tokens (decoded off the clock): identical to greedy, one target forward per
    call, every position but the last of a call an accepted draft; elsewhere it is refused."""
    from hf_specvla.policies.decoding_methods import DecodingMethod

    with pytest.raises(ValueError, match="measured by `compare` only"):
        DecodingMethod.parse("oracle")
    with pytest.raises(ValueError, match="takes no r"):
        DecodingMethod.parse("oracle:r=2", oracle=True)
    out = tmp_path / "oracle"
    args = ["compare", "--policy", policy_dir, "--tasks", "reach", "--episodes", "1", "--max-episode-steps", "4",
            "--methods", "oracle", "--output-dir", str(out)]  # fmt: skip
    assert main(args) == 0
    row = json.loads((out / "summary.json").read_text())["methods"]["oracle"]
    assert row["identical_to_greedy"] == 1 and row["target_forwards_per_call"] == 1.0
    assert row["accepted_by_position"] == [1.0, 1.0, 1.0, 0.0]
    with pytest.raises(SystemExit) as refused:
        main(["eval", "--policy", policy_dir, "--method", "oracle", "--output-dir", str(tmp_path / "eval")])
    assert refused.value.code == 2 and "measured by `compare` only" in capsys.readouterr().err


def test_method_names():
    assert DecodingMethod.parse("prior+tree:r=4") == DecodingMethod("prior+tree", 4)
    assert DecodingMethod.parse("head:k=3").name == "head:k=3"
    assert DecodingMethod.parse("prior:r=0").name == "prior" and DecodingMethod.parse("prior").lossless
    assert DecodingMethod.parse("tree:r=2").uses_draft_head and not DecodingMethod.parse("prior:r=2").uses_draft_head
    assert [m.name for m in parse_methods(["prior", "prior:r=0", "head"])] == ["greedy", "prior", "head"]
    # :compile (static cache + CompileConfig): after the drafters or after the options; one canonical name
    assert DecodingMethod.parse("greedy:compile") == DecodingMethod(compiled=True)
    assert DecodingMethod.parse("prior+tree:r=4:compile") == DecodingMethod("prior+tree", 4, compiled=True)
    assert DecodingMethod.parse("prior+tree:r=4,compile").name == "prior+tree:r=4:compile"
    assert DecodingMethod.parse("head:compile,k=3").name == "head:k=3:compile"
    assert DecodingMethod.parse("tree:compile").uses_draft_head and DecodingMethod.parse("tree:compile").lossless
    kwargs = DecodingMethod.parse("prior:compile").generate_kwargs(None)
    assert kwargs["cache_implementation"] == "static" and kwargs["compile_config"]._compile_all_devices
    assert "compile_config" not in DecodingMethod.parse("prior").generate_kwargs(None)
    with pytest.raises(ValueError, match=re.escape("valid: " + ", ".join(DRAFTER_CHOICES))):
        DecodingMethod.parse("eagle")
    with pytest.raises(ValueError, match=re.escape("'jacobi+head' is not a drafter; valid: greedy, head")):
        DecodingMethod.parse("jacobi+head")
    for bad, message in [("prior:k=3", "needs the head chain"),
                         ("greedy:r=2", "takes no r, rl, rho, dev, m, gate, confirm or k"),
                         ("prior:x=1", "bad option 'x=1'"), ("head:k=0", "k must be an integer >= 1"),
                         ("prior:r=-1", "r must be an integer >= 0"), ("prior:r=x", "bad option 'r=x'"),
                         ("greedy:compile:compile", "'compile' given twice"),
                         ("prior:compiled", "bad option 'compiled'")]:  # fmt: skip
        with pytest.raises(ValueError, match=message):
            DecodingMethod.parse(bad)


def test_relaxed_rule_options_and_presets():
    method = DecodingMethod.parse("prior+jacobi:m=1,r=4/4/4/0,gate=0.50:compile")
    assert method.name == "prior+jacobi:r=4/4/4/0,m=1,gate=0.5:compile"  # one canonical order
    assert DecodingMethod.parse(method.name) == method and not method.lossless and method.widest_tolerance == 4
    assert method.rule_kwargs(4) == {"bin_tolerance": [4, 4, 4, 0], "max_relaxed_per_action": 1,
                                     "confidence_gate": 0.5}  # fmt: skip
    chunked = DecodingMethod.parse("prior:r=2,rl=6/6/6/0")
    assert chunked.rule_kwargs(4)["bin_tolerance"] == [[2, 2, 2, 2], [6, 6, 6, 0]]  # the first action, then the later
    assert chunked.generate_kwargs(None, action_dim=4)["bin_tolerance"] == [[2, 2, 2, 2], [6, 6, 6, 0]]
    assert chunked.tolerances() == [2, 6, 6, 6, 0]
    assert DecodingMethod.parse("prior:r=4,m=0").lossless  # a budget of 0 relaxes nothing
    # presets resolve to full method strings, with or without a draft head
    for preset in PRESETS.values():
        assert DecodingMethod.parse(preset.name) == preset.resolve(False, 4)
        assert DecodingMethod.parse(preset.name, draft_head_given=True) == preset.resolve(True, 4)
    assert DecodingMethod.parse("exact").lossless and not DecodingMethod.parse("fast").lossless
    assert [m.name for m in parse_methods(["exact", "prior+jacobi:compile"])] == ["greedy", "prior+jacobi:compile"]
    for bad, message in [("prior:gate=0.5", "give r"), ("prior:r=4,gate=2", r"gate must be a probability in \(0, 1\]"),
                         ("prior:r=4,gate=x", "gate must be a probability"), ("prior:r=4/x", "bad option 'r=4/x'"),
                         ("prior:r=4/-1", "r must be an integer >= 0"), ("prior:r=4,m=-1", "m must be an integer"),
                         ("prior:r=4,r=2", "r given twice"),
                         ("greedy:m=1", "takes no r, rl, rho, dev, m, gate, confirm or k"),
                         ("prior:rl=", "bad option 'rl='"), ("quick", "or a preset: exact, fast")]:  # fmt: skip
        with pytest.raises(ValueError, match=message):
            DecodingMethod.parse(bad)


# ----------------------------------------------------------------------------- the command, on Meta-World
metaworld = pytest.importorskip("metaworld")

from hf_specvla.cli import main  # noqa: E402
from hf_specvla.metaworld.comparison import PLOTS  # noqa: E402
from tests.training.test_policy_draft import build_policy  # noqa: E402

COLUMNS = {"episodes", "success_rate", "task_success_rates", "vs_greedy", "mean_episode_length", "median_ms_per_call",
           "speedup", "speedup_vs_greedy_compile", "speedup_total", "speedup_total_vs_greedy_compile",
           "timed_episodes", "target_forwards_per_action", "target_forwards_per_call", "tokens_per_target_forward",
           "accept_length_counts", "mean_bin_deviation", "max_bin_deviation", "identical_to_greedy"}  # fmt: skip


@pytest.fixture(scope="module")
def policy_dir(tmp_path_factory):
    return build_policy(tmp_path_factory.mktemp("compare") / "policy", seed=0)


def test_compare_pairs_seeds_keeps_r0_identical_and_resumes(policy_dir, tmp_path, capsys):
    out = tmp_path / "compare"
    args = ["compare", "--policy", policy_dir, "--tasks", "reach", "--episodes", "2", "--max-episode-steps", "6",
            "--methods", "prior", "prior:r=8", "--output-dir", str(out)]  # fmt: skip
    assert main(args) == 0
    assert "| prior:r=8 |" in capsys.readouterr().out
    log = [json.loads(line) for line in (out / "episodes.worker-0.jsonl").read_text().splitlines()]
    assert len(log) == 6
    # pairing: every method ran every seed, and a seed's methods all ran before the next seed started
    methods = {"greedy", "prior", "prior:r=8"}
    for seed in (100_000, 100_001):
        assert {r["method"] for r in log if r["seed"] == seed} == methods
    assert [r["seed"] for r in log] == sorted(r["seed"] for r in log)
    # r=0 is lossless: the same actions, so the same episodes
    by_key = {(r["seed"], r["method"]): r for r in log}
    for seed in (100_000, 100_001):
        greedy, prior = by_key[seed, "greedy"], by_key[seed, "prior"]
        assert [prior[k] for k in ("length", "success", "actions_digest")] == [
            greedy[k] for k in ("length", "success", "actions_digest")
        ]
        relaxed = by_key[seed, "prior:r=8"]
        assert relaxed["bin_distance_count"] == 4 * relaxed["length"]
        # the deviation per action dimension adds up to the total, each dimension's maximum to the overall one
        assert sum(relaxed["bin_distance_sum_per_dim"]) == relaxed["bin_distance_sum"]
        assert max(relaxed["bin_distance_max_per_dim"]) == relaxed["bin_distance_max"]
    summary = json.loads((out / "summary.json").read_text())
    for name, row in summary["methods"].items():
        assert COLUMNS <= set(row), name
    relaxed_row = summary["methods"]["prior:r=8"]
    per_dim = relaxed_row["mean_bin_deviation_per_dim"]
    assert len(per_dim) == 4 and sum(per_dim) / 4 == pytest.approx(relaxed_row["mean_bin_deviation"])
    assert summary["methods"]["prior"]["identical_to_greedy"] == 2
    # acceptance by token position: per call, the positions taken by accepted drafts are the accepted tokens
    for record in log:
        calls, tokens = len(record["latencies_ms"]), 4
        accepted = sum(int(k) - 1 for k, v in record["accept_length_counts"].items() for _ in range(v))
        assert sum(record["accepted_by_position"]) == accepted and len(record["accepted_by_position"]) == tokens
        assert all(0 <= n <= calls for n in record["accepted_by_position"])
        assert record["accepted_by_position"][-1] == 0  # the last token of a call always ends its forward
    assert summary["methods"]["greedy"]["accepted_by_position"] == [0.0] * 4
    assert summary["action_dim"] == 4
    assert "| method | a0.x | a0.y | a0.z | a0.gripper |" in (out / "compare.md").read_text()
    assert summary["methods"]["greedy"]["target_forwards_per_action"] == 4.0
    assert summary["methods"]["greedy"]["target_forwards_per_call"] == 4.0
    for plot in PLOTS:
        assert (out / plot).read_bytes()[:4] == b"\x89PNG"
    assert (out / "compare.md").read_text().startswith("| method |")
    # resume: finished (seed, method) episodes are not run again; more seeds continue the folder
    assert main(args) == 0
    assert len((out / "episodes.worker-0.jsonl").read_text().splitlines()) == 6
    assert main([*args[:6], "3", *args[7:]]) == 0
    assert len((out / "episodes.worker-0.jsonl").read_text().splitlines()) == 9
    # fewer seeds than the folder holds: the summary covers the asked-for subset, and says so
    capsys.readouterr()
    assert main(args) == 0
    assert "summary.json and compare.md cover the 6 episodes this run asked for" in capsys.readouterr().err
    assert json.loads((out / "summary.json").read_text())["methods"]["prior"]["episodes"] == 2
    # other methods in the same folder: refused, naming the setting
    with pytest.raises(SystemExit) as exit_info:
        main([*args[:-4], "prior:r=2", "--output-dir", str(out)])
    assert exit_info.value.code == 2 and "holds another run: methods: [" in capsys.readouterr().err


@pytest.mark.commands  # ~20 s: compare with worker processes
def test_compare_splits_seeds_between_workers(policy_dir, tmp_path):
    out = tmp_path / "workers"
    assert main(["compare", "--policy", policy_dir, "--tasks", "reach", "--episodes", "2", "--max-episode-steps",
                 "3", "--methods", "prior", "--workers", "2", "--output-dir", str(out)]) == 0  # fmt: skip
    logs = sorted(out.glob("episodes.worker-*.jsonl"))
    assert len(logs) == 2
    seeds = [{json.loads(line)["seed"] for line in path.read_text().splitlines()} for path in logs]
    assert seeds == [{100_000}, {100_001}]  # each seed's methods in one worker: ratios taken within a worker
    assert json.loads((out / "summary.json").read_text())["methods"]["prior"]["identical_to_greedy"] == 2


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--methods", "greedy", "eagle"], "valid: greedy, head, tree, prior, prior+head, prior+tree"),
        (["--workers", "0"], "--workers: must be >= 1, got 0"),
        (["--methods", "tree:r=4"], "draft with a draft head: pass --draft-head"),
        (["--tasks", "bogus"], "bogus"),
        (["--methods", "prior:r=999"], "methods ['prior:r=999']: r is wider than the action range"),
        (["--methods", "prior:r=-1"], "r must be an integer >= 0"),
        (["--tree-depth", "9", "--tree-total-tokens", "4"], "total_tokens=4 cannot hold a path of depth=9"),
        (["--tree-top-k", "0"], "--tree-top-k: must be >= 1, got 0"),
        (["--motion-threshold", "0"], "--motion-threshold: must be a finite number > 0, got 0"),
        (["--motion-threshold", "big"], "--motion-threshold: expected a number > 0, got 'big'"),
        (["--methods", "prior:rho=0.1/0.1"], "rho=0.1/0.1 has 2 values, but the policy's actions have 4 dimensions"),
    ],
)
def test_compare_bad_input_is_a_usage_error(policy_dir, tmp_path, capsys, flags, message):
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "--policy", policy_dir, "--output-dir", str(tmp_path / "out"), *flags])
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_compare_refuses_a_draft_head_of_another_policy(policy_dir, tmp_path, capsys):
    from hf_specvla import DraftHead
    from hf_specvla.policies import VLAPolicy

    other = VLAPolicy.from_pretrained(build_policy(tmp_path / "other", seed=1))
    head = DraftHead.from_target(other.model, other.action_tokenizer, action_dim=4,
                                 target_fingerprint=other.weights_fingerprint())  # fmt: skip
    head.save_pretrained(tmp_path / "head")
    with pytest.raises(SystemExit) as exit_info:
        main(["compare", "--policy", policy_dir, "--draft-head", str(tmp_path / "head"), "--tasks", "reach",
              "--methods", "head", "--output-dir", str(tmp_path / "out")])  # fmt: skip
    assert exit_info.value.code == 2 and "trained for another model" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_compare_refuses_a_folder_another_live_run_is_writing(policy_dir, tmp_path, capsys):
    import os

    from hf_specvla.run_folder import lock_folder

    out = tmp_path / "locked"
    args = ["compare", "--policy", policy_dir, "--tasks", "reach", "--episodes", "1", "--max-episode-steps", "2",
            "--methods", "prior", "--output-dir", str(out)]  # fmt: skip
    assert main(args) == 0
    assert (out / ".lock").read_text() == ""  # released after the run: no holder named
    with lock_folder(out):  # a live holder (this process, through another open file)
        with pytest.raises(SystemExit) as exit_info:
            main(args)
    assert exit_info.value.code == 2 and f"pid {os.getpid()}" in capsys.readouterr().err
    (out / ".lock").write_text("999999999")  # a holder that is gone (an older hf_specvla's bare pid): taken over
    assert main(args) == 0


def test_an_unused_draft_head_is_ignored_with_a_warning(policy_dir, tmp_path, capsys):
    from hf_specvla import DraftHead
    from hf_specvla.policies import VLAPolicy

    policy = VLAPolicy.from_pretrained(policy_dir)
    head = DraftHead.from_target(policy.model, policy.action_tokenizer, action_dim=4,
                                 target_fingerprint=policy.weights_fingerprint())  # fmt: skip
    head.save_pretrained(tmp_path / "head")
    out = tmp_path / "no_head_methods"
    args = ["compare", "--policy", policy_dir, "--draft-head", str(tmp_path / "head"), "--tasks", "reach",
            "--episodes", "1", "--max-episode-steps", "2", "--methods", "prior", "--output-dir", str(out)]  # fmt: skip
    assert main(args) == 0
    assert "is not used: none of the methods ['greedy', 'prior'] drafts with a head" in capsys.readouterr().err
    assert json.loads((out / "run.json").read_text())["settings"]["draft_head"] is None


def test_seeds_run_seed_major_so_a_partial_run_covers_every_task():
    from hf_specvla.metaworld.comparison import CompareConfig

    config = CompareConfig(tasks=["reach", "push", "door-open"], episodes_per_task=2, methods=["greedy"], workers=2)
    pairs = config.pairs()
    assert pairs[:3] == [("reach-v3", 100000), ("push-v3", 100000), ("door-open-v3", 100000)]
    assert sorted(pairs) == sorted((t, 100000 + i) for t in ("reach-v3", "push-v3", "door-open-v3") for i in range(2))


def test_the_tree_settings_reach_the_tree_methods_drafter(random_draft):
    from hf_specvla import DraftTreeConfig
    from hf_specvla.metaworld.comparison.methods import CompareConfig, DecodingMethod

    config = CompareConfig("reach", 1, ["tree:compile", "prior+tree:r=4"], tree_top_k=2, tree_total_tokens=8)
    assert config.tree_config() == DraftTreeConfig(top_k=2, depth=DraftTreeConfig.depth, total_tokens=8)
    for name in config.methods[1:]:
        drafter = DecodingMethod.parse(name).generate_kwargs(random_draft, "cpu", config.tree_config())
        assert drafter["assistant_model"].tree_config == config.tree_config(), name
    default = DecodingMethod.parse("tree").generate_kwargs(random_draft)["assistant_model"]
    assert default.tree_config == DraftTreeConfig()
