"""Compiled graphs as files: a graph the engine compiled once is loaded by a later process without dynamo tracing.

Every process used to trace and compile every graph again (a server's warm start: dynamo re-traces its graphs even
when Inductor's cache holds their kernels). torch 2.13's ahead-of-time route saves dynamo's output, its guards and
Inductor's artefacts in one file (``torch.compile(fn, fullgraph=True).aot_compile(...)``, loaded by
``torch.compiler.load_compiled_function``); [`FileBackedFunction`] is a compiled function that takes that route:
per input signature (every tensor's shape, dtype and device, the sizes marked dynamic left out, the cache's type and
layers) it uses the graph it holds, else loads its file, else compiles and saves one.

Where the files live: [`graph_folder`], ``~/.cache/hf_specvla/graphs`` (``$XDG_CACHE_HOME`` respected) for a model on
the CPU, or the folder ``HF_SPECVLA_GRAPH_CACHE`` names; ``off`` compiles in memory as before. A model on a GPU keeps
its graphs in memory unless the variable is set (``on`` or a folder): the route has not run on a GPU yet. A server
given ``--compile-cache DIR`` keeps them in ``DIR/graphs`` ([`graphs_kept_in`]).

What keys a file ([`GraphKey`]), every part a miss when it changes (the log names the parts that differ from the
nearest file of the same function):

* the versions: torch, transformers, ``kernels`` (where installed), Python, the machine, and the code: this package's
  source and the source files of the model's module classes (a policy's or a port's own modeling code);
* the function (its name and bytecode) and its compile settings;
* the model's architecture: its class, its configuration, its modules' classes, every parameter's and buffer's name,
  shape and dtype, its device; the modules it closes over the same;
* the input signature.

**The weights are not part of the key**: they are inputs of the graph, read from the model at every call (checked:
a graph compiled for one policy gives another policy of the same architecture that policy's own tokens), so a policy
retrained or fine-tuned with the same architecture reuses its graphs.

Guards: a file keeps the guards that can be saved ([`portable_guards`]: the inputs' and parameters' shapes, dtypes,
strides and devices, grad mode, autocast and the other ambient state), checked at every call; a call that fails them
compiles anew, from its inputs as marked (a size marked dynamic stays dynamic), and the function keeps that graph
beside the others of the signature ([`GRAPHS_PER_SIGNATURE`]: calls that alternate compile each variant once; the
file holds the newest). What the dropped guards checked (a module's class, its ``forward``, its hooks, the identity of
the model; any guard reaching into a class made inside a function, which no file can name: the ``kernels`` package's
function layers on transformers >= 5.25's Llama-family models) the engine checks itself: the versions and the
architecture in the key (a layer's ``forward`` replaced by ``kernels.kernelize`` included), and a model's graphs
belong to its decoder (a copy gets its own).

A file is written atomically (a temporary file in the same folder, then renamed: two processes compiling the same key
both end with a whole file) and carries the SHA-256 of its content; a file that is truncated, damaged or unreadable is
set aside (renamed ``<name>.damaged-<UTC time>``) with a warning and compiled again; a folder that cannot be written
keeps its graphs in memory, with one warning.
"""

from __future__ import annotations

import enum
import functools
import hashlib
import importlib
import importlib.metadata
import inspect
import json
import logging
import os
import pickle
import platform
import sys
import tempfile
import time
import types
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path

import torch

logger = logging.getLogger(__name__)

#: the environment variable that moves the graph files' folder, or turns them off (``off``, ``0``, ``none``)
FOLDER_ENV = "HF_SPECVLA_GRAPH_CACHE"
_OFF = frozenset({"off", "0", "none", "false", "no"})
_ON = frozenset({"on", "1", "default", "true", "yes"})
#: a file's first line: this tag, a space, the SHA-256 of the rest
_MAGIC = b"hf_specvla-graph-v1"
#: the attribute of a class the engine made at run time (``generation.speculative_class``) that holds the class it was
#: made from
MIXED_FROM = "_hf_specvla_mixed_from"
#: a damaged file is renamed ``<name><DAMAGED><UTC time>`` beside it (never deleted)
DAMAGED = ".damaged-"
#: guard types torch cannot save in a file
_UNSAVED_GUARDS = frozenset(
    {
        "DICT_VERSION",
        "NN_MODULE",
        "ID_MATCH",
        "FUNCTION_MATCH",
        "CLASS_MATCH",
        "MODULE_MATCH",
        "CLOSURE_MATCH",
        "WEAKREF_ALIVE",
    }
)


