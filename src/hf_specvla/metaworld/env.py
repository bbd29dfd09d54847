"""Meta-World v3 tasks as a vision-language-action environment: upright camera images, proprio state, an
instruction, reproducible varied starts, and the scripted expert.

Pitfalls handled here (see shared NOTES.md): the ``corner*`` cameras render upside down (rotated 180 degrees
back); default render quality costs 100+ ms a frame (multisampling, shadows and reflections are switched off:
~5x faster, still correct); an env garbage-collected while another one's GL context is current blanks that
context (envs are closed explicitly and every render makes its own context current first).

Example:
    ```python
    with MetaWorldEnv("push-v3", EnvConfig(image_size=64)) as env:
        obs = env.reset(seed=0)            # {"image": uint8 [64, 64, 3], "state": float32 [4], "instruction": str}
        obs, reward, done, info = env.step(env.expert_action())
    ```
"""

from __future__ import annotations

import gc
import os
import warnings
from dataclasses import dataclass, field

import numpy as np

#: The MT10 benchmark's tasks.
MT10_TASKS = (
    "reach-v3",
    "push-v3",
    "pick-place-v3",
    "door-open-v3",
    "drawer-open-v3",
    "drawer-close-v3",
    "button-press-topdown-v3",
    "peg-insert-side-v3",
    "window-open-v3",
    "window-close-v3",
)

#: A language instruction for each of the 50 v3 tasks.
TASK_INSTRUCTIONS = {
    "assembly-v3": "put the ring on the peg",
    "basketball-v3": "put the ball into the hoop",
    "bin-picking-v3": "move the cube from one bin to the other",
    "box-close-v3": "put the lid on the box",
    "button-press-topdown-v3": "press the button from the top",
    "button-press-topdown-wall-v3": "press the button from the top behind the wall",
    "button-press-v3": "press the button from the front",
    "button-press-wall-v3": "press the button behind the wall",
    "coffee-button-v3": "press the button on the coffee machine",
    "coffee-pull-v3": "pull the mug away from the coffee machine",
    "coffee-push-v3": "push the mug under the coffee machine",
    "dial-turn-v3": "turn the dial",
    "disassemble-v3": "pick the ring off the peg",
    "door-close-v3": "close the door",
    "door-lock-v3": "lock the door by turning the lock",
    "door-open-v3": "open the door",
    "door-unlock-v3": "unlock the door by turning the lock",
    "hand-insert-v3": "put your hand into the hole",
    "drawer-close-v3": "close the drawer",
    "drawer-open-v3": "open the drawer",
    "faucet-open-v3": "turn the faucet on",
    "faucet-close-v3": "turn the faucet off",
    "hammer-v3": "hammer the nail into the wall",
    "handle-press-side-v3": "press the handle down from the side",
    "handle-press-v3": "press the handle down",
    "handle-pull-side-v3": "pull the handle up from the side",
    "handle-pull-v3": "pull the handle up",
    "lever-pull-v3": "pull the lever up",
    "pick-place-wall-v3": "pick up the puck and place it at the goal behind the wall",
    "pick-out-of-hole-v3": "pick the peg out of the hole",
    "pick-place-v3": "pick up the puck and place it at the goal",
    "plate-slide-v3": "slide the plate into the goal",
    "plate-slide-side-v3": "slide the plate sideways into the goal",
    "plate-slide-back-v3": "slide the plate back out of the goal",
    "plate-slide-back-side-v3": "slide the plate sideways back out of the goal",
    "peg-insert-side-v3": "insert the peg into the hole from the side",
    "peg-unplug-side-v3": "unplug the peg sideways",
    "soccer-v3": "kick the ball into the goal",
    "stick-push-v3": "grab the stick and push the box with it",
    "stick-pull-v3": "grab the stick and pull the box with it",
    "push-v3": "push the puck to the goal",
    "push-wall-v3": "push the puck to the goal behind the wall",
    "push-back-v3": "push the puck back to the goal",
    "reach-v3": "reach the goal",
    "reach-wall-v3": "reach the goal behind the wall",
    "shelf-place-v3": "place the puck on the shelf",
    "sweep-into-v3": "sweep the puck into the hole",
    "sweep-v3": "sweep the puck off the table",
    "window-open-v3": "open the window",
    "window-close-v3": "close the window",
}

