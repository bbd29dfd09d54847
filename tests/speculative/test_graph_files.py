"""Compiled graphs as files (``speculative.graph_files``): loaded by a fresh process without tracing, keyed by what
they depend on (not the weights), never stale or damaged, written atomically, kept in memory where a folder cannot
be written."""

from __future__ import annotations

import json
import logging
import os
import subprocess
import sys
import textwrap
import time
import types

import pytest
import torch

from hf_specvla.speculative import graph_files
from hf_specvla.speculative.graph_files import DAMAGED, FileBackedFunction, GraphStore, architecture, environment
from hf_specvla.speculative.regions import LAYER_REGIONS_ENV

#: a fresh process: a tiny module (seeded by argv[2], width argv[3]) called through a file-backed function in the
#: folder argv[1]; prints its result against the eager module's, and what it compiled and loaded. dynamo's ``eager``
#: backend: the file holds what it traced and its guards, as with inductor (whose files the engine's tests load)
FRESH_PROCESS = textwrap.dedent(
    """
    import json, sys, torch
    from hf_specvla.speculative.graph_files import FileBackedFunction, GraphStore, architecture, environment
    folder, seed, width = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
    torch.manual_seed(seed)
    def closing_over(model):
        def run_model(x):
            return model(x).argmax(-1)
        return run_model
    model = torch.nn.Sequential(torch.nn.Linear(width, 16), torch.nn.GELU(), torch.nn.Linear(16, 3)).eval()
    run_model = closing_over(model)
    key = {**environment(), "model": architecture(model)}
    function = FileBackedFunction(run_model, {"fullgraph": True, "backend": "eager"}, key, GraphStore(folder))
    x = torch.randn(64, width, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        got, want = function(x), model(x).argmax(-1)
    print(json.dumps({"equal": bool(torch.equal(got, want)), "compiled": function.compiled, "loaded": function.loaded}))
    """
)


