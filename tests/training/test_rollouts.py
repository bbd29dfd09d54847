"""`hf-specvla rollouts`: a policy's greedy rollouts saved episode by episode; the same arrays in one go, killed and
resumed, in parts or split between workers; the frames the in-process collection of `train-draft` gives; a folder of
another policy or other settings refused; `train-draft --rollouts` trains on it."""

import json
import os
import shlex
import signal
import subprocess
import sys
import time
import weakref
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("metaworld")

from hf_specvla.cli import main  # noqa: E402
from hf_specvla.cli import rollouts as rollouts_command  # noqa: E402
from hf_specvla.cli.main import build_parser  # noqa: E402
from hf_specvla.policies import VLAPolicy  # noqa: E402
from hf_specvla.training.configuration import DraftDataConfig  # noqa: E402
from hf_specvla.training.draft_head import latest_checkpoint  # noqa: E402
from hf_specvla.training.policy_draft import rollout_frames  # noqa: E402
from hf_specvla.training.rollouts import (  # noqa: E402
    MANIFEST,
    RolloutConfig,
    collect_rollouts,
    env_config_for,
    finished_pairs,
    load_episode,
    read_rollout_frames,
)

from .test_policy_draft import build_policy  # noqa: E402

SHIPPED = Path(__file__).resolve().parents[2] / "policies" / "mt10_vla3"
TASKS = ["reach", "push"]


@pytest.fixture(scope="module")
def policy_dirs(tmp_path_factory):
    root = tmp_path_factory.mktemp("policies")
    return build_policy(root / "a", seed=0), build_policy(root / "b", seed=1)


@pytest.fixture(scope="module")
def policy(policy_dirs):
    return VLAPolicy.from_pretrained(policy_dirs[0])


def config(**overrides) -> RolloutConfig:
    settings = dict(tasks=TASKS, episodes_per_task=3, max_steps=5, method="greedy")
    return RolloutConfig(**{**settings, **overrides})


@pytest.fixture(scope="module")
def one_shot(policy, tmp_path_factory):
    """3 episodes of each task collected in one go, one worker."""
    folder = tmp_path_factory.mktemp("one_shot") / "rollouts"
    collect_rollouts(policy, config(), folder, progress=False)
    return folder


def assert_same_episodes(folder, reference) -> None:
    """Every episode of ``reference`` is in ``folder``, every array bit-identical, and nothing else is."""
    assert finished_pairs(folder) == finished_pairs(reference)
    for path in sorted(Path(reference).glob("episodes/*/*.npz")):
        mine, theirs = load_episode(Path(folder) / path.relative_to(reference)), load_episode(path)
        assert mine.keys() == theirs.keys()
        for name in theirs:
            assert mine[name].dtype == theirs[name].dtype and np.array_equal(mine[name], theirs[name]), (path, name)
    manifest = json.loads((Path(folder) / MANIFEST).read_text())
    assert manifest == json.loads((Path(reference) / MANIFEST).read_text())
    assert not list(Path(folder).glob("episodes/*/.*.tmp"))


def test_an_episode_file_holds_the_frames_labels_and_outcome(one_shot, policy):
    arrays = load_episode(one_shot / "episodes" / "push-v3" / "400001.npz")
    frames = len(arrays["image"])
    size, chunk, dim = policy.config.image_size, policy.config.chunk_length, policy.config.action_dim
    assert 1 <= frames <= 5 and arrays["image"].shape == (frames, size, size, 3) and arrays["image"].dtype == np.uint8
    assert arrays["state"].shape == (frames, policy.config.state_dim) and arrays["state"].dtype == np.float32
    assert arrays["previous_action"].shape == (frames, dim) and arrays["action_ids"].shape == (frames, chunk * dim)
    assert arrays["actions"].shape == (frames, chunk, dim)
    assert (str(arrays["task"]), int(arrays["seed"])) == ("push-v3", 400001)
    assert (arrays["previous_action"][0] == -1).all()  # the first frame has no previous action
    # the labels decode to the actions executed
    np.testing.assert_array_equal(policy.actions_from_token_ids(arrays["action_ids"].reshape(frames, chunk, dim)),
                                  arrays["actions"])  # fmt: skip
    manifest = json.loads((one_shot / MANIFEST).read_text())
    assert manifest["complete"] and len(manifest["episodes"]) == 6
    assert [e["frames"] for e in manifest["episodes"] if e["seed"] == 400001 and e["task"] == "push-v3"] == [frames]