SUITES = {"MT10": MT10_TASKS, "MT50": tuple(TASK_INSTRUCTIONS)}
#: Free (not model-defined) cameras: MuJoCo ``mjvCamera`` settings, lookat in world metres, angles in degrees.
#: ``workspace`` looks at the table from the robot's front right, about twice as close as ``corner``, so that
#: a goal marker covers 7-10 pixels of a 64 px image (2-4 from ``corner``), but the hand is often at the image's
#: edge and hides a puck below it. ``overview`` looks down at 45 degrees from the robot's right side at the whole
#: table: hand, puck and goal are seen apart (a goal marker covers 6-8 pixels of a 64 px image).
#: Datasets and policies record only the camera's name, so an entry here is frozen once data exists for it:
#: a different view gets a new name (``workspace2``), never new numbers under an old one.
FREE_CAMERAS = {
    "workspace": {"lookat": (-0.03, 0.7, 0.08), "distance": 0.85, "azimuth": 150.0, "elevation": -45.0},
    "overview": {"lookat": (0.0, 0.68, 0.08), "distance": 0.95, "azimuth": 180.0, "elevation": -45.0},
}
CAMERAS = ("corner", "corner2", "corner3", "topview", "behindGripper", "gripperPOV", *FREE_CAMERAS)
ACTION_DIM = 4  # xyz delta + gripper
STATE_DIM = 4  # hand xyz + gripper opening
SCENE_STATE_DIM = 6  # object xyz + goal xyz (privileged: recorded for auxiliary training targets, never observed)
MAX_EPISODE_STEPS = 500  # Meta-World's max_path_length
#: which rendering of observations an env makes; recorded beside its settings, so that a run or dataset is never
#: extended with frames of another one. 1: the reset frame showed the goal marker where the task's XML puts it
#: (Meta-World moves it to the goal only at the first step); 2: the reset frame shows it at the goal
RENDER_REVISION = 2
MAX_HAND_START_NOISE = 0.15  # metres: an upper bound that keeps starts near the table's workspace (0.1 is tested)


def resolve_tasks(names: str | list[str] | tuple[str, ...]) -> list[str]:
    """Task names from a suite name ("MT10", "MT50"), a task name, or a list of either (``-v3`` optional).

    Raises:
        ValueError: naming the unknown task and listing the valid ones.
    """
    if isinstance(names, str):
        names = [n for n in names.replace(",", " ").split() if n]
    tasks: list[str] = []
    for name in names:
        if name.upper() in SUITES:
            tasks.extend(SUITES[name.upper()])
            continue
        task = name if name.endswith("-v3") else f"{name}-v3"
        if task not in TASK_INSTRUCTIONS:
            raise ValueError(
                f"unknown Meta-World task {name!r}; valid: suites {sorted(SUITES)} or one of "
                f"{', '.join(sorted(TASK_INSTRUCTIONS))}"
            )
        tasks.append(task)
    return list(dict.fromkeys(tasks))


