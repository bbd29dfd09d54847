"""How precisely can a policy's vision tower locate the task's object, goal and hand? The "What the images hold"
table of docs/metaworld.md (policy v3).

Renders scenes from the policy's camera (a reset with the hand start varied by up to 0.1 m, then 1-39 expert steps;
one frame per scene), reads the policy's own scene tokens on the held-out ones (a policy trained with scene targets),
then trains the vision tower with a linear readout on its patch features to the simulator's object, goal and hand
xyz (the tower trained along, as a policy trains it), and prints the held-out errors per task in cm.
``--second-view front`` stacks a low view from the table's far end under the policy's view (each squeezed to half
height: the same image size, so the same image tokens and cost per call). A colour-centroid fit (a quadratic in the
goal marker's pixel centre) gives what the pixels hold for the goals whose marker has a colour of its own; always
guessing the training scenes' mean position gives what knowing nothing scores.

    python examples/metaworld/localization_probe.py --policy runs/v3/mt10_vla3/checkpoint-3000/policy
    python examples/metaworld/localization_probe.py --policy runs/v3/mt10_vla3/checkpoint-3000/policy \\
        --second-view front --scenes 1500 --steps 3000

``--decoder-steps N`` asks whether the policy's decoder can read what the tower holds: a copy of the policy, its
tower held fixed, trains projector and decoder for N steps to emit the 6 scene tokens right after the prompt (no
action tokens before them to lean on), and its held-out errors get a column:

    python examples/metaworld/localization_probe.py --policy runs/v3/tower_pretrained --scenes 1500 --steps 1 \
        --decoder-steps 600

``--save-policy DIR`` keeps the result: the policy with its vision tower trained on the scenes (a start for
``hf-specvla train-vla --init-from DIR``: a tower pretrained to locate what the tasks need), the arguments in
``DIR/scene_pretraining.json``:

    python examples/metaworld/localization_probe.py --policy runs/v3/mt10_vla3/checkpoint-3000/policy \\
        --tasks MT10 --scenes 600 --steps 3000 --save-policy runs/v3/tower_pretrained
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
import torch

#: a low view from the table's far end, aimed where the overview camera looks: it sees heights the overview cannot
FRONT_VIEW = {"azimuth": 0.0, "elevation": -20.0, "distance": 1.0}
#: goal marker colours (the channel that is high while the other two are low); reach's red marker is the arm's colour
MARKER_CHANNEL = {"push-v3": 1, "pick-place-v3": 2}
TRAIN_SEED, VALIDATION_SEED = 300_000, 400_000


def half_height(view: np.ndarray) -> np.ndarray:
    """``[S, S, 3]`` -> ``[S / 2, S, 3]``: each pair of rows averaged."""
    return ((view[0::2].astype(np.uint16) + view[1::2]) // 2).astype(np.uint8)


def render_scenes(task: str, count: int, seed_start: int, image_size: int, camera: str, second_view: str | None):
    """``count`` scenes: images uint8 ``[N, S, S, 3]`` (the second view stacked under the first when asked),
    targets float32 ``[N, 9]`` (object xyz, goal xyz, hand xyz), proprio states float32 ``[N, 4]``."""
    from hf_specvla.metaworld.env import EnvConfig, MetaWorldEnv

    rng = np.random.default_rng(seed_start)
    images, targets, states = [], [], []
    with MetaWorldEnv(task, EnvConfig(image_size=image_size, camera=camera, hand_start_noise=0.1)) as env:
        for seed in range(seed_start, seed_start + count):
            env.reset(seed)
            for _ in range(int(rng.integers(1, 40))):
                observation, *_ = env.step(env.expert_action(), render=False)
            image = env.render()
            if second_view:
                camera_now = env._env.mujoco_renderer.viewer.cam
                kept = {key: getattr(camera_now, key) for key in FRONT_VIEW}
                for key, value in FRONT_VIEW.items():
                    setattr(camera_now, key, value)
                other = env.render()
                for key, value in kept.items():
                    setattr(camera_now, key, value)
                image = np.concatenate([half_height(image), half_height(other)], 0)
            images.append(image)
            targets.append(np.concatenate([env.scene_state(), observation["state"][:3]]))
            states.append(observation["state"])
    return np.stack(images), np.stack(targets).astype(np.float32), np.stack(states)


@torch.no_grad()
def policy_scene_errors(policy, task: str, images: np.ndarray, states: np.ndarray, scenes: np.ndarray) -> np.ndarray:
    """Mean error (m) of the policy's own scene tokens (generated after its action tokens, greedy) ``[2]``: object,
    goal. Only for a policy trained with scene targets, on its own camera's images."""
    from hf_specvla.metaworld.env import TASK_INSTRUCTIONS

    action_tokens, scene_dim = policy.config.action_tokens, policy.config.scene_state_dim
    errors = []
    for image, state, scene in zip(images, states, scenes):
        prompt = torch.tensor([policy.prompt_ids(TASK_INSTRUCTIONS[task], state)])
        output = policy.model.generate(input_ids=prompt, pixel_values=policy.preprocess_images([image]),
                                       max_new_tokens=action_tokens + scene_dim,
                                       min_new_tokens=action_tokens + scene_dim, do_sample=False)  # fmt: skip
        errors.append(scene_token_errors(policy, output[:, -scene_dim:], scene[None]))
    return np.mean(errors, 0)