def test_the_folder_gives_the_frames_of_the_in_process_collection(one_shot, policy):
    """train-draft --rollouts trains on exactly the frames train-draft collects in-process (held-out included)."""
    for max_steps in (5, 3):  # the folder's cut, and a shorter one (each episode's first frames)
        data = DraftDataConfig(TASKS, rollout_episodes=3, rollout_max_steps=max_steps, validation_episodes=1)
        expected = rollout_frames(policy, data, env_config_for(policy.config))
        read = read_rollout_frames(one_shot, policy, data)
        for got, want in zip((read.train, read.validation), expected):
            assert len(got) == len(want) > 0
            for a, b in zip(got, want):
                assert a.keys() == b.keys()
                for key in b:
                    if isinstance(b[key], np.ndarray):
                        assert a[key].dtype == b[key].dtype and np.array_equal(a[key], b[key]), key
                    else:
                        assert a[key] == b[key], key
    two = read_rollout_frames(one_shot, policy, DraftDataConfig(TASKS, rollout_episodes=2, rollout_max_steps=5))
    assert read.episodes == 6 and two.episodes == 4 and two.fingerprint != read.fingerprint
    assert read.fingerprint == json.loads((one_shot / MANIFEST).read_text())["fingerprint"]  # every episode read


@pytest.mark.commands  # ~25 s: worker processes
def test_in_parts_and_with_two_workers_the_arrays_are_those_of_one_go(policy, one_shot, tmp_path):
    folder = tmp_path / "parts"
    first = collect_rollouts(policy, config(max_episodes=2), folder, progress=False)
    # seed by seed across the tasks: a collection cut short holds the first seeds of every task
    assert first["new_episodes"] == 2 and not first["complete"]
    assert finished_pairs(folder) == {("reach-v3", 400000), ("push-v3", 400000)}
    last = collect_rollouts(policy, config(workers=2), folder, resume=True, progress=False)  # 2 episodes each
    assert last["new_episodes"] == 4 and last["complete"]
    assert_same_episodes(folder, one_shot)


@pytest.mark.commands  # ~25 s: a killed worker, resumed
def test_killed_mid_collection_then_resumed_is_bit_exact(policy_dirs, tmp_path):
    """kill -9 while episodes are being written, then the documented rerun (the same command with --resume)."""
    argv = ["rollouts", "--policy", policy_dirs[0], "--tasks", *TASKS, "--episodes-per-task", "8", "--max-steps",
            "5", "--method", "greedy", "--threads", "1"]  # fmt: skip
    killed, straight = tmp_path / "killed", tmp_path / "straight"
    env = dict(os.environ, MUJOCO_GL=os.environ.get("MUJOCO_GL", "egl"))
    process = subprocess.Popen([sys.executable, "-m", "hf_specvla.cli", *argv, "--output-dir", str(killed)], env=env,
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)  # fmt: skip
    deadline = time.monotonic() + 120
    try:
        while not finished_pairs(killed):
            assert process.poll() is None, f"the collection ended (exit {process.returncode}) before the kill"
            assert time.monotonic() < deadline, "no episode was written in 120 s"
            time.sleep(0.02)
    finally:
        process.send_signal(signal.SIGKILL)
        process.wait()
    assert 1 <= len(finished_pairs(killed)) < 16 and not (killed / MANIFEST).exists()
    assert main([*argv, "--output-dir", str(killed), "--resume"]) == 0
    assert main([*argv, "--output-dir", str(straight)]) == 0
    assert_same_episodes(killed, straight)