@dataclass
class EnvConfig:
    """How observations are made.

    Args:
        image_size: side of the square camera image (pixels).
        camera: a Meta-World camera (``corner*`` images are rotated upright) or one of ``FREE_CAMERAS``.
        max_episode_steps: steps before an episode is cut (at most Meta-World's 500).
        hand_start_noise: half-width (metres) of a uniform offset, per axis, added to the task's hand start
            position at each reset, drawn from the reset seed. Meta-World starts the hand at one fixed point;
            demonstrations from varied starts stop the hand position from giving away where the expert is
            heading (a cloned policy then reads the goal from the image instead of copying the state's drift).
            0 gives Meta-World's own starts (used for evaluation).

    ``render_revision`` is not an argument: it is [`RENDER_REVISION`], recorded with the other settings.
    """

    image_size: int = 64
    camera: str = "corner"
    max_episode_steps: int = MAX_EPISODE_STEPS
    hand_start_noise: float = 0.0
    render_revision: int = field(default=RENDER_REVISION, init=False)  # recorded with the settings, not chosen

    def __post_init__(self):
        if self.camera not in CAMERAS:
            raise ValueError(f"camera must be one of {CAMERAS}, got {self.camera!r}")
        if not 16 <= self.image_size <= 512:
            raise ValueError(f"image_size must be in [16, 512] pixels, got {self.image_size}")
        if not 1 <= self.max_episode_steps <= MAX_EPISODE_STEPS:
            raise ValueError(f"max_episode_steps must be in [1, {MAX_EPISODE_STEPS}], got {self.max_episode_steps}")
        if not 0.0 <= self.hand_start_noise <= MAX_HAND_START_NOISE:
            raise ValueError(
                f"hand_start_noise must be in [0, {MAX_HAND_START_NOISE}] metres, got {self.hand_start_noise}"
            )

    def check_renders_for(self, policy_config) -> None:
        """Raises ValueError when this env renders other images than the ones a policy (its ``VLAPolicyConfig``:
        ``image_size``, ``camera``) was trained on. The simulator checks the policy, not the other way round."""
        if self.image_size != policy_config.image_size:
            raise ValueError(f"the policy reads {policy_config.image_size}px images, the env makes {self.image_size}px")
        if self.camera != policy_config.camera:
            raise ValueError(
                f"the policy was trained on camera {policy_config.camera!r}, the env renders {self.camera!r}; "
                f"use EnvConfig(camera={policy_config.camera!r})"
            )


