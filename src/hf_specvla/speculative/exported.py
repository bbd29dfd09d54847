"""A module's call exported as one graph of ATen operations: what dynamo cannot trace whole, made a function it can.

Some code never traces into one dynamo graph: transformers' output-capturing wrappers around a VLM's image encoder
(``get_image_features``) register forward hooks, enter a lock and read ``inspect.signature`` objects, each a graph
break. A graph with breaks can be compiled in memory, but not saved as a file ([`graph_files`] saves whole graphs
only), so every process traced it again (~3-6 s a batch size for a small policy's encoder on a CPU).

``torch.export`` in its non-strict mode runs that Python as Python (the hooks, the lock, the wrappers) and records the
ATen operations it reaches: one graph, whatever the Python around them. [`export_call`] turns that graph into an
ordinary function of the module's parameters and buffers and the call's tensors ([`ExportedCall`]), which dynamo
traces whole, so that it compiles and saves as a file like the engine's other graphs. Its code is generated in each
process from the module (about half a second to a second for a small encoder): it is never read from a file, and
the digest of that code is part of the graph file's key.

What export fixes, as a compiled graph does: every Python-level decision (the config's layer choices, the input
shapes); so one export per input signature, keyed by it. The weights stay inputs: they are read from the module at
every call (a module retrained with the same architecture reuses the graph; one whose parameter is replaced is read
anew). Code that export refuses (data-dependent control flow, a non-tensor input other than None) keeps the caller's
other route: [`export_call`] returns None.
"""

from __future__ import annotations

import hashlib
import logging
import sys
import types
from collections.abc import Callable
from functools import cache

import torch
import torch.utils._pytree as pytree

logger = logging.getLogger(__name__)


class _Call(torch.nn.Module):
    """``getattr(root, method)(**inputs, **settings)`` as a module's forward (what ``torch.export`` exports)."""

    def __init__(self, root: torch.nn.Module, method: str, settings: dict):
        super().__init__()
        self.root, self.method, self.settings = root, method, settings

    def forward(self, **inputs):
        return getattr(self.root, self.method)(**inputs, **self.settings)


class ExportedCall(torch.nn.Module):
    """A module's call as one exported graph: ``forward(**inputs)`` runs the graph's generated code on the root
    module's current parameters and buffers and the call's tensors, and returns the flat outputs (``unflatten``
    builds the call's own output object from them: a ``ModelOutput``, a tuple...).

    Args:
        root: the module the call reads its parameters and buffers from (a submodule: its graphs read its tensors).
        graph: the exported graph's code as a function ``graph(self, *tensors, *inputs)`` of the parameters, buffers
            and constants in its order, then the call's tensors.
        sources: for each of the graph's leading tensors, where it is: ``("parameter" | "buffer", name in root)``,
            or ``("constant", index)`` into ``constants``.
        constants: tensors the export lifted out of the code (made by the call, not the module's).
        input_names: the call's tensor inputs, in the graph's order.
        out_spec: how the flat outputs make the call's output object.
        digest: the SHA-256 of the graph's code (what a graph file compiled from it is keyed by).
    """

    def __init__(
        self,
        root: torch.nn.Module,
        graph: Callable,
        sources: tuple[tuple[str, str | int], ...],
        constants: list[torch.Tensor],
        input_names: tuple[str, ...],
        out_spec,
        digest: str,
    ):
        super().__init__()
        self.root = root
        self.graph = graph
        self.sources = sources
        for index, tensor in enumerate(constants):
            self.register_buffer(f"constant_{index}", tensor, persistent=False)
        self.input_names = input_names
        self.out_spec = out_spec
        self.digest = digest

    def forward(self, **inputs) -> tuple:
        tensors = []
        for kind, name in self.sources:
            if kind == "parameter":
                tensors.append(self.root.get_parameter(name))
            elif kind == "buffer":
                tensors.append(self.root.get_buffer(name))
            else:
                tensors.append(getattr(self, f"constant_{name}"))
        return tuple(self.graph(None, *tensors, *(inputs[name] for name in self.input_names)))

    def unflatten(self, flat: tuple):
        """The call's own output object from the flat outputs of [`forward`]."""
        return pytree.tree_unflatten(list(flat), self.out_spec)


def export_call(root: torch.nn.Module, method: str, inputs: dict, settings: dict) -> ExportedCall | None:
    """``getattr(root, method)(**inputs, **settings)`` exported as one graph ([`ExportedCall`]), for ``inputs``'
    shapes; None (logged once a method) where export refuses the code or the inputs hold anything but tensors and
    None.

    Args:
        root: the module (e.g. a VLM's base model).
        method: its method's name (``"get_image_features"``).
        inputs: the call's inputs (tensors; None entries are left out, as the call's defaults).
        settings: plain keyword arguments fixed in the graph (``return_dict=True``).
    """
    tensors = {name: value for name, value in inputs.items() if value is not None}
    if not all(isinstance(value, torch.Tensor) for value in tensors.values()):
        _refused(type(root).__name__, method, "an input that is not a tensor")
        return None
    try:
        program = torch.export.export(_Call(root, method, settings), (), tensors, strict=False)
    except Exception as error:  # noqa: BLE001 - any refusal keeps the caller's route
        _refused(type(root).__name__, method, f"{type(error).__name__}: {str(error).splitlines()[0][:200]}")
        return None
    sources, constants, user_inputs = [], [], 0
    for spec in program.graph_signature.input_specs:
        kind = spec.kind.name
        if kind == "USER_INPUT":
            user_inputs += 1
        elif kind in ("PARAMETER", "BUFFER"):
            sources.append((kind.lower(), spec.target.removeprefix("root.")))
        elif kind == "CONSTANT_TENSOR":
            sources.append(("constant", len(constants)))
            constants.append(program.constants[spec.target])
        else:  # a custom object, a token: not a plain function of tensors
            _refused(type(root).__name__, method, f"an input of kind {kind}")
            return None
    # the user inputs' placeholders, in order, are the call's keyword tensors as the program flattens them
    flat, in_spec = pytree.tree_flatten(((), tensors))
    if in_spec != program.call_spec.in_spec or len(flat) != user_inputs:
        _refused(type(root).__name__, method, "inputs it flattens otherwise")
        return None
    code = program.graph_module.graph.python_code(root_module="self")
    digest = hashlib.sha256(code.src.encode()).hexdigest()
    graph = _importable_function(code, digest)
    return ExportedCall(root, graph, tuple(sources), constants, tuple(tensors), program.call_spec.out_spec, digest)


def _importable_function(code, digest: str) -> Callable:
    """The graph's generated code as the function ``forward`` of a module named by its digest, registered in
    ``sys.modules``: a graph file refers to the functions it inlined by module and name, so a later process that
    exports the same code finds it there."""
    name = f"{__name__}.graph_{digest[:24]}"
    module = sys.modules.get(name)
    if module is None:
        module = types.ModuleType(name, "an exported graph's code (hf_specvla.speculative.exported)")
        module.__dict__.update(code.globals)
        exec(compile(code.src, f"<exported graph {digest[:24]}>", "exec"), module.__dict__)  # noqa: S102 - generated
        sys.modules[name] = module
    return module.forward


@cache
def _refused(owner: str, method: str, why: str) -> None:
    """Says once (per reason) that a method is not exported."""
    logger.info("%s.%s is not exported as one graph (%s): compiled with graph breaks, in memory", owner, method, why)