def test_speculative_labels_are_greedy_labels(tmp_path):
    """A lossless method (the previous action and Jacobi guesses verified at r=0) saves greedy's tokens, with fewer
    target forwards (the shipped policy v3: its previous action is mostly accepted)."""
    policy = VLAPolicy.from_pretrained(SHIPPED)
    forwards = []
    hook = policy.model.register_forward_hook(lambda *args: forwards.append(1))
    counts = {}
    for method in ("greedy", "prior+jacobi"):
        forwards.clear()
        collect_rollouts(policy, RolloutConfig("reach", 1, max_steps=6, method=method), tmp_path / method,
                         progress=False)  # fmt: skip
        counts[method] = len(forwards)
    hook.remove()
    assert counts["prior+jacobi"] < counts["greedy"]
    greedy = load_episode(tmp_path / "greedy" / "episodes" / "reach-v3" / "400000.npz")
    speculative = load_episode(tmp_path / "prior+jacobi" / "episodes" / "reach-v3" / "400000.npz")
    assert len(greedy["image"]) == 6
    for name in greedy:
        assert np.array_equal(speculative[name], greedy[name]), name


@pytest.mark.slow
def test_the_exact_preset_compiled_gives_greedy_labels(tmp_path):
    policy = VLAPolicy.from_pretrained(SHIPPED)
    for method in ("greedy", "exact"):
        collect_rollouts(policy, RolloutConfig(["reach", "push"], 1, max_steps=12, method=method), tmp_path / method,
                         progress=False)  # fmt: skip
    assert_same_episodes(tmp_path / "exact", tmp_path / "greedy")


def test_a_folder_of_another_policy_or_other_settings_is_refused(policy_dirs, one_shot, tmp_path):
    other = VLAPolicy.from_pretrained(policy_dirs[1])
    copy = tmp_path / "copy"
    # a folder of another collection is refused before anything runs, naming the difference
    with pytest.raises(FileExistsError, match="holds another run: policy: '"):
        collect_rollouts(other, config(), one_shot, resume=True, progress=False)
    same = VLAPolicy.from_pretrained(policy_dirs[0])
    changes = ((dict(max_steps=6), "max_steps: 6 here vs 5 there"),
               (dict(seed_start=7), "seed_start: 7 here vs 400000 there"),
               (dict(method="prior+jacobi"), r"method: 'prior\+jacobi' here vs 'greedy' there"))  # fmt: skip
    for change, named in changes:
        with pytest.raises(FileExistsError, match=named):
            collect_rollouts(same, config(**change), one_shot, resume=True, progress=False)
    with pytest.raises(FileExistsError, match="already holds this rollouts collection; pass --resume"):
        collect_rollouts(same, config(), one_shot, progress=False)
    with pytest.raises(FileNotFoundError, match="no run to resume"):
        collect_rollouts(same, config(), copy, resume=True, progress=False)
    assert not copy.exists()
    # train-draft refuses another policy's rollouts, and asks for no more episodes than the folder holds
    data = DraftDataConfig(TASKS, rollout_episodes=3, rollout_max_steps=5)
    with pytest.raises(ValueError, match="holds rollouts of another policy"):
        read_rollout_frames(one_shot, other, data)
    with pytest.raises(ValueError, match="holds 3 finished episodes .* give --rollout-episodes <= 3"):
        read_rollout_frames(one_shot, same, DraftDataConfig(TASKS, rollout_episodes=4, rollout_max_steps=5))
    with pytest.raises(ValueError, match="give --rollout-max-steps <= 5"):
        read_rollout_frames(one_shot, same, DraftDataConfig(TASKS, rollout_episodes=3, rollout_max_steps=6))
    with pytest.raises(ValueError, match="give --rollout-seed-start 400000"):
        read_rollout_frames(one_shot, same, DraftDataConfig(TASKS, rollout_episodes=3, rollout_seed_start=0))