#: guards on a value's type
_TYPE_GUARDS = frozenset({"TYPE_MATCH", "BUILTIN_MATCH", "FAKE_SCRIPT_TYPE_MATCH"})


def _of_local_class(value) -> bool:
    """Whether ``value`` is a class made inside a function, or an object of one (``<locals>`` in the class's qualified
    name: no module holds it, so no file can name it), e.g. the ``kernels`` package's function layers
    (``_create_func_module.<locals>.Func``), which transformers >= 5.25 hangs on Llama-family models."""
    cls = value if isinstance(value, type) else type(value)
    return "<locals>" in cls.__qualname__


def graph_folder(device_type: str = "cpu") -> Path | None:
    """The folder of graph files for models on ``device_type``: ``$HF_SPECVLA_GRAPH_CACHE`` when it names one; the
    default folder (``$XDG_CACHE_HOME/hf_specvla/graphs``, ``~/.cache/hf_specvla/graphs``) when it is ``on`` (``1``,
    ``default``), or unset and the model is on the CPU (the route is on by default where it is tested; a GPU's graphs
    stay in memory until it is measured there); None, graphs compiled in memory only, when it is ``off`` (``0``,
    ``none``) or unset for a model elsewhere. Inside [`graphs_kept_in`] its folder replaces the variable's or the
    default one (on and off stay the variable's and the device's). Its location is logged once."""
    value = (os.environ.get(FOLDER_ENV) or "").strip()
    if value.lower() in _OFF or (not value and device_type != "cpu"):
        return None
    if _FOLDER_OVERRIDE.get() is not None:
        folder = _FOLDER_OVERRIDE.get()
    elif not value or value.lower() in _ON:
        folder = Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "hf_specvla" / "graphs"
    else:
        folder = Path(value).expanduser()
    _log_folder(str(folder))
    return folder


#: the folder [`graphs_kept_in`] sets for the code it runs (this thread's, this context's), else None
_FOLDER_OVERRIDE: ContextVar[Path | None] = ContextVar("hf_specvla_graph_folder", default=None)


@contextmanager
def graphs_kept_in(folder: str | os.PathLike) -> Iterator[Path]:
    """The graph files of the models first compiled inside the block go to ``folder`` instead of
    ``$HF_SPECVLA_GRAPH_CACHE``'s or the default one (``hf-specvla serve --compile-cache DIR``: ``DIR/graphs``),
    where graph files are on ([`graph_folder`]). A model's graphs keep the folder they were first made in."""
    token = _FOLDER_OVERRIDE.set(Path(folder).expanduser())
    try:
        yield _FOLDER_OVERRIDE.get()
    finally:
        _FOLDER_OVERRIDE.reset(token)


@functools.cache
def _log_folder(folder: str) -> None:
    logger.info("compiled graphs are kept as files in %s (%s=off: in memory only)", folder, FOLDER_ENV)


@functools.cache
def _read_only_warning(folder: str, error: str) -> None:
    logger.warning("cannot write compiled graphs to %s (%s): they are kept in memory only", folder, error)


# --------------------------------------------------------------------------------------------------- the key
@functools.cache
def _source_digest(path: str) -> str:
    try:
        return hashlib.sha256(Path(path).read_bytes()).hexdigest()[:16]
    except OSError:
        return "unreadable"


@functools.cache
def _engine_digest() -> str:
    """A digest of this package's source files (the engine's functions are traced into the graphs)."""
    digest = hashlib.sha256()
    for path in sorted(Path(__file__).resolve().parent.rglob("*.py")):
        digest.update(path.name.encode() + b"\0" + path.read_bytes())
    return digest.hexdigest()[:16]


