"""Demonstration datasets: Parquet round trip, resume without duplicates, statistics, bad input."""

import json

import numpy as np
import pytest

pytest.importorskip("metaworld")

from hf_specvla import ActionNormalizer  # noqa: E402
from hf_specvla.metaworld.demonstrations import (  # noqa: E402
    collect_demonstrations,
    collected_seeds,
    episode_path,
    load_demonstrations,
    read_scene_stats,
    read_stats,
    record_episode,
)
from hf_specvla.metaworld.env import EnvConfig, MetaWorldEnv  # noqa: E402


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("demos")
    collect_demonstrations(root, "reach", 2, EnvConfig(image_size=32), progress=False)
    return root


def test_round_trip_with_common_tools(dataset):
    import pyarrow.parquet as pq

    table = pq.read_table(next((dataset / "data" / "reach-v3").glob("*.parquet"))).to_pydict()
    assert list(table) == [
        "episode_index", "step_index", "task", "instruction", "seed", "image", "state", "action", "success",
        "scene_state",
    ]  # fmt: skip
    assert table["success"][-1] and table["step_index"] == list(range(len(table["step_index"])))
    demos = load_demonstrations(dataset, progress=False)
    assert demos.images.shape[1:] == (32, 32, 3) and demos.images.dtype == np.uint8
    assert len(demos) == len(demos.actions) == len(demos.states) == len(demos.tasks)
    assert np.all(np.abs(demos.actions) <= 1.0)
    assert len(np.unique(demos.episode_index)) == 2
    info = json.loads((dataset / "meta" / "info.json").read_text())
    assert info["image_size"] == 32 and info["action_dim"] == 4


def test_frames_stay_encoded_until_read_and_read_as_the_parquet_images(dataset):
    """Loaded frames are held PNG-encoded (a fraction of the decoded bytes) and every way of indexing them gives the
    decoded images of the Parquet files, in order."""
    import pyarrow.parquet as pq

    from hf_specvla.metaworld.demonstrations import EncodedFrames, decode_png

    demos = load_demonstrations(dataset, progress=False)
    decoded = np.stack([
        decode_png(b) for f in sorted((dataset / "data" / "reach-v3").glob("*.parquet"))
        for b in pq.read_table(f).to_pydict()["image"]
    ])  # fmt: skip
    frames = demos.images
    assert isinstance(frames, EncodedFrames) and len(frames) == len(decoded) == len(demos)
    assert frames.nbytes < decoded.nbytes / 2
    np.testing.assert_array_equal(frames[3], decoded[3])
    np.testing.assert_array_equal(frames[np.int64(-1)], decoded[-1])
    np.testing.assert_array_equal(frames[2:7:2], decoded[2:7:2])
    np.testing.assert_array_equal(frames[[5, 0, 5]], decoded[[5, 0, 5]])
    np.testing.assert_array_equal(frames[np.array([1, 4])], decoded[[1, 4]])
    np.testing.assert_array_equal(np.asarray(frames), decoded)
    assert frames[10:10].shape == (0, 32, 32, 3)
    with pytest.raises(ValueError, match="at least one frame"):
        EncodedFrames([])


def test_resume_adds_only_missing_episodes(dataset):
    before = collected_seeds(dataset, "reach-v3")
    summary = collect_demonstrations(dataset, "reach", 3, EnvConfig(image_size=32), progress=False)
    after = collected_seeds(dataset, "reach-v3")
    assert summary.episodes_written == 1 and after[: len(before)] == before and len(after) == len(set(after)) == 3
    # an interrupted write leaves a .tmp file, which is never read as an episode
    (dataset / "data" / "reach-v3" / "episode_000099.parquet.tmp").write_bytes(b"partial")
    assert collected_seeds(dataset, "reach-v3") == after
    assert len(np.unique(load_demonstrations(dataset, progress=False).episode_index)) == 3