def test_train_draft_on_a_rollouts_folder_records_it(policy_dirs, one_shot, tmp_path, capsys):
    out = tmp_path / "draft"
    args = ["train-draft", "--policy", policy_dirs[0], "--tasks", *TASKS, "--rollouts", str(one_shot), "--max-steps",
            "2", "--save-every", "2", "--eval-every", "2", "--batch-size", "4", "--validation-frames", "2"]  # fmt: skip
    assert main([*args, "--output-dir", str(out)]) == 0
    run = json.loads((out / "run.json").read_text())
    fingerprint = read_rollout_frames(one_shot, VLAPolicy.from_pretrained(policy_dirs[0]),
                                      DraftDataConfig(TASKS, 3, 5)).fingerprint  # fmt: skip
    assert run["paths"]["rollouts"] == str(one_shot) and run["settings"]["data"]["rollouts_fingerprint"] == fingerprint
    assert run["settings"]["data"]["rollout_episodes"] == 3 and run["settings"]["data"]["rollout_max_steps"] == 5
    card = (out / "README.md").read_text()
    assert f"`hf-specvla rollouts` folder `{one_shot}` (episodes fingerprint `{fingerprint}`)" in card
    # another policy with this folder: a usage error naming it, nothing written
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--policy", policy_dirs[1], "--output-dir", str(tmp_path / "other")])
    assert exit_info.value.code == 2 and "holds rollouts of another policy" in capsys.readouterr().err
    assert not (tmp_path / "other").exists()


@pytest.mark.parametrize(
    "flags, message",
    [
        (["--episodes-per-task", "0"], "--episodes-per-task: must be >= 1, got 0"),
        (["--workers", "0"], "--workers: must be >= 1, got 0"),
        (["--tasks", "bogus"], "unknown Meta-World task 'bogus'; valid: suites"),
        (["--method", "fast"], "'fast' relaxes acceptance"),
        (["--method", "head"], "'head' needs a draft head"),
        (["--method", "bogus"], "'bogus' is not a drafter"),
        (["--policy", "./no/such/policy"], "--policy: policy folder 'no/such/policy' does not exist"),
        (["--resume"], "no run to resume"),
    ],
)
def test_bad_input_is_a_usage_error_before_anything_loads(policy_dirs, tmp_path, capsys, flags, message):
    args = ["rollouts", "--policy", policy_dirs[0], "--output-dir", str(tmp_path / "out"), *flags]
    with pytest.raises(SystemExit) as exit_info:
        main(args)
    assert exit_info.value.code == 2 and message in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_train_draft_names_a_rollouts_folder_that_is_not_one(policy_dirs, tmp_path, capsys):
    for folder, message in ((tmp_path / "missing", "does not exist"), (tmp_path, "is not a rollouts folder")):
        with pytest.raises(SystemExit) as exit_info:
            main(["train-draft", "--policy", policy_dirs[0], "--rollouts", str(folder), "--output-dir",
                  str(tmp_path / "out")])  # fmt: skip
        assert exit_info.value.code == 2 and message in capsys.readouterr().err


def test_the_help_examples_parse():
    lines = rollouts_command.EXAMPLES.replace("\\\n", " ").splitlines()
    examples = [shlex.split(line) for line in lines if line.strip().startswith("hf-specvla")]
    assert [argv[1] for argv in examples] == ["rollouts", "rollouts", "train-draft"]
    for argv in examples:
        args = build_parser().parse_args(argv[1:])
        assert args.output_dir.startswith("runs/") and Path(args.policy).is_dir()


def test_rollout_config_validates():
    with pytest.raises(ValueError, match="RolloutConfig.threads must be >= 1, got 0"):
        RolloutConfig(threads=0)
    with pytest.raises(ValueError, match="RolloutConfig.max_episodes must be >= 1, got 0"):
        RolloutConfig(max_episodes=0)
    pairs = RolloutConfig(["reach", "push"], 2).pairs()
    assert pairs == [("reach-v3", 400000), ("push-v3", 400000), ("reach-v3", 400001), ("push-v3", 400001)]