def _version_of(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def environment() -> dict:
    """The versions every graph depends on."""
    import transformers

    return {
        "torch": torch.__version__,
        "transformers": transformers.__version__,
        # the hub-kernel layers transformers >= 5.25 hangs on its models: their code is traced into the graphs
        "kernels": _version_of("kernels"),
        "python": ".".join(map(str, sys.version_info[:3])),
        "machine": platform.machine(),
        "engine": _engine_digest(),
    }


def architecture(module: torch.nn.Module) -> dict:
    """What a module's graphs depend on besides its weights' values: its class and configuration, every submodule's
    class and the source of its code (and of the layers held outside submodules, [`_layers`]), a ``forward`` set on
    one of them, every parameter's and buffer's name, shape and dtype, its device."""
    config = getattr(module, "config", None)
    config_text = config.to_json_string(use_diff=False) if hasattr(config, "to_json_string") else repr(config)
    config_text = (
        json.dumps(
            {k: v for k, v in json.loads(config_text).items() if k not in ("_name_or_path", "transformers_version")},
            sort_keys=True,
        )
        if config_text.startswith("{")
        else config_text
    )
    layers = dict(_layers(module))
    classes = sorted({type(m) for m in layers.values()}, key=lambda c: (c.__module__, c.__qualname__))
    code = {}
    for cls in classes:
        try:
            code[f"{cls.__module__}.{cls.__qualname__}"] = _source_digest(inspect.getsourcefile(cls) or "")
        except TypeError:  # a built-in class
            code[f"{cls.__module__}.{cls.__qualname__}"] = "built-in"
    tensors = hashlib.sha256()
    for name, tensor in [*module.named_parameters(), *module.named_buffers()]:
        tensors.update(f"{name}:{tuple(tensor.shape)}:{tensor.dtype}:{tensor.device};".encode())
    tree = hashlib.sha256("\n".join(f"{n}:{type(m).__qualname__}{_forward_of(m)}" for n, m in layers.items()).encode())
    return {
        "class": f"{type(module).__module__}.{type(module).__qualname__}",
        "config": hashlib.sha256(config_text.encode()).hexdigest()[:16],
        "code": hashlib.sha256(json.dumps(code, sort_keys=True).encode()).hexdigest()[:16],
        "modules": tree.hexdigest()[:16],
        "tensors": tensors.hexdigest()[:16],
    }


def _layers(module: torch.nn.Module) -> Iterator[tuple[str, torch.nn.Module]]:
    """``module.named_modules()`` and the layers its modules hold outside their submodules, in a dictionary
    attribute (the ``kernels`` package's function layers, ``_kernel_funcs``, on Llama-family models from
    transformers 5.25: ``kernelize`` replaces their ``forward``), named ``<module>.<attribute>.<key>``."""
    for name, child in module.named_modules():
        yield name, child
        for attribute, value in vars(child).items():
            if attribute != "_modules" and isinstance(value, dict):
                for key, layer in value.items():
                    if isinstance(layer, torch.nn.Module):
                        yield f"{name}.{attribute}.{key}", layer


def _forward_of(layer: torch.nn.Module) -> str:
    """The ``forward`` set on ``layer`` itself (``kernels.kernelize``, a hook library), as ``:<module>.<name>``;
    empty when it is its class's."""
    forward = vars(layer).get("forward")
    if forward is None:
        return ""
    function = getattr(forward, "__func__", forward)
    return f":{getattr(function, '__module__', '?')}.{getattr(function, '__qualname__', type(function).__qualname__)}"


def _dims(tensor: torch.Tensor) -> tuple:
    """The tensor's sizes, -1 where marked dynamic (``mark_dynamic`` or ``maybe_mark_dynamic``)."""
    dynamic = {*getattr(tensor, "_dynamo_dynamic_indices", ()), *getattr(tensor, "_dynamo_weak_dynamic_indices", ())}
    return tuple(-1 if i in dynamic else s for i, s in enumerate(tensor.shape))


#: values a signature holds by value (anything else by what it is: its type, a function's name)
_PLAIN = (bool, int, float, str, bytes, type(None), torch.dtype, torch.device, enum.Enum)


def signature(value) -> object:
    """A hashable description of a call's inputs as far as its graph depends on them, the same in every process:
    tensors by shape (the sizes marked dynamic as -1), dtype and device; mappings by their items in key order,
    sequences item by item; a cache by its type and its layers' types and first keys' shape; plain values (numbers,
    strings, dtypes, devices, enum members) by value; a function by its qualified name, a ``functools.partial`` by its
    function and arguments; any other object (a module, a helper holding tensors) by its type: what it holds is the
    guards' (its tensors' shapes, its attributes' values), checked at every call."""
    if isinstance(value, torch.Tensor):
        return ("T", _dims(value), value.dtype, value.device)
    if isinstance(value, dict):
        return tuple(sorted((str(k), signature(v)) for k, v in value.items()))
    if isinstance(value, (list, tuple)):
        return (type(value).__name__, *map(signature, value))
    if isinstance(value, _PLAIN):
        return ("value", type(value).__qualname__, value)
    if isinstance(value, functools.partial):
        return ("partial", signature(value.func), signature(value.args), signature(value.keywords))
    if isinstance(value, (types.FunctionType, types.BuiltinFunctionType, types.MethodType)):
        return ("function", getattr(value, "__module__", None), value.__qualname__)
    layers = getattr(value, "layers", None)
    if isinstance(layers, list):  # a transformers Cache
        keys = getattr(layers[0], "keys", None) if layers else None
        shape = tuple(keys.shape) if isinstance(keys, torch.Tensor) else None
        return ("cache", type(value).__name__, tuple(type(layer).__name__ for layer in layers), shape)
    return ("object", type(value).__module__, type(value).__qualname__)


def _text(value) -> str:
    return repr(value).replace("torch.", "")


# --------------------------------------------------------------------------------------------------- the guards
def with_guard_filter(settings: dict, guard_filter: Callable) -> dict:
    """``torch.compile`` settings (a ``CompileConfig``'s ``to_dict()``) with ``guard_filter`` as their
    ``guard_filter_fn``: torch takes it among the backend's ``options``, which it refuses beside a ``mode``, so an
    inductor mode is turned into its options (``torch._inductor.list_mode_options``); another backend's ``"default"``
    mode is dropped. Another backend's other modes keep every guard (the settings unchanged)."""
    settings = dict(settings)
    mode, backend = settings.get("mode"), settings.get("backend", "inductor")
    options = dict(settings.get("options") or {})
    if mode not in (None, "default"):
        if backend != "inductor":
            return settings
        from torch._inductor import list_mode_options

        options = {**list_mode_options(mode), **options}
    settings["mode"], settings["options"] = None, {**options, "guard_filter_fn": guard_filter}
    return settings


def portable_guards(keep: Callable | None = None) -> Callable:
    """A ``guard_filter_fn`` keeping the guards ``keep`` keeps (all when None) that torch can save in a file: none on
    globals, none of the identity-type guards ([`_UNSAVED_GUARDS`])."""

    def filter_guards(entries) -> list[bool]:
        kept = keep(entries) if keep is not None else [True] * len(entries)
        # an object of a class made in a function: neither its type nor what is read through it (its methods' code)
        local = {entry.name for entry in entries if entry.has_value and _of_local_class(entry.value)}
        through_local = [f"type({name})" for name in local]
        return [
            bool(k)
            and not entry.is_global
            and entry.guard_type not in _UNSAVED_GUARDS
            and not _UNSAVED_GUARDS.intersection(entry.derived_guard_types or ())
            and not (entry.guard_type in _TYPE_GUARDS and entry.name in local)
            and not any(text in entry.name for text in through_local)
            for k, entry in zip(kept, entries)
        ]

    return filter_guards


# --------------------------------------------------------------------------------------------------- the files
class GraphStore:
    """Reads and writes graph files in one folder (see the module docstring): ``<function>-<key digest>.graph`` and
    its record ``.json`` (the key's parts, to name what differs on a miss)."""

    def __init__(self, folder: Path):
        self.folder = Path(folder)
        self.writable = True

    def path(self, name: str, parts: dict) -> Path:
        digest = hashlib.sha256(json.dumps(parts, sort_keys=True, default=_text).encode()).hexdigest()[:24]
        return self.folder / f"{name}-{digest}.graph"

    def read(self, path: Path) -> bytes | None:
        """The content of ``path`` when it is whole (its SHA-256 matches), else None: missing (None, silently) or
        damaged (set aside with a warning)."""
        try:
            data = path.read_bytes()
        except FileNotFoundError:
            return None
        except OSError as error:
            logger.warning("cannot read compiled graph %s (%s): compiling it again", path, error)
            return None
        header, _, payload = data.partition(b"\n")
        tag, _, digest = header.partition(b" ")
        if tag != _MAGIC or hashlib.sha256(payload).hexdigest().encode() != digest:
            self.set_aside(path, "truncated or damaged (its checksum does not match)")
            return None
        try:  # a file's modification time: when it was last written or loaded ([`remove_stale`] reads it)
            os.utime(path)
        except OSError:
            pass
        return payload

    def set_aside(self, path: Path, why: str) -> None:
        """Renames a damaged file ``<name>.damaged-<UTC time>`` (never deleted) and says so."""
        aside = path.with_name(path.name + DAMAGED + time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()))
        try:
            os.replace(path, aside)
        except OSError:
            aside = None
        logger.warning(
            "compiled graph %s is %s: %s; compiling it again",
            path,
            why,
            f"set aside as {aside.name}" if aside else "it could not be moved",
        )

    def write(self, path: Path, payload: bytes, parts: dict) -> None:
        """Writes ``payload`` to ``path`` atomically (with its checksum) and its key's record beside it; a folder that
        cannot be written is warned about once and the graph kept in memory."""
        if not self.writable:
            return
        header = _MAGIC + b" " + hashlib.sha256(payload).hexdigest().encode() + b"\n"
        try:
            self.folder.mkdir(parents=True, exist_ok=True)
            for target, data in (
                (path.with_suffix(".json"), json.dumps(parts, indent=1, default=_text).encode()),
                (path, header + payload),
            ):
                with tempfile.NamedTemporaryFile(dir=self.folder, prefix=".tmp-", delete=False) as file:
                    file.write(data)
                    file.flush()
                    os.fsync(file.fileno())
                os.replace(file.name, target)
        except OSError as error:
            self.writable = False
            _read_only_warning(str(self.folder), f"{type(error).__name__}: {error.strerror or error}")

    def nearest_difference(self, name: str, parts: dict) -> list[str]:
        """The key parts that differ between ``parts`` and the nearest record of ``name``'s files (for a miss's log);
        empty when there is none."""
        best, mine = None, json.loads(json.dumps(parts, default=_text))
        for record in self.folder.glob(f"{name}-*.json"):
            try:
                other = json.loads(record.read_text())
            except (OSError, ValueError):
                continue
            differ = sorted(_differences(mine, other))
            if best is None or len(differ) < len(best):
                best = differ
        return best or []


