"""The folder rule: a folder records what produced it; only the same run continues it; overwrite moves it aside;
a torn last log line is redone."""

import json
import logging
import os
import signal
import subprocess
import sys
import textwrap

import pytest
import torch

from hf_specvla.run_folder import (
    LOCK_FILE,
    RUN_FILE,
    TIMING_FILE,
    FolderInUseError,
    FolderTiming,
    RunRecord,
    TimingConditionsError,
    claim_run_folder,
    fingerprint,
    machine_fingerprint,
    open_run_folder,
    read_jsonl,
    resolve_timing,
    timing_conditions,
    write_timing,
)


def test_new_same_other_and_unrecorded_folders(tmp_path):
    folder = tmp_path / "run"
    record = RunRecord("eval", {"policy": "abc", "seed_start": 1})
    assert open_run_folder(folder, record) is False  # new: the record is written first
    assert json.loads((folder / RUN_FILE).read_text())["settings"] == {"policy": "abc", "seed_start": 1}
    (folder / "episodes.jsonl").write_text("{}\n")
    assert open_run_folder(folder, RunRecord("eval", {"policy": "abc", "seed_start": 1})) is True  # continues
    with pytest.raises(FileExistsError, match="policy: 'xyz' here vs 'abc' there.*--overwrite-output-dir"):
        open_run_folder(folder, RunRecord("eval", {"policy": "xyz", "seed_start": 1}))
    with pytest.raises(FileExistsError, match="written by `hf-specvla eval`, this is `hf-specvla compare`"):
        open_run_folder(folder, RunRecord("compare", {"policy": "abc", "seed_start": 1}))
    unrecorded = tmp_path / "old"
    unrecorded.mkdir()
    (unrecorded / "episodes.jsonl").write_text("{}\n")
    with pytest.raises(FileExistsError, match="has no run.json"):
        open_run_folder(unrecorded, record)
    assert open_run_folder(tmp_path / "empty_but_there", record) is False


def test_overwrite_moves_the_previous_run_aside_whole(tmp_path):
    folder = tmp_path / "run"
    open_run_folder(folder, RunRecord("eval", {"policy": "abc"}))
    (folder / "episodes.jsonl").write_text('{"old": 1}\n')
    assert open_run_folder(folder, RunRecord("eval", {"policy": "xyz"}), overwrite=True) is False
    assert sorted(p.name for p in folder.iterdir()) == [LOCK_FILE, RUN_FILE]  # nothing of the old run is mixed in
    (aside,) = tmp_path.glob("run.replaced-*")
    assert (aside / "episodes.jsonl").read_text() == '{"old": 1}\n'  # and nothing was lost


HOLDER = textwrap.dedent("""
    import sys, time
    from hf_specvla.run_folder import RunRecord, claim_run_folder
    run = claim_run_folder(sys.argv[1], RunRecord("eval", {"policy": "abc"}))
    (run.bound / "episodes.jsonl").write_text("{}\\n")
    print("held", flush=True)
    sys.stdin.readline()  # holds the folder until told
    (run.bound / "late.txt").write_text("written after the rename")
    print("wrote", flush=True)
    sys.stdin.readline()
""")


def hold_in_another_process(folder):
    process = subprocess.Popen([sys.executable, "-c", HOLDER, str(folder)], stdin=subprocess.PIPE,
                               stdout=subprocess.PIPE, text=True)  # fmt: skip
    assert process.stdout.readline().strip() == "held"
    return process


def test_a_folder_held_by_a_live_process_is_refused_even_to_overwrite(tmp_path, caplog):
    folder = tmp_path / "run"
    holder = hold_in_another_process(folder)
    try:
        for overwrite in (False, True):
            expected = rf"in use by another run \(pid {holder.pid}, `.*-c .*run`, started 20\d\d-.*\).*live run"
            with pytest.raises(FolderInUseError, match=expected):
                claim_run_folder(folder, RunRecord("eval", {"policy": "xyz"}), overwrite=overwrite)
        assert not list(tmp_path.glob("run.replaced-*"))  # nothing was moved aside
        assert (folder / "episodes.jsonl").exists()
    finally:
        holder.kill()  # kill -9: the OS releases its lock; the lock file still names it
        holder.wait()
    with caplog.at_level(logging.WARNING), claim_run_folder(folder, RunRecord("eval", {"policy": "abc"})) as run:
        assert run.continued
    assert f"taking over the lock of a run that is no longer running (pid {holder.pid}" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING), claim_run_folder(folder, RunRecord("eval", {"policy": "abc"})):
        pass
    assert "taking over" not in caplog.text  # a clean release leaves no holder behind


