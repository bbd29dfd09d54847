"""Meta-World env factory: real, upright images of the requested size; independent envs; seeded starts."""

import numpy as np
import pytest

pytest.importorskip("metaworld")

from hf_specvla.metaworld.env import (  # noqa: E402
    FREE_CAMERAS,
    MT10_TASKS,
    RENDER_REVISION,
    TASK_INSTRUCTIONS,
    EnvConfig,
    MetaWorldEnv,
    resolve_tasks,
)


def test_instructions_for_all_50_tasks():
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS

    assert set(TASK_INSTRUCTIONS) == set(ALL_V3_ENVIRONMENTS) and len(TASK_INSTRUCTIONS) == 50
    assert all(len(text.split()) >= 2 for text in TASK_INSTRUCTIONS.values())
    assert resolve_tasks("MT10") == list(MT10_TASKS) and len(resolve_tasks(["MT50"])) == 50
    assert resolve_tasks("push reach-v3") == ["push-v3", "reach-v3"]


def test_unknown_task_lists_valid_ones():
    with pytest.raises(ValueError, match="unknown Meta-World task 'fly-v3'.*push-v3"):
        resolve_tasks("fly-v3")
    with pytest.raises(ValueError, match="camera"):
        EnvConfig(camera="ceiling")


def test_images_are_real_upright_and_sized():
    with MetaWorldEnv("reach", EnvConfig(image_size=48)) as env:
        obs = env.reset(seed=0)
        image = obs["image"]
        assert image.shape == (48, 48, 3) and image.dtype == np.uint8
        assert image.std() > 10 and image.mean() > 20  # not black, not flat
        # upright: the plain grey wall is at the top, the table and robot base at the bottom
        top, bottom = image[:8], image[-8:]
        assert top.std() < bottom.std()
        assert obs["state"].shape == (4,) and obs["instruction"] == "reach the goal"
        raw = env._env.render()
        np.testing.assert_array_equal(raw[::-1, ::-1], image)


def test_workspace_camera_is_real_upright_and_closer():
    """The free ``workspace`` camera: real image of the requested size, not rotated, objects larger."""
    images = {}
    for camera in ("corner", "workspace"):
        with MetaWorldEnv("push", EnvConfig(image_size=48, camera=camera)) as env:
            images[camera] = env.reset(seed=0)["image"]
    image = images["workspace"]
    assert image.shape == (48, 48, 3) and image.dtype == np.uint8
    assert image.std() > 10 and image.mean() > 20
    # upright: the light floor beyond the table is at the top, the dark wooden table fills the bottom
    assert image[:8].mean() > image[-8:].mean() + 20
    # the green goal marker covers several times more pixels than from the far-away corner camera
    green = {cam: int(((im[..., 1] > 150) & (im[..., 0] < 100)).sum()) for cam, im in images.items()}
    assert green["workspace"] >= 3 * max(green["corner"], 1), green


def test_overview_camera_is_real_upright_and_shows_the_goal():
    """The free ``overview`` camera: the whole table from above the robot's right side, goal marker visible."""
    with MetaWorldEnv("push", EnvConfig(image_size=64, camera="overview")) as env:
        image = env.reset(seed=0)["image"]
    assert image.shape == (64, 64, 3) and image.dtype == np.uint8
    assert image.std() > 10 and image.mean() > 20
    # upright: the light floor beyond the table is at the top, the dark wooden table fills the bottom
    assert image[:6].mean() > image[-6:].mean() + 20
    # the green goal marker is a blob of several pixels, not a speck
    assert int(((image[..., 1] > 150) & (image[..., 0] < 100)).sum()) >= 5


def _marker_centre(image: np.ndarray, channel: int) -> np.ndarray:
    """Mean pixel (row, column) of a saturated red / green / blue marker."""
    others = [c for c in range(3) if c != channel]
    mask = (image[..., channel] > 150) & (image[..., others[0]] < 100) & (image[..., others[1]] < 100)
    assert mask.sum() >= 3, "no marker in the image"
    return np.argwhere(mask).mean(0)


@pytest.mark.parametrize(("task", "channel"), [("push", 1), ("pick-place", 2)])
def test_reset_frame_shows_the_goal_marker_at_the_goal(task, channel):
    """Meta-World's reset leaves the rendered goal marker at the XML's default until the first step: the first frame
    of every episode showed a goal that was not the task's. It must be where the next frames show it."""
    with MetaWorldEnv(task, EnvConfig(image_size=64, camera="overview")) as env:
        centres = []
        for seed in (100000, 100001):  # goals 18 cm apart in x
            first = _marker_centre(env.reset(seed)["image"], channel)
            after_a_step = _marker_centre(env.step(np.zeros(4))[0]["image"], channel)
            np.testing.assert_allclose(first, after_a_step, atol=0.5)
            centres.append(first)
    assert np.abs(centres[0] - centres[1]).max() > 5  # pixels: the two goals are seen apart
    assert EnvConfig().render_revision == RENDER_REVISION == 2