def scene_token_errors(policy, scene_ids: torch.Tensor, scenes: np.ndarray) -> np.ndarray:
    """Mean object and goal errors (m) ``[2]`` of scene tokens ``[N, 6]`` against the true scenes ``[N, >= 6]``."""
    predicted = policy.scene_normalizer.unnormalize(policy.action_tokenizer.decode(scene_ids.numpy()))  # [N, 6]
    return np.array([np.linalg.norm(predicted[:, i : i + 3] - scenes[:, i : i + 3], axis=1).mean() for i in (0, 3)])


def train_decoder_readout(policy, data: dict, steps: int, log_every: int):
    """A copy of ``policy`` (its vision tower fixed) whose projector and decoder learn to emit the 6 scene tokens
    (object xyz, goal xyz) right after the prompt, on the training scenes of ``data`` (``{task: (train, val)}``, as
    [`render_scenes`] returns them); returns ``errors(task) -> [2]``: its held-out object and goal errors (m),
    decoded greedily."""
    from copy import deepcopy

    from hf_specvla.metaworld.env import TASK_INSTRUCTIONS

    model = deepcopy(policy.model).train()
    model.model.vision_tower.requires_grad_(False)
    normalizer, tokenizer = policy.scene_normalizer, policy.action_tokenizer
    parameters = [p for p in model.parameters() if p.requires_grad]
    optimizer = torch.optim.AdamW(parameters, lr=3e-4, weight_decay=0.01)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, 3e-4, total_steps=steps, pct_start=0.05)
    scenes = [(task, i) for task in data for i in range(len(data[task][0][0]))]
    rng = np.random.default_rng(0)
    start = time.perf_counter()
    for step in range(steps):
        images, sequences = [], []
        for k in rng.integers(0, len(scenes), 32):
            task, i = scenes[k]
            train_images, targets, states = data[task][0]
            images.append(train_images[i])
            scene_ids = tokenizer.encode(normalizer.normalize(targets[i : i + 1, :6]))[0].tolist()
            sequences.append(policy.prompt_ids(TASK_INSTRUCTIONS[task], states[i]) + scene_ids)
        length = max(map(len, sequences))
        input_ids = torch.full((len(sequences), length), policy.tokenizer.pad_token_id)
        mask, labels = torch.zeros_like(input_ids), torch.full_like(input_ids, -100)
        for row, sequence in enumerate(sequences):
            input_ids[row, : len(sequence)], mask[row, : len(sequence)] = torch.tensor(sequence), 1
            labels[row, len(sequence) - 6 : len(sequence)] = input_ids[row, len(sequence) - 6 : len(sequence)]
        shift = tuple(int(v) for v in rng.integers(-4, 5, 2))  # a random shift, as train-vla augments
        pixels = torch.roll(policy.preprocess_images(np.stack(images)), shifts=shift, dims=(2, 3))
        loss = model(input_ids=input_ids, attention_mask=mask, pixel_values=pixels, labels=labels).loss
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(parameters, 1.0)
        optimizer.step()
        schedule.step()
        if log_every and (step + 1) % log_every == 0:
            seconds = time.perf_counter() - start
            print(f"  decoder step {step + 1}/{steps}: loss {loss.item():.3f} ({seconds:.0f} s)", flush=True)
    model.eval()

    @torch.no_grad()
    def errors(task: str) -> np.ndarray:
        images, targets, states = data[task][1]
        prompts = torch.tensor([policy.prompt_ids(TASK_INSTRUCTIONS[task], state) for state in states])
        output = model.generate(input_ids=prompts, pixel_values=policy.preprocess_images(images), max_new_tokens=6,
                                min_new_tokens=6, do_sample=False)  # fmt: skip
        return scene_token_errors(policy, output[:, -6:], targets)

    return errors