def test_scene_state_is_where_the_object_and_goal_are(dataset):
    """The privileged scene state of every frame: reach's goal does not move during an episode, and the first
    frame's values are the ones the env gives after ``reset`` of the same seed."""
    demos = load_demonstrations(dataset, progress=False)
    assert demos.scene_states.shape == (len(demos), 6) and demos.scene_states.dtype == np.float32
    for episode in np.unique(demos.episode_index):
        goals = demos.scene_states[demos.episode_index == episode, 3:]
        np.testing.assert_array_equal(goals, np.broadcast_to(goals[0], goals.shape))
    seed = int(demos.episode_index[0] % 1_000_000)
    with MetaWorldEnv("reach", EnvConfig(image_size=32)) as env:
        env.reset(seed)
        np.testing.assert_allclose(demos.scene_states[0], env.scene_state(), atol=1e-6)
    scene_norm = read_scene_stats(dataset)
    assert scene_norm.action_dim == 6 and np.all(scene_norm.q01 <= scene_norm.q99)


def test_episodes_without_scene_state_are_read_and_refused_for_scene_targets(dataset, tmp_path):
    """A dataset collected before the scene_state column existed still loads; scene targets are refused."""
    import shutil

    import pyarrow.parquet as pq

    old = tmp_path / "old"
    shutil.copytree(dataset, old)
    for file in (old / "data").glob("*/*.parquet"):
        pq.write_table(pq.read_table(file).drop_columns(["scene_state"]), file)
    demos = load_demonstrations(old, progress=False)
    assert demos.scene_states is None and len(demos) == len(load_demonstrations(dataset, progress=False))
    with pytest.raises(ValueError, match="without the scene_state column"):
        read_scene_stats([old, dataset])


def test_statistics(dataset):
    action_norm, state_norm = read_stats(dataset)
    assert action_norm.action_dim == 4 and state_norm.action_dim == 4
    assert list(action_norm.mask) == [True, True, True, False]  # the gripper is not rescaled
    assert np.all(action_norm.q01 <= action_norm.q99)


def test_mixing_settings_is_refused(dataset):
    with pytest.raises(ValueError, match="image_size=32"):
        collect_demonstrations(dataset, "reach", 3, EnvConfig(image_size=48), progress=False)
    with pytest.raises(ValueError, match="hand_start_noise=0.0, but this collection uses 0.1"):
        collect_demonstrations(dataset, "reach", 3, EnvConfig(image_size=32, hand_start_noise=0.1), progress=False)


def test_a_dataset_of_an_older_rendering_is_not_extended(dataset, tmp_path):
    """A dataset recorded before ``render_revision`` existed has revision-1 first frames (a stale goal marker): new
    episodes of revision 2 go into another folder, the old dataset stays as it is and still loads."""
    import shutil

    old = tmp_path / "old"
    shutil.copytree(dataset, old)
    info = json.loads((old / "meta" / "info.json").read_text())
    assert info["render_revision"] == 2
    del info["render_revision"]
    (old / "meta" / "info.json").write_text(json.dumps(info))
    before = sorted(p.name for p in (old / "data" / "reach-v3").glob("*.parquet"))
    with pytest.raises(ValueError, match="render_revision=1, but this collection uses 2"):
        collect_demonstrations(old, "reach", 3, EnvConfig(image_size=32), progress=False)
    assert sorted(p.name for p in (old / "data" / "reach-v3").glob("*.parquet")) == before
    assert len(set(load_demonstrations(old, progress=False).episode_index)) == len(before)


def test_missing_dataset(tmp_path):
    with pytest.raises(FileNotFoundError, match="hf-specvla collect"):
        load_demonstrations(tmp_path)


@pytest.fixture(scope="module")
def noisy_dataset(tmp_path_factory):
    root = tmp_path_factory.mktemp("noisy_demos")
    collect_demonstrations(root, "reach", 2, EnvConfig(image_size=32), progress=False, action_noise=0.3)
    return root