def remove_stale(folder: str | os.PathLike, unused_days: float | None = None) -> int:
    """Removes from ``folder`` the graph files no process of this environment can load: those whose versions or engine
    code ([`environment`]: torch, transformers, ``kernels``, Python, the machine, this package's engine source) differ
    from this process's, and, when ``unused_days`` is given, those neither written nor loaded for that many days.
    Returns how many graphs it removed. For a folder one environment owns (the tests' under tox): a folder that
    environments share keeps the others' graphs, which this would remove."""
    folder, current = Path(folder), json.loads(json.dumps(environment(), default=_text))
    oldest = time.time() - unused_days * 86400 if unused_days is not None else None
    removed = 0
    for record in folder.glob("*.json"):
        graph = record.with_suffix(".graph")
        try:
            parts = json.loads(record.read_text())
            stale = any(parts.get(name) != value for name, value in current.items())
            stale = stale or (oldest is not None and graph.stat().st_mtime < oldest)
        except (OSError, ValueError):
            stale = not graph.exists()  # a record without its graph
        if stale:
            for path in (graph, record):
                path.unlink(missing_ok=True)
            removed += 1
    if removed:
        logger.info("removed %d stale compiled graph(s) from %s", removed, folder)
    return removed


def _differences(mine: dict, other: dict, prefix: str = "") -> set[str]:
    found = set()
    for key in set(mine) | set(other):
        a, b = mine.get(key), other.get(key)
        if isinstance(a, dict) and isinstance(b, dict):
            found |= _differences(a, b, f"{prefix}{key}.")
        elif a != b:
            found.add(f"{prefix}{key}")
    return found