def test_a_live_run_is_never_redirected_into_a_new_folder_of_its_name(tmp_path):
    """The holder's folder is renamed and a new run starts under the old name: the holder's later writes land in
    the folder it claimed (now renamed), never in the new run's."""
    folder = tmp_path / "run"
    holder = hold_in_another_process(folder)
    try:
        os.replace(folder, tmp_path / "renamed")  # e.g. a user's mv while the run is live
        with claim_run_folder(folder, RunRecord("eval", {"policy": "xyz"})) as new_run:
            holder.stdin.write("\n")
            holder.stdin.flush()
            assert holder.stdout.readline().strip() == "wrote"
            assert (tmp_path / "renamed" / "late.txt").read_text() == "written after the rename"
            assert sorted(p.name for p in new_run.bound.iterdir()) == [LOCK_FILE, RUN_FILE]
    finally:
        holder.send_signal(signal.SIGKILL)
        holder.wait()


def test_a_torn_last_line_is_dropped_and_redone(tmp_path, caplog):
    log = tmp_path / "episodes.jsonl"
    log.write_text('{"seed": 1}\n{"seed": 2}\n{"seed": 3, "succ')
    with caplog.at_level(logging.WARNING):
        assert read_jsonl(log) == [{"seed": 1}, {"seed": 2}]
    assert "torn last line" in caplog.text and log.read_text() == '{"seed": 1}\n{"seed": 2}\n'
    log.write_text('{"seed": 1}\n{"se\n{"seed": 3}\n')
    with pytest.raises(ValueError, match="line 2 is not valid JSON"):
        read_jsonl(log)


def test_fingerprint_is_about_weights_not_paths():
    a, b = torch.nn.Linear(3, 2), torch.nn.Linear(3, 2)
    assert fingerprint(a) != fingerprint(b)
    b.load_state_dict(a.state_dict())
    assert fingerprint(a) == fingerprint(b)


# ------------------------------------------------------------------------------- evaluation folders
pytest.importorskip("metaworld")


@pytest.fixture(scope="module")
def tiny_policy():
    from hf_specvla import ActionNormalizer
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

    config = VLAPolicyConfig(image_size=32, patch_size=16, vision_hidden_size=32, vision_layers=1,
                             text_hidden_size=64, text_layers=2, text_heads=4)  # fmt: skip
    actions = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4)
    states = ActionNormalizer(q01=[-0.5, 0.3, 0.0, 0.0], q99=[0.5, 1.0, 0.4, 1.0])
    return VLAPolicy.build(["reach the goal"], actions, states, config, seed=3)