def test_action_noise_perturbs_the_path_but_records_clean_actions(dataset, noisy_dataset):
    from hf_specvla.metaworld.env import MetaWorldEnv

    clean, noisy = load_demonstrations(dataset, progress=False), load_demonstrations(noisy_dataset, progress=False)
    assert json.loads((noisy_dataset / "meta" / "info.json").read_text())["action_noise"] == 0.3
    assert np.allclose(clean.states[0], noisy.states[0])  # same seed, same start ...
    first = noisy.episode_index == noisy.episode_index[0]
    n = min(first.sum(), (clean.episode_index == clean.episode_index[0]).sum())
    assert not np.allclose(clean.states[:n], noisy.states[:n])  # ... then the executed noise moves the hand
    # every recorded action is the expert's (clean) action in the recorded state, not the executed one
    with MetaWorldEnv("reach-v3", EnvConfig(image_size=32)) as env:
        env.reset(int(noisy.episode_index[0] % 1_000_000))
        expert_first = env.expert_action()
    assert np.allclose(noisy.actions[0], expert_first)
    assert np.all(np.abs(noisy.actions) <= 1.0)


def test_extending_with_other_noise_is_refused(noisy_dataset):
    with pytest.raises(ValueError, match="action_noise=0.3"):
        collect_demonstrations(noisy_dataset, "reach", 3, EnvConfig(image_size=32), progress=False)
    with pytest.raises(ValueError, match=r"action_noise must be in \[0, 1\]"):
        collect_demonstrations(noisy_dataset, "reach", 3, EnvConfig(image_size=32), progress=False, action_noise=-1)


def test_several_folders_load_together(dataset, noisy_dataset, tmp_path):
    single = [load_demonstrations(r, progress=False) for r in (dataset, noisy_dataset)]
    both = load_demonstrations([dataset, noisy_dataset], progress=False)
    assert len(both) == sum(len(d) for d in single)
    # the same seeds in two folders are different episodes: ids stay unique
    assert len(np.unique(both.episode_index)) == sum(len(np.unique(d.episode_index)) for d in single)
    action_norm, _ = read_stats([dataset, noisy_dataset])
    assert np.all(action_norm.q01 <= action_norm.q99)
    other = tmp_path / "other"
    collect_demonstrations(other, "reach", 1, EnvConfig(image_size=48), progress=False)
    with pytest.raises(ValueError, match="image_size=48"):
        load_demonstrations([dataset, other], progress=False)


# ----------------------------------------------------------------------------- policy-driven (DAgger) collection
@pytest.fixture(scope="module")
def tiny_policy():
    from hf_specvla.metaworld.env import TASK_INSTRUCTIONS
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig

    action_norm = ActionNormalizer(q01=[-1.0] * 4, q99=[1.0] * 4, mask=[True, True, True, False])
    state_norm = ActionNormalizer(q01=[-0.5, 0.3, 0.0, 0.0], q99=[0.5, 0.9, 0.3, 1.0])
    config = VLAPolicyConfig(image_size=32, vision_hidden_size=32, vision_layers=1, text_hidden_size=64,
                             text_layers=1, text_heads=4)  # fmt: skip
    return VLAPolicy.build(list(TASK_INSTRUCTIONS.values()), action_norm, state_norm, config, seed=0)


SHORT = EnvConfig(image_size=32, max_episode_steps=12)


def _replay(rows: dict, choose_action) -> None:
    """Replays an episode from its seed: every recorded state must come back and every recorded action must be the
    expert's in that state; ``choose_action(obs, expert_action)`` is what the collection executed."""
    from hf_specvla.metaworld.env import MetaWorldEnv

    with MetaWorldEnv(rows["task"][0], SHORT) as env:
        obs = env.reset(rows["seed"][0])
        for state, action in zip(rows["state"], rows["action"]):
            assert np.allclose(obs["state"], state, atol=1e-6)
            expert = env.expert_action()
            assert np.allclose(action, expert, atol=1e-6)
            obs, *_ = env.step(choose_action(obs, expert))