def fresh_process(folder, seed: int = 0, width: int = 8) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path)}
    return subprocess.Popen(
        [sys.executable, "-c", FRESH_PROCESS, str(folder), str(seed), str(width)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=env,
    )


def result(process: subprocess.Popen) -> dict:
    out, err = process.communicate(timeout=600)
    assert process.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


def graph_files_in(folder) -> list:
    return sorted(p for p in folder.iterdir() if p.suffix == ".graph")


def test_a_graph_is_loaded_by_a_fresh_process_and_reads_that_process_weights(tmp_path):
    first = result(fresh_process(tmp_path, seed=0))
    assert first == {"equal": True, "compiled": 1, "loaded": 0}
    assert len(graph_files_in(tmp_path)) == 1
    # another process, other weights of the same architecture: the file is used, and the weights are its own
    second = result(fresh_process(tmp_path, seed=1))
    assert second == {"equal": True, "compiled": 0, "loaded": 1}
    # another architecture: a miss, a file of its own
    third = result(fresh_process(tmp_path, seed=0, width=12))
    assert third == {"equal": True, "compiled": 1, "loaded": 0}
    assert len(graph_files_in(tmp_path)) == 2


def test_two_processes_compiling_one_key_at_once_both_end_with_a_whole_file(tmp_path):
    racing = [fresh_process(tmp_path, seed=s) for s in (0, 1)]
    assert all(result(p)["equal"] for p in racing)
    assert len(graph_files_in(tmp_path)) == 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp-")]
    assert result(fresh_process(tmp_path, seed=2)) == {"equal": True, "compiled": 0, "loaded": 1}


def small_model(width: int = 8, dtype=torch.float32):
    torch.manual_seed(0)
    return torch.nn.Sequential(torch.nn.Linear(width, 16), torch.nn.Tanh(), torch.nn.Linear(16, 3)).eval().to(dtype)


def file_backed(model, folder, key_extra: dict | None = None, **settings) -> FileBackedFunction:
    def run_small(x):
        return model(x)

    key = {**environment(), "model": architecture(model), **(key_extra or {})}
    return FileBackedFunction(run_small, {"fullgraph": True, "backend": "eager", **settings}, key, GraphStore(folder))


@pytest.mark.parametrize("damage", ["truncated", "one byte changed", "not a graph"])
def test_a_damaged_file_is_set_aside_with_a_warning_and_compiled_again(tmp_path, caplog, damage):
    model, x = small_model(), torch.randn(4, 8)
    with torch.no_grad():
        file_backed(model, tmp_path)(x)
        (path,) = graph_files_in(tmp_path)
        data = path.read_bytes()
        if damage == "truncated":
            path.write_bytes(data[: len(data) // 2])
        elif damage == "one byte changed":
            middle = len(data) // 2
            path.write_bytes(data[:middle] + bytes([data[middle] ^ 0xFF]) + data[middle + 1 :])
        else:
            path.write_bytes(b"hello")
        function = file_backed(model, tmp_path)
        with caplog.at_level(logging.WARNING, logger="hf_specvla"):
            out = function(x)
        assert torch.allclose(out, model(x))
    assert (function.compiled, function.loaded) == (1, 0)
    assert any("set aside" in r.getMessage() and path.name in r.getMessage() for r in caplog.records)
    assert [p.name for p in tmp_path.iterdir() if DAMAGED in p.name][0].startswith(path.name + DAMAGED)
    assert file_backed(model, tmp_path)(x) is not None and len(graph_files_in(tmp_path)) == 1  # healed: whole again


def test_a_folder_that_cannot_be_written_keeps_graphs_in_memory_with_one_warning(tmp_path, caplog):
    blocker = tmp_path / "a-file"
    blocker.write_text("not a folder")
    graph_files._read_only_warning.cache_clear()
    model = small_model()
    function = file_backed(model, blocker / "graphs")
    with caplog.at_level(logging.WARNING, logger="hf_specvla"), torch.no_grad():
        for rows in (2, 3, 2):
            x = torch.randn(rows, 8)
            assert torch.allclose(function(x), model(x), atol=1e-6)
    warnings = [r for r in caplog.records if "kept in memory only" in r.getMessage()]
    assert len(warnings) == 1 and str(blocker / "graphs") in warnings[0].getMessage()
    assert function.compiled == 2  # one graph per shape, in memory


def test_every_keyed_input_is_a_miss_named_in_the_log(tmp_path, caplog, monkeypatch):
    model, x = small_model(), torch.randn(4, 8)
    with torch.no_grad():
        file_backed(model, tmp_path)(x)
        cases = {
            "torch": lambda: file_backed(model, tmp_path, {"torch": "0.0.0"})(x),
            "model.tensors": lambda: file_backed(small_model(dtype=torch.float64), tmp_path)(x.double()),
            "inputs": lambda: file_backed(model, tmp_path)(torch.randn(5, 8)),
        }
        for part, call in cases.items():
            caplog.clear()
            with caplog.at_level(logging.INFO, logger="hf_specvla"):
                call()
            misses = [r.getMessage() for r in caplog.records if "no graph file for its key" in r.getMessage()]
            assert misses and part in misses[0], (part, misses)
    # and the same key is a hit
    again = file_backed(model, tmp_path)
    with torch.no_grad():
        again(x)
    assert (again.compiled, again.loaded) == (0, 1)


def test_the_folder_follows_the_environment_variable(monkeypatch, tmp_path):
    monkeypatch.setenv(graph_files.FOLDER_ENV, "off")
    assert graph_files.graph_folder() is None
    monkeypatch.setenv(graph_files.FOLDER_ENV, str(tmp_path / "g"))
    assert graph_files.graph_folder() == tmp_path / "g"
    monkeypatch.setenv(graph_files.FOLDER_ENV, "on")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert graph_files.graph_folder() == tmp_path / "xdg" / "hf_specvla" / "graphs"
    monkeypatch.delenv(graph_files.FOLDER_ENV)
    assert graph_files.graph_folder("cpu") == tmp_path / "xdg" / "hf_specvla" / "graphs"  # on by default on the CPU
    assert graph_files.graph_folder("cuda") is None  # not yet measured on a GPU
    monkeypatch.setenv(graph_files.FOLDER_ENV, "on")
    assert graph_files.graph_folder("cuda") == tmp_path / "xdg" / "hf_specvla" / "graphs"


def test_a_servers_compile_cache_moves_the_folder_not_the_switch(monkeypatch, tmp_path):
    """Inside ``graphs_kept_in`` (``serve --compile-cache DIR``: ``DIR/graphs``) graph files go to its folder instead
    of the variable's or the default one; ``off`` and a GPU's default (in memory) still hold, and the block's end
    restores the folder."""
    served = tmp_path / "served" / "graphs"
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    for value, device, inside in [("", "cpu", served), (str(tmp_path / "g"), "cpu", served), ("on", "cuda", served),
                                  ("off", "cpu", None), ("", "cuda", None)]:  # fmt: skip
        monkeypatch.setenv(graph_files.FOLDER_ENV, value)
        before = graph_files.graph_folder(device)
        with graph_files.graphs_kept_in(served):
            assert graph_files.graph_folder(device) == inside, (value, device)
        assert graph_files.graph_folder(device) == before


def test_a_call_that_fails_its_graph_guards_compiles_again(tmp_path, caplog):
    """What the key leaves to the guards (here a parameter replaced by one of another shape between calls) is
    checked at every call."""
    model = small_model()
    function = file_backed(model, tmp_path)
    x = torch.randn(4, 8)
    with torch.no_grad():
        function(x)
        model[2] = torch.nn.Linear(16, 5)
        with caplog.at_level(logging.INFO, logger="hf_specvla"):
            out = function(x)
        assert out.shape == (4, 5) and torch.allclose(out, model(x))
    assert any("failed its graph's guards" in r.getMessage() for r in caplog.records)


def test_a_dimension_marked_dynamic_stays_dynamic_in_a_graph_compiled_again_after_a_failed_guard(tmp_path, caplog):
    """A graph whose input has a dimension marked dynamic (the engine's prefill: every prompt length) and which a
    call compiles again because it failed a guard (here grad mode, on after the first call) is traced from the
    inputs as marked: still one graph for every size, in this process and in the next one that loads its file. (It
    used to be traced from the unmarked inputs: a graph of one size under the key of every size, compiled again and
    saved over at each change of size, by every later process too.)"""
    model = small_model()
    function = file_backed(model, tmp_path, dynamic=False)  # as a CompileConfig compiles: no automatic dynamic sizes

    def call(function, size: int):
        x = torch.randn(size, 8)
        torch._dynamo.mark_dynamic(x, 0)
        assert torch.equal(function(x), model(x))

    with torch.no_grad():
        call(function, 4)
    with caplog.at_level(logging.INFO, logger="hf_specvla"):  # grad mode on: a guard fails, once
        for size in (5, 6, 5, 7, 6):
            call(function, size)
    assert function.compiled == 2
    assert sum("failed its graph's guards" in r.getMessage() for r in caplog.records) == 1
    later = file_backed(model, tmp_path, dynamic=False)  # a later process's: the file serves every size
    for size in (9, 3, 12):
        call(later, size)
    assert (later.loaded, later.compiled) == (1, 0)


def test_calls_that_alternate_between_guards_compile_each_once(tmp_path, caplog):
    """Calls that alternate between what a graph's guards tell apart (grad mode off and on, as a script's calls and a
    session's may) compile one graph each, then run whichever passes, as dynamo's own cache does: a function keeps
    several graphs per input signature ([`GRAPHS_PER_SIGNATURE`]), not one compiled again at every change."""
    model = small_model()
    function = file_backed(model, tmp_path)
    x = torch.randn(4, 8)
    with caplog.at_level(logging.INFO, logger="hf_specvla"):
        for _ in range(4):
            with torch.no_grad():
                assert torch.equal(function(x), model(x))
            out = function(x)
            assert out.requires_grad and torch.equal(out, model(x))
    assert function.compiled == 2
    assert sum("failed its graph's guards" in r.getMessage() for r in caplog.records) == 1
    # more variants than it keeps (which parameters take gradients: 2^4 of them): the least recently used goes
    parameters = list(model.parameters())
    variants = graph_files.GRAPHS_PER_SIGNATURE + 1
    for variant in [*range(variants), 0]:
        for bit, parameter in enumerate(parameters):
            parameter.requires_grad_(bool(variant >> bit & 1))
        assert torch.equal(function(x), model(x))
    assert function.compiled == 2 + variants + 1  # each variant once, then variant 0 again: it was dropped
    assert len(function.graphs[graph_files.signature(((x,), {}))]) == graph_files.GRAPHS_PER_SIGNATURE


def test_the_model_key_holds_no_weights():
    a, b = small_model(), small_model()
    with torch.no_grad():
        b[0].weight.add_(1.0)
    assert architecture(a) == architecture(b)
    assert architecture(a) != architecture(small_model(width=9))
    assert json.dumps(architecture(a))  # a JSON record


def test_stale_graphs_are_removed_and_a_loaded_one_counts_as_used(tmp_path):
    """``remove_stale``: a graph of another engine's code goes (no process of this code can load it), and so does a
    record without its graph; with ``unused_days``, a graph neither written nor loaded for longer goes, while one
    loaded since (its time refreshed) stays."""
    records = {}
    with torch.no_grad():
        for width in (8, 9, 10):
            before = set(tmp_path.glob("*.json"))
            file_backed(small_model(width), tmp_path)(torch.randn(4, width))
            (records[width],) = set(tmp_path.glob("*.json")) - before
    records[8].write_text(json.dumps({**json.loads(records[8].read_text()), "engine": "another engine's code"}))
    (tmp_path / "orphan-0.json").write_text("{}")
    assert graph_files.remove_stale(tmp_path) == 2  # another engine's graph, the orphan record
    assert {p.stem for p in graph_files_in(tmp_path)} == {records[9].stem, records[10].stem}
    eight_days_ago = time.time() - 8 * 86400
    for width in (9, 10):
        os.utime(records[width].with_suffix(".graph"), (eight_days_ago, eight_days_ago))
    loader = file_backed(small_model(9), tmp_path)
    with torch.no_grad():
        loader(torch.randn(4, 9))
    assert loader.loaded == 1 and loader.compiled == 0
    assert graph_files.remove_stale(tmp_path, unused_days=7) == 1  # width 10's; width 9's was just loaded
    assert [p.stem for p in graph_files_in(tmp_path)] == [records[9].stem]


def _function_layer(function):
    """A layer made from a function inside a function, as the ``kernels`` package makes its hub function layers
    (``_create_func_module.<locals>.Func``, on every Llama-family model from transformers 5.25)."""

    class Func(torch.nn.Module):
        def forward(self, *args, **kwargs):
            return function(*args, **kwargs)

    return Func


def _scaled(x, factor=2.0):
    return x * factor


class WithFunctionLayer(torch.nn.Module):
    """A model calling a function layer it holds outside its submodules (``kernels``' ``use_kernelized_func``)."""

    def __init__(self, seed: int):
        super().__init__()
        torch.manual_seed(seed)
        self.linear = torch.nn.Linear(8, 3)
        self.__dict__["_kernel_funcs"] = {"scaled": _function_layer(_scaled)()}

    def forward(self, x):
        return self._kernel_funcs["scaled"](self.linear(x))


def test_a_model_calling_a_layer_whose_class_was_made_in_a_function_is_saved_and_loaded(tmp_path, caplog):
    """torch cannot save a guard on a class made inside a function (no file can name it): those guards are left to
    the key (the versions and the model's code), and the graph is a file that a later function loads."""
    x = torch.randn(4, 8)
    with torch.no_grad(), caplog.at_level(logging.WARNING, logger="hf_specvla"):
        first = file_backed(WithFunctionLayer(seed=0), tmp_path)
        out = first(x)
        assert first.compiled == 1 and first.in_memory is None, [r.getMessage() for r in caplog.records]
        assert torch.equal(out, WithFunctionLayer(seed=0)(x))
        other = WithFunctionLayer(seed=1)  # other weights, one architecture: the file, its own weights
        second = file_backed(other, tmp_path)
        assert torch.equal(second(x), other(x)) and second.loaded == 1 and second.compiled == 0
    assert not caplog.records
    # what the dropped guards checked is the key's: a function layer's forward replaced (``kernels.kernelize``)
    kernelized = WithFunctionLayer(seed=0)
    layer = kernelized._kernel_funcs["scaled"]
    layer.forward = types.MethodType(lambda self, x: x, layer)
    assert architecture(kernelized) != architecture(WithFunctionLayer(seed=1)) == architecture(WithFunctionLayer(0))


#: a fresh process: a tiny Llama (weights seeded by argv[2]) decoding with Jacobi drafts through compiled rounds
#: (inductor) whose graphs are files in argv[1]; prints whether it equals eager greedy, and what was loaded
ENGINE_PROCESS = textwrap.dedent(
    """
    import json, logging, sys, torch
    from transformers import LlamaConfig, LlamaForCausalLM
    from hf_specvla import enable_speculation
    from hf_specvla.speculative import JacobiDrafter, compiled_decoding_kwargs
    logging.basicConfig(level=logging.WARNING)
    records = []
    class Keep(logging.Handler):
        def emit(self, record):
            records.append(record.getMessage())
    logging.getLogger("hf_specvla").addHandler(Keep()); logging.getLogger("hf_specvla").setLevel(logging.INFO)
    torch.manual_seed(int(sys.argv[2]))
    config = LlamaConfig(vocab_size=96, hidden_size=32, intermediate_size=64, num_hidden_layers=2,
                         num_attention_heads=4, num_key_value_heads=2, max_position_embeddings=256)
    model = enable_speculation(LlamaForCausalLM(config).eval())
    prompt = torch.randint(3, 96, (1, 9), generator=torch.Generator().manual_seed(0))
    greedy = model.generate(input_ids=prompt, max_new_tokens=12, do_sample=False)
    equal = []
    for _ in range(2):
        out = model.generate(input_ids=prompt, max_new_tokens=12, do_sample=False, assistant_model=JacobiDrafter(),
                             **compiled_decoding_kwargs("cpu"))
        equal.append(bool(torch.equal(out, greedy)))
    print(json.dumps({"equal": equal, "loaded": sum("loaded compiled graph" in m for m in records),
                      "compiled": sum("no graph file" in m for m in records)}))
    """
)


@pytest.mark.slow
@pytest.mark.parametrize("layer_regions", ["off", "on"])
def test_the_engine_loads_its_rounds_from_files_in_a_fresh_process_and_decodes_greedy_tokens(tmp_path, layer_regions):
    """The compiled rounds (acceptance in the graph) and the prefill's model call, saved by one process, are loaded by
    the next without compiling, for a model of other weights too, and both decode greedy's tokens; also with the
    decoder layers compiled once (``regions``: a nested compile region in every graph)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(sys.path), graph_files.FOLDER_ENV: str(tmp_path),
           LAYER_REGIONS_ENV: layer_regions}  # fmt: skip
    runs = []
    for seed in (0, 1):
        done = subprocess.run(
            [sys.executable, "-c", ENGINE_PROCESS, str(tmp_path), str(seed)],
            capture_output=True, text=True, env=env, timeout=900,
        )  # fmt: skip
        assert done.returncode == 0, done.stderr[-3000:]
        runs.append(json.loads(done.stdout.strip().splitlines()[-1]))
    first, second = runs
    assert first["equal"] == [True, True] and first["compiled"] >= 2 and first["loaded"] == 0
    assert second["equal"] == [True, True] and second["compiled"] == 0 and second["loaded"] == first["compiled"]


def test_a_signature_is_the_same_for_a_new_object_of_the_same_kind_in_every_call():
    """A call's helpers made anew every call (a draft head's ``embed`` partial) give the same signature, so that
    their graph is looked up, not compiled again; what differs in kind differs."""
    import enum
    import functools

    from hf_specvla.speculative.graph_files import signature

    class Mode(enum.Enum):
        A = 1
        B = 2

    def first(x):
        return x

    def second(x):
        return x

    holder = type("Holder", (), {})
    assert signature(functools.partial(first, holder())) == signature(functools.partial(first, holder()))
    assert signature(functools.partial(first, holder())) != signature(functools.partial(second, holder()))
    assert signature(Mode.A) != signature(Mode.B) and signature(3) != signature(4)
    assert signature(torch.zeros(2, 3)) != signature(torch.zeros(2, 4)) != signature(torch.zeros(2, 4).double())


def test_a_draft_heads_compiled_round_is_compiled_once_not_at_every_call(tmp_path, monkeypatch, caplog):
    """Every call makes its own drafting helpers; the head's round graph is compiled at the first call only."""
    from transformers import CompileConfig

    from hf_specvla import DraftHead, DraftHeadDrafter, DraftTreeConfig

    from .test_compiled_verification import _model, greedy

    monkeypatch.setenv(graph_files.FOLDER_ENV, str(tmp_path))
    model = _model("llama")
    torch.manual_seed(1)
    head = DraftHead.from_target(model, num_draft_tokens=3).eval()
    config = CompileConfig(backend="eager", fullgraph=True, dynamic=False, mode="default")
    config._compile_all_devices = True
    input_ids = torch.randint(6, 64, (1, 7), generator=torch.Generator().manual_seed(0))
    expected = greedy(model, input_ids)
    compiles = []
    for _ in range(3):
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="hf_specvla"):
            tree = DraftHeadDrafter(head, tree=DraftTreeConfig(top_k=3, depth=4, total_tokens=12))
            out = greedy(model, input_ids, assistant_model=tree, cache_implementation="static", compile_config=config)
        assert torch.equal(out, expected)
        compiles.append(sum("no graph file for its key" in r.getMessage() for r in caplog.records))
    assert compiles[0] > 0 and compiles[1:] == [0, 0], compiles


def test_a_transformers_models_compiled_rounds_are_files_that_a_model_of_its_architecture_loads(
    tmp_path, monkeypatch, caplog
):
    """Whatever the installed transformers hangs on its models (from 5.25 the ``kernels`` package's function layers,
    classes made in a function), a Llama's compiled rounds and prefill are saved as files, none kept in memory for want
    of a file, and another model of its architecture loads them all and decodes its own greedy tokens. The release
    tests (tf520, tflatest) run this one with graph files on, so that a new release cannot drop the route unseen."""
    from hf_specvla import JacobiDrafter
    from hf_specvla.speculative.compiled import reset_compilation

    from .test_compiled_verification import _model, eager_compile_config, greedy

    monkeypatch.setenv(graph_files.FOLDER_ENV, str(tmp_path))
    input_ids = torch.randint(6, 64, (1, 7), generator=torch.Generator().manual_seed(0))
    compiled, loaded = [], []
    for seed in (0, 1):
        reset_compilation()
        model = _model("llama")
        if seed:
            with torch.no_grad():
                for parameter in model.parameters():
                    parameter.add_(0.01 * torch.randn_like(parameter))
        expected = greedy(model, input_ids)
        caplog.clear()
        with caplog.at_level(logging.INFO, logger="hf_specvla"):
            out = greedy(model, input_ids, assistant_model=JacobiDrafter(), cache_implementation="static",
                         compile_config=eager_compile_config())  # fmt: skip
        assert torch.equal(out, expected), seed
        messages = [r.getMessage() for r in caplog.records]
        assert not [m for m in messages if "cannot be saved" in m or "kept in memory" in m], messages
        compiled.append(sum("no graph file for its key" in m for m in messages))
        loaded.append(sum("loaded compiled graph" in m for m in messages))
    reset_compilation()
    assert compiled[0] >= 2 and loaded[0] == 0, (compiled, loaded)
    assert compiled[1] == 0 and loaded[1] == compiled[0], (compiled, loaded)