# --------------------------------------------------------------------------------------------------- the function
#: the graphs a [`FileBackedFunction`] keeps per input signature, each compiled for other guards (as dynamo keeps a
#: code object's graphs, up to its recompile limit): a call runs the first whose guards it passes, so calls that
#: alternate between what the guards tell apart (grad mode on and off, a hook added and removed) compile each once
GRAPHS_PER_SIGNATURE = 8


class FileBackedFunction:
    """``torch.compile(function, **settings)`` whose graphs are files (see the module docstring): a graph per input
    signature, loaded from its file when there is one, else compiled ahead of time and saved; a call that fails its
    guards gets one of its own beside it ([`GRAPHS_PER_SIGNATURE`]).

    Args:
        function: a plain function (its closure's modules are the graph's external data: a file never holds a model).
        settings: ``torch.compile``'s keyword arguments; ``fullgraph`` is forced (the route saves whole graphs only).
        key: what the graphs depend on besides the inputs' signature (the versions, the architecture; see
            [`GraphKey`]); ``name`` is the files' prefix.
        store: where the files are.
        guard_filter: the guards the graphs would keep in memory (None: all); only the portable ones are kept.
    """

    def __init__(
        self,
        function: Callable,
        settings: dict,
        key: dict,
        store: GraphStore,
        name: str | None = None,
        guard_filter: Callable | None = None,
    ):
        self.name = name or function.__code__.co_name
        # the modules it closes over: the graph's external data, a file never holds them; a model whose class the
        # engine mixed (``speculative_class``: made at run time, no name a file can hold) as a view of its own class
        cells = function.__closure__ or ()
        contents = [_plain_view(cell.cell_contents) for cell in cells]
        self.function = types.FunctionType(
            function.__code__,
            function.__globals__,
            function.__name__,
            function.__defaults__,
            tuple(types.CellType(value) for value in contents) or None,
        )
        self.function.__kwdefaults__ = function.__kwdefaults__
        self.external = {
            var: value
            for var, value in zip(function.__code__.co_freevars, contents)
            if isinstance(value, torch.nn.Module)
        }
        #: torch.compile's settings in memory (the function's own guards), for a graph that cannot be saved
        self.memory_settings = dict(settings) if guard_filter is None else with_guard_filter(settings, guard_filter)
        self.original = function
        #: None while no graph failed to save; else the function compiled in memory (dynamo's cache), used for every
        #: input from then on
        self.in_memory: Callable | None = None
        settings = with_guard_filter({**settings, "fullgraph": True}, portable_guards(guard_filter))
        self.settings = settings
        self.key = {
            **key,
            "function": f"{function.__module__}.{self.name}",
            "bytecode": hashlib.sha256(function.__code__.co_code).hexdigest()[:16],
            "settings": {k: v for k, v in settings.items() if k != "options"}
            | {"options": sorted(k for k in (settings.get("options") or {}) if k != "guard_filter_fn")},
            "closure": {
                var: architecture(cell.cell_contents) if var in self.external else _closure_value(cell.cell_contents)
                for var, cell in zip(function.__code__.co_freevars, cells)
            },
        }
        self.store = store
        #: input signature -> its graphs, each for other guards, the most recently used first
        self.graphs: dict[object, list[Callable]] = {}
        self.compile_seconds = 0.0
        self.loaded = 0
        self.compiled = 0

    def __deepcopy__(self, memo) -> FileBackedFunction:
        """Itself: a deep copy of a model copies its decoder, which the copy replaces by its own at its first call
        (``SpeculativeDecoder.of``); the graphs stay the original's (loaded graphs hold torch objects no copy takes)."""
        return self

    def __call__(self, *args, **kwargs):
        if self.in_memory is not None:
            return self.in_memory(*args, **kwargs)
        key = signature((args, kwargs))
        graphs = self.graphs.get(key)
        if graphs is None:
            graph = self._load_or_compile(args, kwargs, self._parts(key))
            if graph is None:  # it cannot be saved: in memory from now on
                return self.in_memory(*args, **kwargs)
            graphs = self.graphs[key] = [graph]
        marks = _unmark_dynamic((args, kwargs))  # what a loaded graph's guards expect (see _compile)
        for index, graph in enumerate(graphs):  # the most recently used first
            if graph.guard_check(*args, **kwargs):
                if index:
                    graphs.insert(0, graphs.pop(index))
                return graph(*args, **kwargs)
        # what the key leaves to the guards (a parameter swapped, grad mode, a hook): none of its graphs passes
        logger.info(
            "compiling %s again: a call failed its graph's guards (%s)",
            self.name,
            _failed_guard(graphs[0], args, kwargs),
        )
        # traced from the inputs as marked, as the key says (a dimension marked dynamic stays so: traced from unmarked
        # inputs, the graph would hold this call's size under a key for every size)
        _mark_dynamic_again(marks)
        graph = self._compile(args, kwargs, self._parts(key))
        if graph is None:
            return self.in_memory(*args, **kwargs)
        _unmark_dynamic((args, kwargs))
        graphs.insert(0, graph)
        del graphs[GRAPHS_PER_SIGNATURE:]
        return graph(*args, **kwargs)

    def _parts(self, inputs) -> dict:
        return {**self.key, "inputs": inputs}

    def _load_or_compile(self, args: tuple, kwargs: dict, parts: dict):
        """The graph for these inputs from its file, else compiled (and saved)."""
        path = self.store.path(self.name, parts)
        payload = self.store.read(path)
        if payload is not None:
            start = time.perf_counter()
            graph = self._deserialize(payload, path)
            if graph is not None:
                self.loaded += 1
                self.compile_seconds += time.perf_counter() - start
                logger.info("loaded compiled graph %s in %.2f s", path.name, time.perf_counter() - start)
                return graph
        else:
            differ = self.store.nearest_difference(self.name, parts)
            logger.info(
                "compiling %s: no graph file for its key%s",
                self.name,
                f" (the nearest file differs in {', '.join(differ)})" if differ else "",
            )
        return self._compile(args, kwargs, parts)

    def _compile(self, args: tuple, kwargs: dict, parts: dict):
        """Compiles the graph ahead of time, saves it, and returns it as loaded from what was saved (so that this
        process runs what a later one will: a graph loaded from bytes checks its guards as a file's does; e.g. it
        expects no dynamic-dimension marks on its inputs)."""
        start = time.perf_counter()
        settings = {**self.settings, "options": dict(self.settings["options"])}  # torch pops the guard filter from it
        from torch._dynamo.exc import PackageError

        try:
            compiled = torch.compile(self.function, **settings).aot_compile((args, kwargs))
        # what it reaches cannot be saved (an object torch cannot pickle in its guards' state: e.g. a model's forward
        # replaced on the instance by a function closing over the model): compiled in memory, as without files
        except (PackageError, pickle.PicklingError, TypeError) as error:
            logger.warning(
                "compiled graph %s cannot be saved as a file (%s: %s): compiled in memory",
                self.name,
                type(error).__name__,
                str(error).splitlines()[0][:200] if str(error) else "",
            )
            self.in_memory = torch.compile(self.original, **self.memory_settings)
            return None
        self.compiled += 1
        try:
            payload = pickle.dumps(
                {
                    "graph": type(compiled).serialize(compiled, dict(self.external)).serialized_data,
                    "modules": self._modules_referenced(compiled),
                }
            )
        except Exception as error:  # noqa: BLE001 - torch refusing to save a graph: it is used from memory
            logger.warning("compiled graph %s kept in memory only: torch cannot save it (%s)", self.name, error)
            compiled.disable_guard_check()
            self.compile_seconds += time.perf_counter() - start
            return compiled
        graph = self._deserialize(payload, None)
        self.store.write(self.store.path(self.name, parts), payload, parts)
        self.compile_seconds += time.perf_counter() - start
        return graph

    def _deserialize(self, payload: bytes, path: Path | None):
        """A graph from a file's content; None (the file set aside) when it cannot be loaded."""
        from torch._dynamo.aot_compile import AOTCompiledFunction
        from torch._guards import TracingContext, tracing

        try:
            content = pickle.loads(payload)
            scope = {**self.function.__globals__}
            scope.update({ref: importlib.import_module(name) for ref, name in content["modules"].items()})
            # (torch 2.13 unpickles a nested compile region's guards, see ``regions``, with sources that install a
            # guard as they are made, which needs a tracing context: an empty one, dropped after)
            with tracing(TracingContext(None)):
                graph = AOTCompiledFunction.deserialize(content["graph"], scope, dict(self.external))
        except Exception as error:  # noqa: BLE001 - any failure to load is a damaged file: compiled again
            if path is None:
                raise
            self.store.set_aside(path, f"unreadable ({type(error).__name__}: {str(error)[:200]})")
            return None
        graph.disable_guard_check()  # checked by __call__, once a call
        return graph

    def _modules_referenced(self, graph) -> dict[str, str]:
        """The Python modules the graph's code reads under names dynamo made up while it traced (``___module_<name>
        _<id>``: installed in the traced function's globals in this process, not saved by torch 2.13), by their
        import names, so that a later process can provide them."""
        refs = graph._artifacts.runtime_env.external_refs
        scope = self.function.__globals__
        return {
            ref: scope[ref].__name__
            for ref in refs
            if ref.startswith("___module_") and inspect.ismodule(scope.get(ref))
        }