def test_policy_driven_episodes_keep_failures_and_label_with_the_expert(tiny_policy, tmp_path):
    import pyarrow.parquet as pq

    summary = collect_demonstrations(tmp_path, "reach", 2, SHORT, seed_start=7, progress=False, policy=tiny_policy)
    assert summary.episodes_written == 2 and summary.expert_failures == 0
    assert collected_seeds(tmp_path, "reach-v3") == [7, 8]  # every seed gives an episode
    rows = pq.read_table(episode_path(tmp_path, "reach-v3", 7)).to_pydict()
    assert len(rows["step_index"]) == 12 and not rows["success"][-1]  # a random policy fails: kept all the same
    # the policy drove (replaying its actions reproduces the states) and the expert labelled every state
    _replay(rows, lambda obs, expert: tiny_policy.predict_action(obs["image"], obs["instruction"], obs["state"]))
    info = json.loads((tmp_path / "meta" / "info.json").read_text())
    assert info["policy"] == "in-memory" and info["expert_mix"] == 0.0 and info["max_episode_steps"] == 12
    assert summary.driven_successes == 0


def test_expert_mix_one_is_the_expert_episode(tiny_policy):
    from hf_specvla.metaworld.env import MetaWorldEnv

    with MetaWorldEnv("reach-v3", SHORT) as env:
        rows = record_episode(env, 3, policy=tiny_policy, expert_mix=1.0)
    _replay(rows, lambda obs, expert: expert)


def test_policy_driven_bad_input(tiny_policy, tmp_path):
    with pytest.raises(ValueError, match=r"expert_mix must be in \[0, 1\].*got 1.5"):
        collect_demonstrations(tmp_path, "reach", 1, SHORT, progress=False, policy=tiny_policy, expert_mix=1.5)
    with pytest.raises(ValueError, match="the policy reads 32px images, the env makes 48px"):
        collect_demonstrations(tmp_path, "reach", 1, EnvConfig(image_size=48), progress=False, policy=tiny_policy)
    collect_demonstrations(tmp_path, "reach", 1, SHORT, progress=False, policy=tiny_policy, expert_mix=0.5)
    with pytest.raises(ValueError, match="expert_mix=0.5, but this collection uses 0.25"):
        collect_demonstrations(tmp_path, "reach", 2, SHORT, progress=False, policy=tiny_policy, expert_mix=0.25)
    with pytest.raises(ValueError, match="policy_weights='[0-9a-f]{16}', but this collection uses None"):
        collect_demonstrations(tmp_path, "reach", 2, SHORT, progress=False)
    # another policy is refused even where both are "in-memory" (identity by weights, not by path)
    from hf_specvla.policies import VLAPolicy

    other = VLAPolicy.build(["reach the goal"], tiny_policy.action_normalizer, tiny_policy.state_normalizer,
                            tiny_policy.config, seed=99)  # fmt: skip
    with pytest.raises(ValueError, match="policy_weights="):
        collect_demonstrations(tmp_path, "reach", 2, SHORT, progress=False, policy=other, expert_mix=0.5)


def test_a_bad_collection_writes_nothing(tmp_path):
    """Regression (reliability issue, case 8): `collect --seed-start -5` used to write meta/info.json first, and the
    half-made folder then refused the corrected command."""
    folder = tmp_path / "demos"
    with pytest.raises(ValueError, match="seed_start must be >= 0.*got -5"):
        collect_demonstrations(folder, "reach", 1, EnvConfig(image_size=32), seed_start=-5, progress=False)
    assert not folder.exists()
    from hf_specvla.cli import main

    with pytest.raises(SystemExit) as exit_info:
        main(["collect", "--tasks", "reach", "--seed-start", "-5", "--output-dir", str(folder)])
    assert exit_info.value.code == 2 and not folder.exists()