class MetaWorldEnv:
    """One Meta-World v3 task with image observations. Use as a context manager or call ``close()``.

    Observations are dicts: ``image`` uint8 ``[S, S, 3]`` (upright), ``state`` float32 ``[4]`` (hand xyz,
    gripper opening), ``instruction`` str. ``reset(seed)`` draws the object / goal positions from ``seed``:
    the same seed gives the same start, different seeds give varied starts.
    """

    def __init__(self, task: str, config: EnvConfig | None = None):
        os.environ.setdefault("MUJOCO_GL", "egl")
        (self.task,) = resolve_tasks([task])
        self.config = config or EnvConfig()
        from metaworld.env_dict import ALL_V3_ENVIRONMENTS
        from metaworld.policies import ENV_POLICY_MAP

        size, camera = self.config.image_size, self.config.camera
        view = {"camera_id": -1} if camera in FREE_CAMERAS else {"camera_name": camera}
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            env = ALL_V3_ENVIRONMENTS[self.task](render_mode="rgb_array", width=size, height=size, **view)
        if camera in FREE_CAMERAS:  # applied to the viewer's camera when the renderer makes it (first render)
            env.mujoco_renderer.default_cam_config = {
                key: np.asarray(value) if isinstance(value, tuple) else value
                for key, value in FREE_CAMERAS[camera].items()
            }
        env.seeded_rand_vec = True  # starts are drawn from env.np_random, which reset(seed) seeds
        env._set_task_called = True
        env._partially_observable = False  # the scripted expert reads the goal from the raw observation
        # step() clips observations to this cached space, computed while the goal was hidden (all zeros)
        env.__dict__.pop("sawyer_observation_space", None)
        env.model.vis.quality.offsamples = 0  # no multisampling: must be set before the first render
        self._env = env
        self._hand_start = np.array(env.hand_init_pos, dtype=np.float64)
        self._expert = ENV_POLICY_MAP[self.task]()
        self._raw_obs: np.ndarray | None = None
        self._fast_render_set = False
        self.steps = 0

    # ----------------------------------------------------------------------------- observations
    @property
    def instruction(self) -> str:
        return TASK_INSTRUCTIONS[self.task]

    def render(self) -> np.ndarray:
        """The current camera image, uint8 ``[S, S, 3]``, upright."""
        renderer = self._env.mujoco_renderer
        if renderer.viewer is not None:
            renderer.viewer.make_context_current()  # several live envs: render into our own context
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            image = self._env.render()
        if not self._fast_render_set:  # the scene exists only after the first render
            import mujoco

            flags = renderer.viewer.scn.flags
            flags[mujoco.mjtRndFlag.mjRND_SHADOW] = 0
            flags[mujoco.mjtRndFlag.mjRND_REFLECTION] = 0
            self._fast_render_set = True
            image = self._env.render()
        if self.config.camera.startswith("corner"):
            image = image[::-1, ::-1]  # these cameras come out rotated by 180 degrees
        return np.ascontiguousarray(image)

    def _observation(self, render: bool = True) -> dict:
        state = np.asarray(self._raw_obs[:STATE_DIM], dtype=np.float32)
        return {"image": self.render() if render else None, "state": state, "instruction": self.instruction}

    # ----------------------------------------------------------------------------- control
    def reset(self, seed: int) -> dict:
        """Starts an episode whose object and goal positions are drawn from ``seed``."""
        self._env.seed(int(seed))
        noise = self.config.hand_start_noise
        if noise > 0:  # its own stream: the objects and goal are the same as without the noise
            offset = np.random.default_rng([int(seed), 1]).uniform(-noise, noise, size=3)
            self._env.hand_init_pos = self._hand_start + offset
        self._env._freeze_rand_vec = False  # draw a new start vector during this reset ...
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self._raw_obs, _ = self._env.reset()
        # Meta-World's reset moves the goal site in the model but leaves the rendered marker where the XML put it
        # until the first step() re-places it: place it now, as step() does, so the first frame shows the goal
        for site in self._env._target_site_config:
            self._env._set_pos_site(*site)
        self._env._freeze_rand_vec = True  # ... and keep it: some tasks re-read it while stepping
        self.steps = 0
        return self._observation()

    def step(self, action, render: bool = True) -> tuple[dict, float, bool, dict]:
        """Applies a 4-dim action (clipped to [-1, 1]). ``render=False`` skips the camera image (``image`` is None;
        rendering is most of a step's cost): for steps whose frame is not used, `render()` gives it later.

        Returns:
            (observation, reward, done, info) with ``info["success"]`` (bool) and ``info["truncated"]`` (the
            step limit was reached). ``done`` is success or truncation.
        """
        if self._raw_obs is None:
            raise RuntimeError("call reset(seed) before step()")
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(ACTION_DIM), -1.0, 1.0)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self._raw_obs, reward, _, _, info = self._env.step(action)
        self.steps += 1
        success = bool(info.get("success", 0.0) > 0.5)
        truncated = self.steps >= self.config.max_episode_steps
        observation = self._observation(render)
        return observation, float(reward), success or truncated, {"success": success, "truncated": truncated}

    def scene_state(self) -> np.ndarray:
        """Where the task's object and goal are, float32 ``[6]`` (object xyz, goal xyz) from the simulator.

        Privileged information, not an observation: a policy never gets it. Demonstrations record it so that
        training can ask the model to locate the object and the goal in the image (an auxiliary target).
        The object is the task's first one (the puck, the button, the drawer or window handle, the peg).
        """
        if self._raw_obs is None:
            raise RuntimeError("call reset(seed) before scene_state()")
        raw = np.asarray(self._raw_obs, dtype=np.float32)
        return np.concatenate([raw[4:7], raw[-3:]])

    def expert_action(self) -> np.ndarray:
        """The scripted expert's action for the current state, clipped to [-1, 1] (raw ones reach ~24)."""
        if self._raw_obs is None:
            raise RuntimeError("call reset(seed) before expert_action()")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # "Constant(s) may be too high": the clip below is the answer
            action = self._expert.get_action(self._raw_obs)
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    # ----------------------------------------------------------------------------- lifetime
    def close(self) -> None:
        """Frees the GL context now (not whenever the garbage collector gets to it)."""
        if self._env is not None:
            self._env.close()
            self._env = None
            gc.collect()

    def __enter__(self) -> MetaWorldEnv:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