def _failed_guard(graph, args: tuple, kwargs: dict) -> str:
    """The first guard of ``graph`` that a call with ``args`` / ``kwargs`` fails, as torch words it (for the log)."""
    try:
        f_locals = graph.prepare_f_locals(*args, **kwargs)
        return " ".join(str(graph._artifacts.guard_manager.check_verbose(f_locals).verbose_code_parts).split())[:300]
    except Exception as error:  # noqa: BLE001 - a diagnosis only
        return f"unknown: {type(error).__name__}"


def _plain_view(value):
    """``value``, or for a model whose class the engine made (``enable_speculation``'s class, made at run time: no
    module holds it, [`MIXED_FROM`] names the class it was made from) a view of it as that class: an object of the
    original class sharing the model's ``__dict__`` (its modules, parameters, buffers, hooks and settings: any change
    to the model is the view's), so that a graph traced through it names an importable class."""
    original = type(value).__dict__.get(MIXED_FROM)
    if original is None:
        return value
    view = object.__new__(original)
    view.__dict__ = value.__dict__
    return view


def _closure_value(value) -> str:
    """A value a compiled function closes over, as its key holds it (traced into the graph as a constant): by its
    ``repr`` when that names no memory address, else by its type and, for a tensor, its shape, dtype and device."""
    if isinstance(value, torch.Tensor):
        return f"tensor{tuple(value.shape)}:{value.dtype}:{value.device}"
    text = repr(value)
    return f"<{type(value).__qualname__}>" if " at 0x" in text else text