def test_a_torn_stats_file_is_recomputed(dataset, caplog):
    """Regression (reliability issue, case 9): a torn meta/stats.json (a crash mid-write) stopped everything with a
    raw JSONDecodeError; the statistics are derived data, so they are recomputed from the episodes."""
    import logging

    from hf_specvla.metaworld.demonstrations import dataset_stats

    path = dataset / "meta" / "stats.json"
    good = path.read_text()
    expected = dataset_stats(dataset).action.to_dict()
    path.write_text(good[: len(good) // 2])
    with caplog.at_level(logging.WARNING):
        assert dataset_stats(dataset).action.to_dict() == expected
    assert "damaged" in caplog.text and json.loads(path.read_text())  # and the file is whole again


def test_a_batch_larger_than_the_training_frames_is_a_clear_error(dataset, tmp_path):
    """Regression (reliability issue, case 6): `train-vla --batch-size` larger than the frames crashed with a
    ZeroDivisionError."""
    from hf_specvla.metaworld.demonstrations import dataset_stats
    from hf_specvla.policies import VLAPolicy, VLAPolicyConfig
    from hf_specvla.training.behaviour_cloning import VLATrainingConfig, train_vla

    demos = load_demonstrations(dataset, progress=False)
    stats = dataset_stats(dataset)
    policy = VLAPolicy.build(["reach the goal"], stats.action, stats.state,
                             VLAPolicyConfig(image_size=32, vision_hidden_size=32, vision_layers=1, text_hidden_size=64,
                                             text_layers=1, text_heads=4))  # fmt: skip
    config = VLATrainingConfig(str(tmp_path / "out"), max_steps=1, batch_size=10_000, val_episodes=1)
    with pytest.raises(ValueError, match="batch_size=10000 is larger than the .* training frames"):
        train_vla(policy, demos, config, progress=False)
    assert not (tmp_path / "out").exists()  # nothing written


@pytest.mark.rollouts  # ~35 s: ten simulator episodes twice
def test_vectorised_evaluation_gives_the_one_at_a_time_episodes(tiny_policy, tmp_path):
    """Episodes run in lockstep (one batched policy call per step) are the episodes run one at a time (greedy)."""
    from hf_specvla.metaworld.evaluation import evaluate, rollout_batch

    def episodes(folder):
        lines = (folder / "episodes.jsonl").read_text().splitlines()
        return sorted((json.loads(line) for line in lines), key=lambda e: (e["task"], e["seed"]))

    settings = dict(env_config=SHORT, seed_start=100, progress=False)
    evaluate(tiny_policy, ["reach", "push"], 3, tmp_path / "one", **settings)
    evaluate(tiny_policy, ["reach", "push"], 3, tmp_path / "four", num_envs=4, **settings)  # chunks mix tasks
    one, four = episodes(tmp_path / "one"), episodes(tmp_path / "four")
    assert [(e["task"], e["seed"], e["success"], e["length"]) for e in one] == [
        (e["task"], e["seed"], e["success"], e["length"]) for e in four
    ]
    with pytest.raises(ValueError, match="num_envs must be an int >= 1"):
        evaluate(tiny_policy, "reach", 1, tmp_path / "bad", num_envs=0, **settings)
    from hf_specvla.metaworld.env import MetaWorldEnv
    from hf_specvla.metaworld.evaluation import rollout

    # where each episode ends up (the hand's state after its last action): the same actions were taken
    tasks, seeds = ["reach", "push", "reach"], [5, 6, 7]
    envs = [MetaWorldEnv(task, SHORT) for task in tasks]
    try:
        alone = [rollout(tiny_policy, env, seed) for env, seed in zip(envs, seeds)]
        alone_states = [env._observation()["state"] for env in envs]
        batched = rollout_batch(tiny_policy, envs, seeds)
        assert [(r.success, r.length) for r in alone] == [(r.success, r.length) for r in batched]
        for env, state in zip(envs, alone_states):
            np.testing.assert_array_equal(env._observation()["state"], state)
        with pytest.raises(ValueError, match="distinct environment objects"):
            rollout_batch(tiny_policy, [envs[0], envs[0]], [1, 2])
    finally:
        for env in envs:
            env.close()


def test_train_vla_on_fewer_frames_than_a_batch_is_refused_before_the_policy_is_built(dataset, tmp_path, capsys,
                                                                                      monkeypatch):  # fmt: skip
    """It was a traceback from inside the training (issue 76)."""
    from hf_specvla.cli import main
    from hf_specvla.policies import VLAPolicy

    monkeypatch.setattr(VLAPolicy, "build", classmethod(lambda *a, **k: pytest.fail("the policy was built")))
    with pytest.raises(SystemExit) as exit_info:
        main(["train-vla", "--data", str(dataset), "--batch-size", "100000", "--output-dir", str(tmp_path / "p")])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2 and "Traceback" not in err
    assert "batch_size=100000 is larger than the" in err and "use --batch-size" in err
    assert not (tmp_path / "p" / "run.json").exists()