def test_a_step_without_its_image_is_the_same_step():
    """``step(render=False)`` skips only the camera: the simulation, and the frame rendered afterwards, are the same."""
    observations = []
    for render in (True, False):
        with MetaWorldEnv("push", EnvConfig(image_size=32, camera="overview")) as env:
            env.reset(seed=7)
            observation, *_ = env.step(env.expert_action(), render=render)
            observations.append((observation, env.render()))
    (rendered, after_rendered), (skipped, after_skipped) = observations
    assert skipped["image"] is None
    np.testing.assert_array_equal(rendered["state"], skipped["state"])
    np.testing.assert_array_equal(rendered["image"], after_skipped)
    np.testing.assert_array_equal(after_rendered, after_skipped)


def test_free_camera_settings_are_frozen():
    """Datasets and policies record only a free camera's name: its view must never move."""
    assert FREE_CAMERAS["workspace"] == {
        "lookat": (-0.03, 0.7, 0.08),
        "distance": 0.85,
        "azimuth": 150.0,
        "elevation": -45.0,
    }
    assert FREE_CAMERAS["overview"] == {
        "lookat": (0.0, 0.68, 0.08),
        "distance": 0.95,
        "azimuth": 180.0,
        "elevation": -45.0,
    }


def test_same_seed_same_start_and_varied_seeds():
    with MetaWorldEnv("push") as env:
        first = env.reset(seed=3)
        goal_a = env._raw_obs[-3:].copy()
        again = env.reset(seed=3)
        goal_b = env._raw_obs[-3:].copy()
        other = env.reset(seed=4)
        np.testing.assert_array_equal(first["image"], again["image"])
        np.testing.assert_array_equal(goal_a, goal_b)
        assert not np.array_equal(goal_a, env._raw_obs[-3:]) or not np.array_equal(first["image"], other["image"])


def test_hand_start_noise_varies_only_the_hand_start_reproducibly():
    with MetaWorldEnv("push") as env:
        plain = env.reset(seed=5)["state"]
        plain_goal, plain_puck = env._raw_obs[-3:].copy(), env._raw_obs[4:7].copy()
    with MetaWorldEnv("push", EnvConfig(hand_start_noise=0.1)) as env:
        starts = [env.reset(seed=seed)["state"] for seed in (5, 6, 5)]
        np.testing.assert_allclose(env._raw_obs[-3:], plain_goal, atol=1e-4)  # same objects and goal as without
        np.testing.assert_allclose(env._raw_obs[4:7], plain_puck, atol=1e-4)
    np.testing.assert_array_equal(starts[0], starts[2])  # same seed, same start
    assert not np.allclose(starts[0][:3], starts[1][:3])  # other seed, other hand start
    for start in starts:  # within the noise (plus the few mm the reset's settling leaves)
        assert np.all(np.abs(start[:3] - plain[:3]) <= 0.1 + 0.01)
    assert np.abs(starts[0][:3] - plain[:3]).max() > 0.01
    with pytest.raises(ValueError, match=r"hand_start_noise must be in \[0, 0.15\] metres, got -0.1"):
        EnvConfig(hand_start_noise=-0.1)


def test_several_envs_render_independently_and_close_cleanly():
    with MetaWorldEnv("drawer-open") as alone:
        expected = alone.reset(seed=1)["image"]
    a, b = MetaWorldEnv("drawer-open"), MetaWorldEnv("window-close")
    try:
        b.reset(seed=1)
        np.testing.assert_array_equal(a.reset(seed=1)["image"], expected)
        b.step(b.expert_action())
        image_a = a.render()
        b.close()
        after = a.render()  # closing one env never blanks another
        np.testing.assert_array_equal(after, image_a)
        assert after.mean() > 20
    finally:
        a.close()
        b.close()


def test_expert_solves_and_actions_are_clipped():
    with MetaWorldEnv("button-press-topdown") as env:
        env.reset(seed=0)
        for _ in range(300):
            action = env.expert_action()
            assert action.shape == (4,) and np.all(np.abs(action) <= 1.0)
            _, _, done, info = env.step(action)
            if done:
                break
        assert info["success"]