def test_eval_refuses_another_run_and_redoes_a_torn_episode(tmp_path, tiny_policy, caplog):
    """Regression (reliability issue, cases 3 and 9): evaluating into a folder that holds results of another
    policy, decoding setting or step limit used to "resume" and report the old numbers; a torn last line of
    episodes.jsonl used to stop resume with a raw JSONDecodeError."""
    from hf_specvla.metaworld.env import EnvConfig
    from hf_specvla.metaworld.evaluation import evaluate
    from hf_specvla.policies import VLAPolicy

    env = EnvConfig(32, tiny_policy.config.camera, max_episode_steps=2)
    out = tmp_path / "eval"
    first = evaluate(tiny_policy, "reach", 2, out, env, progress=False)
    lines = (out / "episodes.jsonl").read_text().splitlines()
    assert len(lines) == 2
    with pytest.raises(
        FileExistsError, match=r"holds another run: decoding.action_prior: True here vs '\(not set\)' there; choose"
    ):
        evaluate(tiny_policy, "reach", 2, out, env, generate_kwargs={"action_prior": True}, progress=False)
    with pytest.raises(FileExistsError, match="max_episode_steps"):
        evaluate(tiny_policy, "reach", 2, out, EnvConfig(32, env.camera, max_episode_steps=3), progress=False)
    other = VLAPolicy.build(["reach the goal"], tiny_policy.action_normalizer, tiny_policy.state_normalizer,
                            tiny_policy.config, seed=4)  # fmt: skip
    with pytest.raises(FileExistsError, match="holds another run: policy: "):
        evaluate(other, "reach", 2, out, env, progress=False)
    # a crash mid-write of the second episode: its line is dropped and the episode redone, identically
    (out / "episodes.jsonl").write_text(lines[0] + "\n" + lines[1][: len(lines[1]) // 2])
    with caplog.at_level(logging.WARNING):
        again = evaluate(tiny_policy, "reach", 2, out, env, progress=False)
    # the warning names the folder the user gave, not the claimed folder's /proc/<pid>/fd binding (issue 55, item 5)
    assert f"{out / 'episodes.jsonl'}: dropping a torn last line" in caplog.text and "/proc/" not in caplog.text

    def without_latencies(text_lines):  # wall times differ between runs; everything else must not
        return [{k: v for k, v in json.loads(x).items() if k != "latencies_ms"} for x in text_lines]

    assert without_latencies((out / "episodes.jsonl").read_text().splitlines()) == without_latencies(lines)
    assert again["overall"]["success_rate"] == first["overall"]["success_rate"]
    # the explicit way out: the old run is moved aside, the new one starts clean
    evaluate(other, "reach", 1, out, env, overwrite=True, progress=False)
    assert len((out / "episodes.jsonl").read_text().splitlines()) == 1
    assert len(list(tmp_path.glob("eval.replaced-*/episodes.jsonl"))) == 1


def test_an_eval_folder_records_a_typed_plan_as_its_loose_options(tmp_path, tiny_policy):
    """``evaluate(decoding=plan)`` (what ``hf-specvla eval`` passes) records the same decoding as the plan's loose
    options: a folder made either way continues the other way, and another plan is refused naming what differs."""
    from hf_specvla.metaworld.env import EnvConfig
    from hf_specvla.metaworld.evaluation import evaluate
    from hf_specvla.policies import DecodingMethod

    env = EnvConfig(32, tiny_policy.config.camera, max_episode_steps=2)
    plan = DecodingMethod.parse("prior+jacobi:r=1").plan(None, action_dim=tiny_policy.config.action_dim)
    out = tmp_path / "eval"
    evaluate(tiny_policy, "reach", 1, out, env, decoding=plan, progress=False)
    loose = evaluate(tiny_policy, "reach", 2, out, env, generate_kwargs=plan.predict_kwargs(), progress=False)
    assert loose["overall"]["episodes"] == 2 and len((out / "episodes.jsonl").read_text().splitlines()) == 2
    exact = DecodingMethod.parse("prior+jacobi").plan(None, action_dim=tiny_policy.config.action_dim)
    with pytest.raises(FileExistsError, match=r"holds another run: decoding.bin_tolerance: '\(not set\)' here vs 1"):
        evaluate(tiny_policy, "reach", 2, out, env, decoding=exact, progress=False)
    with pytest.raises(TypeError, match=r"evaluate got decoding=dict: decoding= takes a DecodingPlan"):
        evaluate(tiny_policy, "reach", 2, tmp_path / "never", env, decoding=plan.predict_kwargs(), progress=False)
    assert not (tmp_path / "never").exists()  # refused before the folder was claimed


def test_video_is_checked_up_front_and_never_costs_an_episode(tmp_path, tiny_policy, monkeypatch, caplog):
    """Regression (reliability issue, case 7): `--video x.mp4` failed after the first rollout (no mp4 writer), that
    episode was never logged, and every rerun failed the same way; `--video` on a resumed folder was dropped."""
    import hf_specvla.metaworld.evaluation as evaluation
    from hf_specvla.cli import main
    from hf_specvla.metaworld.env import EnvConfig

    with pytest.raises(ValueError, match="extension must be one of"):
        evaluation.check_video_path("x.avi")
    monkeypatch.setattr(evaluation.importlib.util, "find_spec", lambda name: None)  # no imageio-ffmpeg
    with pytest.raises(ValueError, match="needs imageio-ffmpeg"):
        evaluation.check_video_path(tmp_path / "x.mp4")
    with pytest.raises(SystemExit) as exit_info:
        main(["eval", "--policy", "p", "--output-dir", str(tmp_path / "e"), "--video", str(tmp_path / "x.mp4")])
    assert exit_info.value.code == 2 and not (tmp_path / "e").exists()  # refused before anything is written
    monkeypatch.undo()

    env = EnvConfig(32, tiny_policy.config.camera, max_episode_steps=2)
    out = tmp_path / "eval"

    def broken_writer(frames, path):
        raise OSError("disk full")

    monkeypatch.setattr(evaluation, "_save_video", broken_writer)
    with pytest.raises(OSError, match="disk full"):
        evaluation.evaluate(tiny_policy, "reach", 2, out, env, video_path=tmp_path / "v.gif", progress=False)
    assert len((out / "episodes.jsonl").read_text().splitlines()) == 1  # the episode was logged first
    monkeypatch.undo()
    evaluation.evaluate(tiny_policy, "reach", 2, out, env, video_path=tmp_path / "v.gif", progress=False)
    assert (tmp_path / "v.gif").exists()  # the rerun records the first episode it runs
    with caplog.at_level(logging.WARNING):
        evaluation.evaluate(tiny_policy, "reach", 2, out, env, video_path=tmp_path / "w.gif", progress=False)
    assert "no video written" in caplog.text and not (tmp_path / "w.gif").exists()


# ----------------------------------------------------------------------------- timing conditions
def test_timings_continue_only_under_their_conditions(tmp_path, caplog):
    folder = tmp_path / "run"
    folder.mkdir()
    one, two = timing_conditions(1, 1, 1), timing_conditions(1, 2, 2)
    assert one["machine"] == machine_fingerprint() and {"system", "cpu", "cpu_count", "torch"} <= set(one["machine"])
    assert resolve_timing(folder, one, []) == FolderTiming(one, None)  # a new folder takes this run's conditions
    write_timing(folder, FolderTiming(one, None))
    records = [{"seed": s, "timing": one} for s in range(3)]
    assert resolve_timing(folder, one, records) == FolderTiming(one, None)  # the same conditions continue
    # other threads: refused, naming what differs, both conditions and the ways out
    with pytest.raises(TimingConditionsError) as refusal:
        resolve_timing(folder, two, records)
    message = str(refusal.value)
    assert "threads: 2 here vs 1 there" in message and "torch_threads: 2 here vs 1 there" in message
    assert "recorded workers=1, threads=1, torch_threads=1 on " in message
    assert "this run workers=1, threads=2, torch_threads=2 (the same machine)" in message
    assert "--restart-timing" in message and isinstance(refusal.value, FileExistsError)  # the CLI's usage errors
    other_machine = {**one, "machine": {**one["machine"], "cpu_count": 96}}
    with pytest.raises(TimingConditionsError, match="machine.cpu_count: 96 here vs"):
        resolve_timing(folder, other_machine, records)
    # a restart: this run's conditions from now on; the earlier records stay, out of the speed figures
    with caplog.at_level(logging.WARNING):
        restarted = resolve_timing(folder, two, records, restart=True)
    assert restarted == FolderTiming(two, None) and "timing restarted" in caplog.text
    assert not any(restarted.timed(r) for r in records) and restarted.timed({"timing": two})
    write_timing(folder, restarted)
    assert json.loads((folder / TIMING_FILE).read_text())["conditions"]["threads"] == 2
    assert resolve_timing(folder, two, [*records, {"timing": two}]) == restarted  # and it continues without the flag
    with pytest.raises(TimingConditionsError, match="threads: 1 here vs 2 there"):
        resolve_timing(folder, one, records)  # the first conditions are not the folder's any more


def test_records_from_before_timing_conditions_were_recorded(tmp_path, caplog):
    """Records without ``timing`` are taken as timed under the first continuing run's conditions (with a warning),
    unless what the folder recorded elsewhere disagrees (refused) or the timing restarts (left out)."""
    folder = tmp_path / "old"
    folder.mkdir()
    now, untimed = timing_conditions(2, 1, 1), [{"seed": 0}, {"seed": 1}]
    with caplog.at_level(logging.WARNING):
        adopted = resolve_timing(folder, now, untimed, untimed_hint={"workers": 2, "threads": 1})
    assert adopted == FolderTiming(now, now) and all(adopted.timed(r) for r in untimed)
    assert "2 records were written before timing conditions were recorded; they are taken as timed" in caplog.text
    with pytest.raises(TimingConditionsError, match=r"workers: 2 here vs 1 there\): recorded workers=1, threads=1;"):
        resolve_timing(folder, now, untimed, untimed_hint={"workers": 1, "threads": 1})
    for hint in ({"workers": 1, "threads": 1}, None):  # restarted: they stay, out of the speed figures
        restarted = resolve_timing(folder, now, untimed, restart=True, untimed_hint=hint)
        assert restarted == FolderTiming(now, None) and not any(restarted.timed(r) for r in untimed)
    write_timing(folder, adopted)  # once adopted, they count under those conditions only
    later = resolve_timing(folder, timing_conditions(1, 1, 1), [*untimed, {"timing": now}], restart=True)
    assert later.untimed_conditions == now and not later.timed(untimed[0])


def test_a_draft_run_from_before_float16_hidden_states_is_told_what_changed():
    """train-draft stored float32 hidden states before it recorded how: such a folder reads as float32, so a run that
    stores float16 is refused naming the storage, and one that stores float32 continues it."""
    old = RunRecord("train-draft", {"policy": "abc"})
    half = RunRecord("train-draft", {"policy": "abc", "distillation": {"hidden_dtype": "float16"}})
    full = RunRecord("train-draft", {"policy": "abc", "distillation": {"hidden_dtype": "float32"}})
    assert old.differences(half) == ["distillation.hidden_dtype: 'float16' here vs 'float32' there"]
    assert old.differences(full) == []


#: every method ``DecodingMethod`` accepts, the presets among them
RECORDED_METHODS = ("none", "prior", "jacobi", "prior+jacobi", "exact", "fast", "greedy:compile", "none:compile",
                    "prior+jacobi:r=4/4/4/0,m=1:compile")  # fmt: skip
HEAD_METHODS = ("head", "tree", "prior+head", "prior+tree", "jacobi+tree", "prior+jacobi+tree",
                "prior+jacobi+tree:compile", "exact", "fast")  # fmt: skip
_DESCRIBE = """
import json, sys
from hf_specvla import DraftHead
from hf_specvla.metaworld.evaluation import describe_decoding
from hf_specvla.policies import DecodingMethod
head = DraftHead.from_pretrained(sys.argv[1])
methods = json.loads(sys.argv[2])
print(json.dumps({f"{name}|{with_head}": describe_decoding(DecodingMethod.parse(name, with_head, 4).plan(
    head if with_head else None, action_dim=4).predict_kwargs()) for name, with_head in methods}))
"""


def test_a_folders_decoding_record_is_the_same_in_every_process_for_every_method(tmp_path, tiny_policy):
    """Reliability-6 row 6: the record of a plan's decoding holds no ``repr`` with a memory address and names a
    tree's head by its fingerprint, so that the same settings give the same record in another process (an eval
    folder continues), for every method ``DecodingMethod`` accepts, with and without a head."""
    from hf_specvla import DraftHead
    from hf_specvla.metaworld.evaluation import describe_decoding
    from hf_specvla.policies import DecodingMethod

    head = DraftHead.from_target(tiny_policy.model, tiny_policy.action_tokenizer, action_dim=4).eval()
    head.save_pretrained(tmp_path / "head")
    methods = [(name, False) for name in RECORDED_METHODS] + [(name, True) for name in HEAD_METHODS]
    here = {}
    for name, with_head in methods:
        records = [describe_decoding(DecodingMethod.parse(name, with_head, 4).plan(
            head if with_head else None, action_dim=4).predict_kwargs()) for _ in range(2)]  # fmt: skip
        assert records[0] == records[1], name
        text = json.dumps(records[0])
        assert " at 0x" not in text, (name, text)
        if with_head and "tree" in DecodingMethod.parse(name, True, 4).drafters:
            assert fingerprint(head) in text, (name, text)  # the tree's head named by its weights
        here[f"{name}|{with_head}"] = records[0]
    other = subprocess.run([sys.executable, "-c", _DESCRIBE, str(tmp_path / "head"), json.dumps(methods)],
                           capture_output=True, text=True, timeout=600, check=True)  # fmt: skip
    assert json.loads(other.stdout.strip().splitlines()[-1]) == json.loads(json.dumps(here))


@pytest.mark.parametrize("method", ["none", "jacobi+tree", "prior+jacobi+tree"])
def test_an_eval_folder_of_every_plan_continues(tmp_path, tiny_policy, method):
    """Reliability-6 row 6: ``evaluate(decoding=plan)`` run again with more episodes continues its folder (it used to
    say "holds another run" for ``none`` and the tree plans), and a plan of another head is refused naming it."""
    from hf_specvla import DraftHead
    from hf_specvla.metaworld.env import EnvConfig
    from hf_specvla.metaworld.evaluation import evaluate
    from hf_specvla.policies import DecodingMethod

    torch.manual_seed(0)
    heads = [DraftHead.from_target(tiny_policy.model, tiny_policy.action_tokenizer, action_dim=4).eval()
             for _ in range(2)]  # fmt: skip
    env = EnvConfig(32, tiny_policy.config.camera, max_episode_steps=2)
    out = tmp_path / "eval"

    def plan(head):  # made anew each run, as each run of the command makes its own
        return DecodingMethod.parse(method, True, 4).plan(head, action_dim=4)

    evaluate(tiny_policy, "reach", 1, out, env, decoding=plan(heads[0]), progress=False)
    summary = evaluate(tiny_policy, "reach", 2, out, env, decoding=plan(heads[0]), progress=False)
    assert summary["overall"]["episodes"] == 2
    if "tree" in method:
        with pytest.raises(FileExistsError, match="holds another run: decoding.assistant_model"):
            evaluate(tiny_policy, "reach", 3, out, env, decoding=plan(heads[1]), progress=False)
