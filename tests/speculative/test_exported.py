"""A module's call exported as one graph (``speculative.exported``): the image encoder that dynamo cannot trace whole
(transformers' output-capturing hooks) as a plain function of its weights and inputs, equal to the eager call, reading
the module's current weights, compiled and saved as a graph file that a fresh process loads."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from hf_specvla.speculative import graph_files
from hf_specvla.speculative.exported import export_call

from ..conftest import llava_prompt


def _encode(model, pixel_values):
    return model.base_model.get_image_features(pixel_values=pixel_values, return_dict=True)


def _assert_same_output(got, want) -> None:
    assert type(got) is type(want)
    for name in ("last_hidden_state", "pooler_output", "hidden_states"):
        a, b = getattr(got, name, None), getattr(want, name, None)
        if isinstance(b, torch.Tensor):
            assert torch.equal(a, b), name
        elif isinstance(b, (list, tuple)):
            same = [x is y is None or (x is not None and y is not None and torch.equal(x, y)) for x, y in zip(a, b)]
            assert len(a) == len(b) and all(same), name
        else:
            assert a is None and b is None, name


def test_an_exported_image_encoder_is_its_eager_call_on_the_current_weights(tiny_llava):
    """The exported encoder gives the eager ``get_image_features``' output object, tensor for tensor, and reads the
    weights at every call: a weight changed in place, or a parameter replaced by another, is what it computes with."""
    pixel_values = llava_prompt(torch.Generator().manual_seed(0))["pixel_values"].repeat(2, 1, 1, 1)
    with torch.no_grad():
        exported = export_call(tiny_llava.base_model, "get_image_features", {"pixel_values": pixel_values},
                               {"return_dict": True})  # fmt: skip
        assert exported is not None and exported.input_names == ("pixel_values",)

        def check() -> None:
            _assert_same_output(
                exported.unflatten(exported(pixel_values=pixel_values)), _encode(tiny_llava, pixel_values)
            )

        check()
        projector = tiny_llava.base_model.multi_modal_projector.linear_1
        original = projector.weight
        try:
            projector.weight.mul_(2.0)  # in place (a power of two: undone exactly below)
            check()
            projector.weight = torch.nn.Parameter(torch.randn_like(original))  # another parameter object
            check()
        finally:
            projector.weight = original
            original.mul_(0.5)


def test_what_export_refuses_is_none_and_said_once(tiny_llava, caplog):
    """A non-tensor input, or code export cannot follow (a branch on a tensor's value), is not exported: None, and
    the caller keeps its other route (dynamo with graph breaks, in memory)."""

    class Branchy(torch.nn.Module):
        def forward_images(self, pixel_values):
            return pixel_values * 2 if pixel_values.sum() > 0 else pixel_values  # data-dependent

    with caplog.at_level(logging.INFO, logger="hf_specvla"):
        assert export_call(Branchy(), "forward_images", {"pixel_values": torch.ones(1, 3)}, {}) is None
        assert export_call(tiny_llava.base_model, "get_image_features", {"pixel_values": [1, 2]}, {}) is None
    said = [r.getMessage() for r in caplog.records if "is not exported as one graph" in r.getMessage()]
    assert len(said) == 2 and "Branchy.forward_images" in said[0] and "not a tensor" in said[1], said


#: a fresh process: the tiny Llava of the tests (seeded by argv[2]) decoding compiled speculative calls (its drafts
#: greedy's own) whose graphs are files in argv[1]; prints whether each equals eager greedy, what was loaded and
#: compiled, and how many graphs dynamo traced
VLM_PROCESS = textwrap.dedent(
    """
    import json, logging, sys, torch
    sys.path.insert(0, sys.argv[3])
    from tests.conftest import build_tiny_llava, llava_prompt
    from hf_specvla.speculative import compiled_decoding_kwargs
    from torch._dynamo.utils import counters
    records = []
    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())
    logging.getLogger("hf_specvla").addHandler(Keep()); logging.getLogger("hf_specvla").setLevel(logging.INFO)
    model = build_tiny_llava()
    if int(sys.argv[2]):
        torch.manual_seed(int(sys.argv[2]))
        with torch.no_grad():
            for parameter in model.parameters():
                parameter.add_(0.05 * torch.randn_like(parameter))
    generator = torch.Generator().manual_seed(4)
    equal = []
    for batch_size in (1, 2):
        prompts = [llava_prompt(generator, text_len=3) for _ in range(batch_size)]
        prompt = {name: torch.cat([p[name] for p in prompts]) for name in prompts[0]}
        greedy = model.generate(**prompt, max_new_tokens=6, do_sample=False)
        drafts = greedy[:, prompt["input_ids"].shape[1]:-1]
        out = model.generate(**prompt, max_new_tokens=6, do_sample=False, draft_ids=drafts,
                             **compiled_decoding_kwargs("cpu"))
        equal.append(bool(torch.equal(out, greedy)))
    print(json.dumps({"equal": equal, "traced": counters["stats"]["unique_graphs"],
                      "encoder_loaded": sum("loaded compiled graph encode_images" in m for m in records),
                      "compiled": sum("no graph file" in m for m in records)}))
    """
)


@pytest.mark.slow  # ~60 s: two fresh processes, the first compiles every graph
def test_a_fresh_process_loads_the_image_encoder_from_its_file_and_traces_nothing(tmp_path):
    """A VLM's compiled speculative calls at batch sizes 1 and 2, in a process after another one saved the graphs
    (a model of other weights): every graph loaded from its file, the image encoder's one per batch size included,
    dynamo traces none, and both processes decode greedy's tokens."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), graph_files.FOLDER_ENV: str(tmp_path)}
    runs = []
    for seed in (0, 1):
        done = subprocess.run([sys.executable, "-c", VLM_PROCESS, str(tmp_path), str(seed), root],
                              capture_output=True, text=True, env=env, timeout=900)  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    first, later = runs
    assert first["equal"] == [True, True] and first["compiled"] >= 4 and first["traced"] > 0, first
    assert later["equal"] == [True, True] and later["compiled"] == 0 and later["traced"] == 0, later
    assert later["encoder_loaded"] == 2, later