def test_train_draft_holds_one_batch_of_images_and_one_episode_at_a_time(policy, one_shot, tmp_path, monkeypatch):
    """Memory that grows slowly with the frames: while the distillation set is built, the pixel values of only the
    batch being run are alive (before: every training frame's, built up front), and of the episode files only the one
    being read and the held-out frames' (before: every episode read)."""
    from hf_specvla.training import policy_draft, rollouts
    from hf_specvla.training.configuration import DraftTrainingConfig

    pixels, images, alive = [], [], {"pixel_values": 0, "episode_images": 0}
    preprocess, read, generate = policy.preprocess_images, rollouts.load_episode, policy.model.generate

    def counting_preprocess(images_):
        values = preprocess(images_)
        pixels.append(weakref.ref(values))
        return values

    def counting_read(path):
        arrays = read(path)
        image = arrays["image"]
        images.append(weakref.ref(image if image.base is None else image.base))  # the memory's owner (frames: views)
        return arrays

    def counting_generate(*args, **kwargs):
        for name, refs in (("pixel_values", pixels), ("episode_images", images)):
            alive[name] = max(alive[name], sum(ref() is not None for ref in refs))
        return generate(*args, **kwargs)

    monkeypatch.setattr(policy, "preprocess_images", counting_preprocess)
    monkeypatch.setattr(rollouts, "load_episode", counting_read)
    monkeypatch.setattr(policy.model, "generate", counting_generate)
    data = DraftDataConfig(TASKS, rollout_episodes=3, rollout_max_steps=5, validation_frames=2, prompt_batch_size=2)
    tokens = policy.config.action_tokens - 1
    training = DraftTrainingConfig(str(tmp_path / "draft"), max_steps=1, batch_size=4, save_every=0, eval_every=0,
                                   unroll_steps=tokens)  # fmt: skip
    policy_draft.train_policy_draft_head(policy, training, data, rollouts=one_shot, progress=False, head_version="v3",
                                         num_draft_tokens=tokens)  # fmt: skip
    batches = 2 * 2 * 5 // 2  # 2 tasks x 2 training episodes x 5 frames, 2 frames a batch
    assert len(pixels) > batches and alive["pixel_values"] == 1, (len(pixels), alive)
    # the episode being read (1), and the 2 held-out episodes the 2 validation frames are views of; 6 episodes in all
    assert alive["episode_images"] <= 3 < len(images), (len(images), alive)
    record = json.loads((tmp_path / "draft" / "distillation_set.json").read_text())
    assert record["data"]["examples"] == 20 and record["data"]["hidden_dtype"] == "float16"
    assert 0 < record["measured"]["hidden_bytes"] < 1e9 * record["measured"]["peak_rss_gb"]


def test_a_resumed_run_refuses_a_rebuilt_set_that_differs(policy_dirs, one_shot, tmp_path, capsys):
    """--resume rebuilds the distillation set from the recipe: the same set (its token ids' fingerprint, recorded in
    distillation_set.json), or a refusal naming what differs."""
    out = tmp_path / "draft"
    args = ["train-draft", "--policy", policy_dirs[0], "--tasks", *TASKS, "--rollouts", str(one_shot),
            "--save-every", "1", "--eval-every", "0", "--batch-size", "4", "--validation-frames", "2",
            "--output-dir", str(out)]  # fmt: skip
    assert main([*args, "--max-steps", "1"]) == 0
    assert main([*args, "--max-steps", "2", "--resume"]) == 0  # the same set rebuilt
    record = json.loads((out / "distillation_set.json").read_text())
    assert json.loads((out / "run.json").read_text())["settings"]["distillation"] == {"hidden_dtype": "float16"}
    record["data"]["token_ids"] = "0" * 16  # as if the frames or the policy's greedy tokens had changed
    (out / "distillation_set.json").write_text(json.dumps(record))
    with pytest.raises(SystemExit) as exit_info:
        main([*args, "--max-steps", "3", "--resume"])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "another distillation set than the one rebuilt" in err and "token_ids" in err
    assert latest_checkpoint(out).name == "checkpoint-2"