#: the attributes ``torch._dynamo.mark_dynamic`` sets on a tensor
_MARKS = ("_dynamo_", "_has_dynamo_dim_marking", "_specialize_on")


def _unmark_dynamic(value, removed: list | None = None) -> list[tuple[torch.Tensor, str, object]]:
    """Drops dynamo's dynamic-dimension marks from the tensors in ``value`` (nested in mappings and sequences): a
    graph loaded from a file was traced from marked inputs but its guards expect none. Returns what it dropped,
    ``(tensor, attribute, value)`` each ([`_mark_dynamic_again`])."""
    removed = [] if removed is None else removed
    if isinstance(value, torch.Tensor):
        for mark in [name for name in vars(value) if name.startswith(_MARKS)]:
            removed.append((value, mark, getattr(value, mark)))
            delattr(value, mark)
    elif isinstance(value, dict):
        for item in value.values():
            _unmark_dynamic(item, removed)
    elif isinstance(value, (list, tuple)):
        for item in value:
            _unmark_dynamic(item, removed)
    return removed


def _mark_dynamic_again(marks: list[tuple[torch.Tensor, str, object]]) -> None:
    """Puts back the marks [`_unmark_dynamic`] dropped."""
    for tensor, name, value in marks:
        setattr(tensor, name, value)
