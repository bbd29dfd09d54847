"""What the commands share: argument types, the help format, the one place where a library error becomes a usage
error, the training-run flags and logging. Light at import: no training, simulator or data code."""

from __future__ import annotations

import argparse
import logging
import math
import os
from contextlib import contextmanager
from pathlib import Path


def at_least(minimum: int):
    """argparse ``type``: an int >= ``minimum``, else a usage error naming the value (exit code 2)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer >= {minimum}, got {text!r}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"must be >= {minimum}, got {value}")
        return value

    parse.__name__ = f"int >= {minimum}"  # what argparse names in its error
    return parse


POSITIVE, NON_NEGATIVE = at_least(1), at_least(0)


def positive_number(text: str) -> float:
    """argparse ``type``: a finite number > 0, else a usage error naming the value (exit code 2)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number > 0, got {text!r}") from None
    if not math.isfinite(value) or value <= 0:
        raise argparse.ArgumentTypeError(f"must be a finite number > 0, got {text}")
    return value


positive_number.__name__ = "number > 0"


def _device_flag(text: str) -> str:
    """argparse ``type`` of ``--device``: its spelling (``policies.devices.check_device``; no torch), else a usage
    error naming the value and the valid ones."""
    from ..policies.devices import check_device

    try:
        return check_device(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def _dtype_flag(text: str) -> str:
    """argparse ``type`` of ``--dtype``, as [`_device_flag`]."""
    from ..policies.devices import check_dtype

    try:
        return check_dtype(text)
    except ValueError as error:
        raise argparse.ArgumentTypeError(str(error)) from None


def add_device_arguments(parser: argparse.ArgumentParser) -> None:
    """--device, --dtype: where the policy (and its draft head) runs and in what precision; shared by every command
    that runs a policy. Their spelling is checked at parse time (no torch); whether the device is there, by
    [`resolve_placement`] right before the policy loads."""
    from ..policies.devices import DEFAULT_DEVICE, DEFAULT_DTYPE

    parser.add_argument(
        "--device",
        type=_device_flag,
        default=DEFAULT_DEVICE,
        help="where the policy and its draft head run: auto (cuda when torch sees a GPU, else cpu), cpu, cuda, cuda:N",
    )
    parser.add_argument(
        "--dtype",
        type=_dtype_flag,
        default=DEFAULT_DTYPE,
        help="the weights' precision: auto (bfloat16 on a CUDA device, float32 on cpu), bfloat16, float16, float32 "
        "(a draft head is checked against the policy as saved, then cast)",
    )


def resolve_placement(args, parser):
    """``--device`` / ``--dtype`` resolved on this machine (a [`Placement`]); a usage error naming the device when
    it is not here (``cuda`` without CUDA, ``cuda:3`` with one GPU). Imports torch: call it right before the policy
    loads, after the cheap checks, before anything is written."""
    from ..policies.devices import Placement

    with usage_errors(parser, "--device", (ValueError,)):
        return Placement.resolve(args.device, args.dtype)


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the examples' line breaks and shows every option's default (but a flag's: ``--no-compile`` does not
    default to True; and an option whose help says its default itself, as one that depends on other options does,
    gets no "(default: None)" after it)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        if isinstance(action, argparse._StoreConstAction):  # store_true / store_false / store_const flags
            return action.help or ""
        if "(default: " in (action.help or ""):
            return action.help
        return super()._get_help_string(action)


@contextmanager
def usage_errors(
    parser: argparse.ArgumentParser,
    flag: str | None = None,
    errors: tuple[type[Exception], ...] = (ValueError, FileExistsError, FileNotFoundError),
):
    """A library refusal raised inside the block (bad value, folder of another run, missing folder) becomes a usage
    error (exit code 2) that names ``flag``: the only place the CLI translates library errors."""
    try:
        yield
    except errors as error:
        parser.error(f"{flag}: {error}" if flag else str(error))


def add_training_run_arguments(parser: argparse.ArgumentParser, seed: int) -> None:
    """--resume, --overwrite-output-dir, --seed, --threads: shared by the trainers."""
    parser.add_argument("--resume", action="store_true", help="continue from the newest checkpoint in --output-dir")
    parser.add_argument(
        "--overwrite-output-dir", action="store_true", help="move the folder's previous run aside, train from scratch"
    )
    parser.add_argument("--seed", type=int, default=seed, help="random seed")
    parser.add_argument("--threads", type=POSITIVE, default=None, help="torch CPU threads (default: torch's)")


def check_training_folder(output_dir: str, resume: bool, overwrite: bool, parser) -> None:
    """The common folder mistakes as usage errors before any data is loaded (the full check of the folder's
    run.json runs once the data's fingerprint is known)."""
    from ..training.checkpoints import check_output_dir

    with usage_errors(parser, errors=(FileExistsError, FileNotFoundError)):
        check_output_dir(Path(output_dir), None, resume, overwrite)


def check_draft_head_flag(draft_head: str | None, parser) -> None:
    """``--draft-head`` must be a saved draft head (or a hub id): a usage error before anything is loaded. Without
    the flag nothing is imported (the engine pulls in torch and transformers: seconds before the next usage error)."""
    if draft_head is not None:
        from ..speculative import check_draft_head_folder

        with usage_errors(parser, "--draft-head", (FileNotFoundError, ValueError)):
            check_draft_head_folder(draft_head)


def check_output_dir_flag(output_dir: str, parser, flag: str = "--output-dir") -> None:
    """``flag`` must name a folder that exists or can be made: a usage error, before anything loads or is written,
    when it is a file, when a folder above it is a file, or when the nearest existing folder above it is not
    writable."""
    path = Path(output_dir)
    if path.exists() and not path.is_dir():
        parser.error(f"{flag} {output_dir}: is a file, not a folder; give a folder (it is made if missing)")
    existing = next((p for p in (path, *path.parents) if p.exists()), Path("."))  # Path.exists: False under a file
    if not existing.is_dir():
        parser.error(f"{flag} {output_dir}: {existing} is a file, so no folder can be made under it; give another path")
    if not os.access(existing, os.W_OK | os.X_OK):
        parser.error(f"{flag} {output_dir}: {existing} is not writable; give a folder you can write to")


def read_policy_config(path: str, parser, flag: str = "--policy", unnorm_key: str | None = None):
    """What checks need before the slow load, read without loading the model: a Meta-World policy's
    [`VLAPolicyConfig`] (action layout, image settings), or an OpenVLA checkpoint's [`OpenVLAPolicyLayout`] (its
    action length, ``unnorm_key`` checked); the same usage error as [`load_policy`] when the folder holds no policy."""
    import json

    from ..policies.configuration_vla import POLICY_CONFIG_NAME, VLAPolicyConfig, check_policy_folder

    if _is_openvla(path):
        from ..policies.loading import read_policy_layout

        with usage_errors(parser, "--unnorm-key" if unnorm_key else flag, (ValueError, OSError)):
            return read_policy_layout(path, unnorm_key)
    with usage_errors(parser, flag, (FileNotFoundError,)):
        check_policy_folder(path)  # names the missing folder or file, as load_policy does
    if unnorm_key is not None:
        parser.error(
            f"--unnorm-key {unnorm_key}: {flag} {path} is a Meta-World policy with one set of action statistics; "
            f"--unnorm-key names an OpenVLA checkpoint's dataset"
        )
    config_path = Path(path) / POLICY_CONFIG_NAME
    try:
        return VLAPolicyConfig(**json.loads(config_path.read_text()))
    except (ValueError, TypeError) as error:  # not JSON, unknown or bad fields
        parser.error(f"{flag} {path}: {config_path} is not a policy configuration: {error}")


def _is_openvla(path: str) -> bool:
    """Whether ``path`` names an OpenVLA checkpoint (a folder or a hub id; anything else is read as a Meta-World
    policy folder, whose check names what is missing)."""
    from ..policies.loading import policy_kind

    try:
        return policy_kind(path) == "openvla"
    except (FileNotFoundError, ValueError):
        return False


def check_bin_tolerances(tolerances: list[int], n_bins: int, given: str, parser) -> None:
    """A tolerance wider than the action range (``0 .. n_bins - 1``) is a usage error naming ``given`` (the flag
    and its values), in the engine's own words."""
    from ..speculative import check_bin_tolerance_range

    with usage_errors(parser, errors=(ValueError,)):
        check_bin_tolerance_range(tolerances, n_bins, given)


def load_policy(path: str, parser, flag: str = "--policy", unnorm_key: str | None = None, dtype=None):
    """The saved policy ``flag`` names (a Meta-World policy folder, or an OpenVLA checkpoint: a folder or a hub id,
    loaded in ``dtype`` when given, with ``unnorm_key`` its default dataset); a usage error when the folder holds none
    (checked before the policy's imports: torch and transformers take seconds) or its weights file is damaged (one
    line naming the file)."""
    from ..policies.configuration_vla import check_policy_folder

    openvla = _is_openvla(path)
    if not openvla:
        with usage_errors(parser, flag, (FileNotFoundError,)):
            check_policy_folder(path)
    from ..policies.loading import load_policy as load
    from ..speculative import DamagedWeightsError

    with usage_errors(
        parser, flag, (DamagedWeightsError, FileNotFoundError, ValueError) if openvla else (DamagedWeightsError,)
    ):
        return load(path, unnorm_key, **({"dtype": dtype} if openvla and dtype is not None else {}))


def load_draft_head(path: str, parser, flag: str = "--draft-head"):
    """The saved draft head ``flag`` names, in eval mode; a usage error (one line naming the file) when its weights
    file is damaged."""
    from ..speculative import DamagedWeightsError, DraftHead

    with usage_errors(parser, flag, (DamagedWeightsError,)):
        return DraftHead.from_pretrained(path).eval()


def check_tasks(tasks: list[str], parser) -> None:
    """``--tasks``: suites and/or Meta-World task names; a usage error listing the valid ones, before anything loads."""
    from ..metaworld.env import resolve_tasks

    with usage_errors(parser, "--tasks", (ValueError,)):
        resolve_tasks(tasks)


def load_draft_head_for(policy, draft_head: str, parser):
    """The ``--draft-head`` for ``policy``; a usage error when it was made for another model."""
    head = load_draft_head(draft_head, parser)
    with usage_errors(parser, f"--draft-head {draft_head}"):
        policy.check_draft_head(head)
    return head


def configure_logging(verbose: bool = False) -> None:
    """hf_specvla's own messages at INFO (DEBUG with ``-v``), each on its own line even while a progress bar is
    drawn; other libraries' INFO (OpenGL, accelerate, ...) and transformers' weight-loading bars are left out; a
    launched run's secondary processes log warnings only."""
    from transformers.utils import logging as transformers_logging

    from ..progress import ProgressAwareHandler, is_secondary_process

    handler = ProgressAwareHandler()
    handler.setFormatter(logging.Formatter("%(levelname)s %(name)s: %(message)s"))
    root = logging.getLogger()
    for existing in [h for h in root.handlers if isinstance(h, ProgressAwareHandler)]:  # main() called again
        root.removeHandler(existing)
    root.addHandler(handler)
    root.setLevel(logging.WARNING)
    level = logging.WARNING if is_secondary_process() else logging.DEBUG if verbose else logging.INFO
    logging.getLogger("hf_specvla").setLevel(level)
    transformers_logging.disable_progress_bar()


def add_tree_arguments(parser: argparse.ArgumentParser) -> None:
    """--tree-top-k, --tree-depth, --tree-total-tokens: the EAGLE-2 tree of the head's tree methods."""
    parser.add_argument(
        "--tree-top-k", type=POSITIVE, default=None, help="EAGLE-2 tree top_k (default: DraftTreeConfig's)"
    )
    parser.add_argument(
        "--tree-depth", type=POSITIVE, default=None, help="EAGLE-2 tree depth (default: DraftTreeConfig's)"
    )
    parser.add_argument(
        "--tree-total-tokens", type=POSITIVE, default=None, help="EAGLE-2 tree nodes kept (default: DraftTreeConfig's)"
    )