def marker_centres(images: np.ndarray, channel: int) -> np.ndarray:
    """Pixel (column, row) centre of the saturated marker of ``channel`` in each image ``[N, 2]`` (per half when
    the image stacks two views: ``[N, 4]``)."""
    others = [c for c in range(3) if c != channel]
    halves = [images] if images.shape[1] == images.shape[2] else [images[:, : images.shape[1] // 2],
                                                                   images[:, images.shape[1] // 2 :]]  # fmt: skip
    centres = []
    for part in halves:
        part = part.astype(np.int16)
        mask = (part[..., channel] > 180) & (part[..., others[0]] < 80) & (part[..., others[1]] < 80)
        rows, columns = np.indices(mask.shape[1:])
        count = np.maximum(mask.sum((1, 2)), 1)
        centres += [(mask * columns).sum((1, 2)) / count, (mask * rows).sum((1, 2)) / count]
    return np.stack(centres, 1)


def colour_fit_error(train_images, train_goals, val_images, val_goals, channel: int) -> float:
    """Mean held-out goal error (m) of a quadratic fit from the marker's pixel centre(s) to the goal xyz."""
    features = lambda c: np.concatenate([c, c**2, np.ones((len(c), 1))], 1)  # noqa: E731
    weights, *_ = np.linalg.lstsq(features(marker_centres(train_images, channel)), train_goals, rcond=None)
    predicted = features(marker_centres(val_images, channel)) @ weights
    return float(np.linalg.norm(predicted - val_goals, axis=1).mean())


def train_readout(policy, train_images, train_targets, steps: int, fresh_patch_size: int | None, log_every: int):
    """Trains the policy's vision tower (or a fresh one with another patch size) and a linear readout on its patch
    features to the standardised targets; returns ``predict(images) -> [N, 9]`` in metres."""
    tower = policy.model.model.vision_tower
    if fresh_patch_size:
        from copy import deepcopy

        from transformers import CLIPVisionModel

        config = deepcopy(tower.config)
        config.patch_size = fresh_patch_size
        torch.manual_seed(0)
        tower = CLIPVisionModel(config)
    tokens = (policy.config.image_size // tower.config.patch_size) ** 2
    readout = torch.nn.Linear(tokens * tower.config.hidden_size, train_targets.shape[1])
    pixels = policy.preprocess_images(list(train_images))  # [N, 3, S, S]
    targets = torch.from_numpy(train_targets)
    mean, std = targets.mean(0), targets.std(0) + 1e-3

    def forward(batch):
        features = tower(pixel_values=batch).last_hidden_state[:, 1:]  # [B, tokens, D], the class token dropped
        return readout(features.flatten(1))

    parameters = [*tower.parameters(), *readout.parameters()]
    optimizer = torch.optim.AdamW(parameters, lr=5e-4, weight_decay=0.01)
    schedule = torch.optim.lr_scheduler.OneCycleLR(optimizer, 5e-4, total_steps=steps, pct_start=0.05)
    generator = torch.Generator().manual_seed(0)
    start = time.perf_counter()
    for step in range(steps):
        rows = torch.randint(0, len(pixels), (64,), generator=generator)
        shift = tuple(int(s) for s in torch.randint(-4, 5, (2,), generator=generator))
        batch = torch.roll(pixels[rows], shifts=shift, dims=(2, 3))  # a random shift, as train-vla augments
        loss = ((forward(batch) - (targets[rows] - mean) / std) ** 2).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        schedule.step()
        if log_every and (step + 1) % log_every == 0:
            seconds = time.perf_counter() - start
            print(f"  step {step + 1}/{steps}: loss {loss.item():.3f} ({seconds:.0f} s)", flush=True)

    @torch.no_grad()
    def predict(images):
        batches = [policy.preprocess_images(list(images[i : i + 256])) for i in range(0, len(images), 256)]
        return (torch.cat([forward(b) for b in batches]) * std + mean).numpy()

    return predict


def main():
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--policy", required=True, help="a policy folder: its camera, image size and vision tower")
    parser.add_argument("--tasks", nargs="+", default=["reach", "push", "pick-place", "peg-insert-side"])
    parser.add_argument("--scenes", type=int, default=2500, help="training scenes per task")
    parser.add_argument("--validation-scenes", type=int, default=200, help="held-out scenes per task")
    parser.add_argument("--steps", type=int, default=1200, help="readout training steps (batch 64)")
    parser.add_argument("--second-view", choices=["none", "front"], default="none")
    parser.add_argument("--fresh-patch-size", type=int, default=None,
                        help="train a fresh tower of the policy's widths with this patch size instead")  # fmt: skip
    parser.add_argument("--save-policy", type=Path, default=None,
                        help="save the policy with its scene-trained tower here (a new folder)")  # fmt: skip
    parser.add_argument("--decoder-steps", type=int, default=0,
                        help="also train a copy of the policy's decoder (tower fixed) this many steps to emit the "
                             "scene tokens right after the prompt, and report its errors (policies with scene "
                             "targets; 0 = not)")  # fmt: skip
    parser.add_argument("--threads", type=int, default=1)
    args = parser.parse_args()
    if args.save_policy is not None and args.save_policy.exists() and any(args.save_policy.iterdir()):
        parser.error(f"--save-policy {args.save_policy} is not empty: name a new folder (nothing is overwritten)")
    if args.save_policy is not None and (args.fresh_patch_size or args.second_view != "none"):
        parser.error("--save-policy keeps the policy's own tower on its own view: drop --fresh-patch-size / "
                     "--second-view")  # fmt: skip
    if args.scenes < 2 or args.validation_scenes < 1 or args.steps < 1 or args.decoder_steps < 0:
        parser.error(f"--scenes >= 2, --validation-scenes >= 1, --steps >= 1 and --decoder-steps >= 0, got "
                     f"{args.scenes}, {args.validation_scenes}, {args.steps}, {args.decoder_steps}")  # fmt: skip
    if args.decoder_steps and args.second_view != "none":
        parser.error("--decoder-steps trains the policy's decoder on its own view: drop --second-view")
    from hf_specvla.metaworld.env import FREE_CAMERAS, resolve_tasks
    from hf_specvla.policies import VLAPolicy

    try:
        tasks = resolve_tasks(args.tasks)
    except ValueError as error:
        parser.error(str(error))
    torch.set_num_threads(args.threads)
    policy = VLAPolicy.from_pretrained(args.policy)
    if args.decoder_steps and not policy.config.scene_state_dim:
        parser.error(f"--decoder-steps: {args.policy} was trained without scene targets: it has no scene statistics "
                     "to emit scene tokens in")  # fmt: skip
    size, camera = policy.config.image_size, policy.config.camera
    if args.fresh_patch_size and size % args.fresh_patch_size:
        parser.error(f"--fresh-patch-size must divide the policy's {size} px images, got {args.fresh_patch_size}")
    second = None if args.second_view == "none" else args.second_view
    if second and camera not in FREE_CAMERAS:
        parser.error(f"--second-view moves a free camera; the policy's camera {camera!r} is not one of "
                     f"{sorted(FREE_CAMERAS)}")  # fmt: skip
    data = {}
    for task in tasks:
        start = time.perf_counter()
        train = render_scenes(task, args.scenes, TRAIN_SEED, size, camera, second)
        validation = render_scenes(task, args.validation_scenes, VALIDATION_SEED, size, camera, second)
        data[task] = (train, validation)
        print(f"{task}: {args.scenes} + {args.validation_scenes} scenes rendered ({time.perf_counter() - start:.0f} s)")
    own = {}
    if policy.config.scene_state_dim and not second:
        policy.model.eval()
        for task in tasks:
            images, targets, states = data[task][1]
            own[task] = policy_scene_errors(policy, task, images, states, targets[:, :6])
    decoder_errors = None
    if args.decoder_steps:
        decoder_errors = train_decoder_readout(policy, data, args.decoder_steps, max(args.decoder_steps // 4, 1))
    train_images = np.concatenate([data[t][0][0] for t in tasks])
    train_targets = np.concatenate([data[t][0][1] for t in tasks])
    predict = train_readout(policy, train_images, train_targets, args.steps, args.fresh_patch_size,
                            max(args.steps // 4, 1))  # fmt: skip
    if args.save_policy is not None:
        policy.save_pretrained(args.save_policy)
        record = {"script": "examples/metaworld/localization_probe.py", "policy": args.policy, "tasks": tasks,
                  "scenes": args.scenes, "steps": args.steps, "train_seed": TRAIN_SEED}  # fmt: skip
        (args.save_policy / "scene_pretraining.json").write_text(json.dumps(record, indent=2))
        print(f"saved the policy with its scene-trained tower to {args.save_policy}")
    view = f"{camera} + front, stacked" if second else camera
    tower = f"fresh, {args.fresh_patch_size} px patches" if args.fresh_patch_size else "the policy's"
    print(f"\nvision tower: {tower}; view: {view}; {args.scenes} scenes per task; {args.steps} steps")
    decoder = f" | the decoder, scene tokens first ({args.decoder_steps} steps): object / goal"
    decoder = decoder if decoder_errors else ""
    print("| task | object | goal | hand | goal from the marker's colour | the policy's scene tokens: object / goal "
          f"| the training mean: object / goal{decoder} |")  # fmt: skip
    print("|---|---:|---:|---:|---:|---:|---:|" + ("---:|" if decoder_errors else ""))
    for task in tasks:
        (train_x, train_y, _), (val_x, val_y, _) = data[task]
        error = np.abs(predict(val_x) - val_y)
        norms = [np.linalg.norm(error[:, i : i + 3], axis=1).mean() * 100 for i in (0, 3, 6)]
        colour = "-"
        if task in MARKER_CHANNEL:
            goal_error = colour_fit_error(train_x, train_y[:, 3:6], val_x, val_y[:, 3:6], MARKER_CHANNEL[task])
            colour = f"{100 * goal_error:.1f}"
        scene = f"{100 * own[task][0]:.1f} / {100 * own[task][1]:.1f}" if task in own else "-"
        guess = train_y.mean(0)  # [9]
        mean = [np.linalg.norm(val_y[:, i : i + 3] - guess[i : i + 3], axis=1).mean() * 100 for i in (0, 3)]
        read = ""
        if decoder_errors:
            object_error, goal_error = 100 * decoder_errors(task)
            read = f" {object_error:.1f} / {goal_error:.1f} |"
        print(f"| {task} | {norms[0]:.1f} | {norms[1]:.1f} | {norms[2]:.1f} | {colour} | {scene} "
              f"| {mean[0]:.1f} / {mean[1]:.1f} |{read}")  # fmt: skip


if __name__ == "__main__":
    main()
