"""Draft trees: drafted tokens with parents, verified by the target in one forward.

A [`DraftTree`] hangs below the *root*, the last token whose target logits will be known in the verification
forward (the last prompt token at the prefill, the last emitted token afterwards). Node ``i`` holds a drafted
token, the index of its parent (``-1`` = a child of the root) and the name of the drafter that proposed it.
Nodes are stored parents-first (``parents[i] < i``), so one pass in index order visits every parent before its
children. A chain of k drafts is a tree of width 1.

What verification needs is derived here, once per tree (Medusa's ``generate_medusa_buffers`` idea, as data):

* ``depths`` ``[N]``: 0 for the root's children; node i is fed at position ``root_position + 1 + depth``;
* ``ancestor_or_self`` ``[N, N]`` bool: row i is True at i and at every ancestor of i. It is the tree's attention
  mask (a node attends to its ancestors and itself, never to siblings or cousins) and it turns path questions
  ("does every node on the path pass?", "total bin distance along the path") into one matrix product.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import InitVar, dataclass, field
from functools import cached_property

import torch


@dataclass
class DraftTree:
    """Drafted tokens arranged as a tree below the root (see module docstring).

    The structure (parents, depths) is also kept on the host, so that deriving masks, cutting or merging trees never
    waits for the device; the drafted tokens too when the tree was built from host lists ([`from_lists`]). A tree
    built on the device (a draft head's) may leave its parents there (``host_parents`` None): what verification needs
    (depths, the tree mask) is then derived on the device, and the host copies arrive with the verification's one read
    ([`accept_trees`]); ``depth_bound`` tells, meanwhile, how deep it can be.

    Args:
        token_ids: ``[N]`` int64 drafted token ids.
        parents: ``[N]`` int64 parent node index, ``-1`` for the root's children; ``parents[i] < i``.
        sources: ``N`` names of the drafter that proposed each node (for statistics).
        host_parents: ``parents`` on the host, or None (read from ``parents`` here, or with ``structure_on_device``
            when first needed: [`parent_list`]).
        token_list: ``token_ids`` on the host, or None (read when first needed: [`host_tokens`]).
        structure_on_device: leave the parents on the device (a drafter's tree: verification derives what it needs
            there and the verification's read brings them to the host).
        depth_bound: for a tree whose parents stay on the device, at most how deep it is (its longest path's length);
            None: ``N``.
    """

    token_ids: torch.Tensor
    parents: torch.Tensor
    sources: list[str] = field(default_factory=list)
    host_parents: list[int] | None = field(default=None, repr=False, compare=False)
    token_list: list[int] | None = field(default=None, repr=False, compare=False)
    structure_on_device: InitVar[bool] = False
    depth_bound: int | None = field(default=None, repr=False, compare=False)

    def __post_init__(self, structure_on_device: bool):
        if self.token_ids.ndim != 1 or self.parents.shape != self.token_ids.shape:
            raise ValueError(
                f"DraftTree needs token_ids and parents of the same shape [N], got {tuple(self.token_ids.shape)} and "
                f"{tuple(self.parents.shape)}"
            )
        n = self.token_ids.shape[0]
        if not self.sources:
            self.sources = ["draft"] * n
        if len(self.sources) != n:
            raise ValueError(f"DraftTree has {n} nodes but {len(self.sources)} sources")
        if self.host_parents is not None:
            self._check_parents(self.host_parents)
        elif not structure_on_device:
            self.parent_list  # noqa: B018 (read and checked now)

    @staticmethod
    def _check_parents(parents: list[int]) -> None:
        if any(not -1 <= parent < i for i, parent in enumerate(parents)):
            raise ValueError(f"DraftTree parents must satisfy -1 <= parents[i] < i, got {parents}")

    @property
    def parent_list(self) -> list[int]:
        """The parents on the host (read from the device once, the first time, for a tree that left them there)."""
        if self.host_parents is None:
            parents = self.parents.tolist()
            self._check_parents(parents)
            self.host_parents = parents
        return self.host_parents

    def knows_structure(self) -> bool:
        """Whether the parents are on the host (deriving the structure reads nothing from the device)."""
        return self.host_parents is not None

    # ----------------------------------------------------------------- building
    @classmethod
    def from_lists(
        cls, token_ids: Sequence[int], parents: Sequence[int], sources: list[str], device: torch.device | str = "cpu"
    ) -> DraftTree:
        """A tree from host lists (kept as its host copies: nothing is read back from the device)."""
        tokens, parent_list = [int(t) for t in token_ids], [int(p) for p in parents]
        return cls(
            torch.tensor(tokens, dtype=torch.long, device=device),
            torch.tensor(parent_list, dtype=torch.long, device=device),
            sources,
            parent_list,
            tokens,
        )

    @classmethod
    def chain(cls, token_ids: torch.Tensor, source: str) -> DraftTree:
        """A chain of the drafted ``token_ids`` ``[N]`` (node i below node i - 1), tokens left on the device (the
        verification's read brings them to the host), its structure known on the host."""
        num_nodes = token_ids.shape[0]
        parents = torch.arange(-1, num_nodes - 1, device=token_ids.device)
        return cls(token_ids, parents, [source] * num_nodes, list(range(-1, num_nodes - 1)))

    @classmethod
    def empty(cls, device: torch.device | str = "cpu") -> DraftTree:
        return cls.from_lists([], [], [], device)

    @classmethod
    def from_paths(cls, paths: Iterable[Sequence[int]], source: str, device: torch.device | str = "cpu") -> DraftTree:
        """A tree (a trie: shared prefixes become one node) from root-to-leaf token sequences."""
        tokens, parents, sources = [], [], []
        index: dict[tuple[int, ...], int] = {}  # path prefix -> node
        for path in paths:
            parent = -1
            for depth in range(len(path)):
                key = tuple(int(t) for t in path[: depth + 1])
                if key not in index:
                    index[key] = len(tokens)
                    tokens.append(key[-1])
                    parents.append(parent)
                    sources.append(source)
                parent = index[key]
        return cls.from_lists(tokens, parents, sources, device)

    @property
    def num_nodes(self) -> int:
        return self.token_ids.shape[0]

    def __len__(self) -> int:
        return self.num_nodes

    @property
    def host_tokens(self) -> list[int]:
        """The drafted tokens on the host (read from the device once, the first time, for a tree built there)."""
        if self.token_list is None:
            self.token_list = self.token_ids.tolist()
        return self.token_list

    # ----------------------------------------------------------------- derived buffers
    @cached_property
    def depth_list(self) -> list[int]:
        """Depth of each node (0 = child of the root), on the host."""
        depths: list[int] = []
        for parent in self.parent_list:
            depths.append(0 if parent < 0 else depths[parent] + 1)
        return depths

    @cached_property
    def depths(self) -> torch.Tensor:
        """``[N]`` int64 depth of each node (0 = child of the root)."""
        if not self.knows_structure():  # on the device: the ancestors each node has
            return self.ancestor_or_self.sum(dim=-1) - 1
        return torch.tensor(self.depth_list, dtype=torch.long, device=self.token_ids.device)

    @cached_property
    def ancestor_or_self(self) -> torch.Tensor:
        """``[N, N]`` bool: ``[i, j]`` is True when node j is node i or one of its ancestors."""
        n = self.num_nodes
        if not self.knows_structure():  # on the device: a node's row is itself or its parent's row, ``depth`` times
            eye = torch.eye(n, dtype=torch.bool, device=self.token_ids.device)
            has_parent = (self.parents >= 0)[:, None]  # [N, 1]
            rows = eye
            for _ in range(max((self.depth_bound or n) - 1, 0)):
                rows = eye | (has_parent & rows[self.parents.clamp(min=0)])
            return rows
        rows = [[False] * n for _ in range(n)]
        for i, parent in enumerate(self.parent_list):
            if parent >= 0:
                rows[i] = list(rows[parent])
            rows[i][i] = True
        return torch.tensor(rows, dtype=torch.bool, device=self.token_ids.device).reshape(n, n)

    @cached_property
    def is_chain(self) -> bool:
        """True when the tree is one path (node i's parent is node i-1): its tree mask is the causal mask. A tree
        whose parents are on the device counts as no chain (its explicit tree mask is exact either way)."""
        return self.knows_structure() and self.host_parents == list(range(-1, self.num_nodes - 1))

    @property
    def max_depth(self) -> int:
        """Depth of the deepest node + 1 (the longest path's length), 0 for an empty tree."""
        return max(self.depth_list) + 1 if self.num_nodes else 0

    def path_to(self, node: int) -> list[int]:
        """Node indices from the root's child down to ``node`` (ascending, parents first)."""
        path, parents = [], self.parent_list
        while node >= 0:
            path.append(node)
            node = parents[node]
        return path[::-1]

    def paths(self) -> list[list[int]]:
        """Every root-to-leaf path, as node indices."""
        has_child = set(p for p in self.parent_list if p >= 0)
        return [self.path_to(i) for i in range(self.num_nodes) if i not in has_child]

    def token_paths(self) -> list[list[int]]:
        """Every root-to-leaf path, as token ids."""
        tokens = self.host_tokens
        return [[tokens[i] for i in path] for path in self.paths()]

    # ----------------------------------------------------------------- editing (each returns a new tree)
    def select(self, keep: torch.Tensor | Sequence[bool]) -> DraftTree:
        """The sub-tree of the nodes where ``keep`` (``[N]`` bool) is True; a kept node's ancestors must be kept."""
        keep_list = keep.tolist() if isinstance(keep, torch.Tensor) else list(keep)
        new_index, parents = {}, self.parent_list
        for i, kept in enumerate(keep_list):
            if kept:
                if parents[i] >= 0 and parents[i] not in new_index:
                    raise ValueError(f"DraftTree.select keeps node {i} but drops its parent {parents[i]}")
                new_index[i] = len(new_index)
        nodes = list(new_index)
        index = torch.tensor(nodes, dtype=torch.long, device=self.token_ids.device)
        new_parents = [new_index[parents[i]] if parents[i] >= 0 else -1 for i in nodes]
        return DraftTree(
            self.token_ids.index_select(0, index),
            torch.tensor(new_parents, dtype=torch.long, device=self.token_ids.device),
            [self.sources[i] for i in nodes],
            new_parents,
            None if self.token_list is None else [self.token_list[i] for i in nodes],
        )

    def first_path(self) -> DraftTree:
        """The chain of the tree's first root-to-leaf path (the tree itself when it is a chain)."""
        if self.is_chain:
            return self
        first = set(self.paths()[0])
        return self.select([i in first for i in range(self.num_nodes)])

    def truncate_depth(self, max_depth: int) -> DraftTree:
        """Drops every node at depth >= ``max_depth`` (so that no path drafts past a length limit)."""
        if self.num_nodes == 0 or (not self.knows_structure() and (self.depth_bound or self.num_nodes) <= max_depth):
            return self
        if self.max_depth <= max_depth:
            return self
        return self.select([depth < max_depth for depth in self.depth_list])

    def truncate_nodes(self, max_nodes: int) -> DraftTree:
        """The first ``max_nodes`` nodes (a sub-tree: parents come first), e.g. to fit a fixed number of cache slots."""
        if self.num_nodes <= max_nodes:
            return self
        if not self.knows_structure():  # parents come first: the first nodes are a tree, cut on the device
            keep = max(max_nodes, 0)
            return DraftTree(
                self.token_ids[:keep],
                self.parents[:keep],
                self.sources[:keep],
                None,
                None if self.token_list is None else self.token_list[:keep],
                True,
                self.depth_bound,
            )
        return self.select([i < max(max_nodes, 0) for i in range(self.num_nodes)])

    def merge(self, other: DraftTree) -> DraftTree:
        """Union of two trees: nodes with the same token path become one (the first tree's source is kept)."""
        if other.num_nodes == 0:
            return self
        if self.num_nodes == 0:
            return other
        tokens, parents, sources = list(self.host_tokens), list(self.parent_list), list(self.sources)
        index = {(parents[i], tokens[i]): i for i in range(len(tokens))}  # (parent node, token) -> node
        other_tokens, other_parents = other.host_tokens, other.parent_list
        mapped: list[int] = []
        for j, token in enumerate(other_tokens):
            parent = mapped[other_parents[j]] if other_parents[j] >= 0 else -1
            key = (parent, token)
            if key not in index:
                index[key] = len(tokens)
                tokens.append(token)
                parents.append(parent)
                sources.append(other.sources[j])
            mapped.append(index[key])
        return DraftTree.from_lists(tokens, parents, sources, self.token_ids.device)

    def __repr__(self) -> str:
        return f"DraftTree(nodes={self.num_nodes}, depth={self.max_depth}, paths={self.token_paths()})"


@dataclass
class TreeBatch:
    """One draft tree per batch row, padded to a common node count for one batched target forward.

    Row b's real nodes are ``0 .. trees[b].num_nodes - 1``; the others are *filler*: token 0, depth 0, attending
    to themselves only and attended by nothing, their outputs never read and their cache entries never kept.

    Attributes:
        trees: the rows' trees.
        min_nodes: pad to at least this many nodes (a fixed verification width, so that a compiled forward sees
            one shape; see ``speculative.compiled``).
        token_ids: ``[B, N]`` int64 (N = the largest tree's node count, at least ``min_nodes``).
        parents: ``[B, N]`` int64 (filler: -1, a child of the root).
        depths: ``[B, N]`` int64.
        ancestor_or_self: ``[B, N, N]`` bool, each row's tree mask (filler: the diagonal only).
        is_real: ``[B, N]`` bool, False at filler nodes.
    """

    trees: list[DraftTree]
    min_nodes: int = 0
    #: structures made before, by (N, device, every row's parents), least recently used first (a decoder's
    #: ``tree_structures``): a round's trees repeat a few shapes (a Jacobi tail of k tokens padded to its width), so
    #: their structure tensors are made once, never written (every user reads them); None: made for this batch
    structures: dict | None = field(default=None, repr=False, compare=False)
    token_ids: torch.Tensor = field(init=False)
    parents: torch.Tensor = field(init=False)
    depths: torch.Tensor = field(init=False)
    ancestor_or_self: torch.Tensor = field(init=False)
    is_real: torch.Tensor = field(init=False)

    def __post_init__(self):
        if not self.trees:
            raise ValueError("TreeBatch needs at least one tree")
        device = self.trees[0].token_ids.device
        n, b = max(self.min_nodes, *(t.num_nodes for t in self.trees)), len(self.trees)
        if all(t.num_nodes == n for t in self.trees):  # no filler: the rows' own tensors, stacked
            self.token_ids = torch.stack([t.token_ids for t in self.trees])
        else:
            self.token_ids = torch.zeros(b, n, dtype=torch.long, device=device)
            for row, tree in enumerate(self.trees):
                self.token_ids[row, : tree.num_nodes] = tree.token_ids
        if not all(t.knows_structure() for t in self.trees):  # a structure on the device: derived there
            self.parents, self.depths, self.ancestor_or_self, self.is_real = _padded_structure(self.trees, n, device)
            return
        if self.structures is None:
            structure = _padded_structure(self.trees, n, device)
        else:
            structures = self.structures
            key = (n, device, tuple(tuple(t.host_parents) for t in self.trees))  # made once per structure
            structure = structures.pop(key, None)
            if structure is None:
                structure = _padded_structure(self.trees, n, device)
            structures[key] = structure  # most recently used last
            if len(structures) > STRUCTURES_KEPT:
                del structures[next(iter(structures))]
        self.parents, self.depths, self.ancestor_or_self, self.is_real = structure

    @property
    def num_nodes(self) -> int:
        """N, the padded node count."""
        return self.token_ids.shape[1]

    @property
    def max_depth(self) -> int:
        """The deepest row's path length (0 when no row has a node)."""
        return max(tree.max_depth for tree in self.trees)

    @cached_property
    def path_token_ids(self) -> torch.Tensor:
        """``[B, N, D]`` (D = ``max_depth``) the tokens on the path to each node, root's child first, 0 beyond the
        node's depth: node i's path is ``path_token_ids[b, i, : depths[b, i] + 1]``."""
        depth_slot = self.depths[:, :, None] == torch.arange(self.max_depth, device=self.depths.device)  # [B, N, D]
        on_path = self.ancestor_or_self[:, :, :, None] & depth_slot[:, None, :, :]  # [B, N(node), N(ancestor), D]
        return (on_path.long() * self.token_ids[:, None, :, None]).sum(dim=2)

    @property
    def is_causal(self) -> bool:
        """True when every row's tree is a chain (filler after it is harmless under a causal mask, as nothing real
        attends to it): the causal mask then is every row's tree mask."""
        return all(tree.is_chain for tree in self.trees)


#: the structures a [`TreeBatch`]'s ``structures`` keeps (least recently used out)
STRUCTURES_KEPT = 256


def _padded_structure(trees: Sequence[DraftTree], n: int, device) -> tuple[torch.Tensor, ...]:
    """(parents ``[B, N]``, depths ``[B, N]``, ancestor_or_self ``[B, N, N]``, is_real ``[B, N]``) of ``trees``
    padded with filler to ``n`` nodes (see [`TreeBatch`]), from each tree's own tensors."""
    b = len(trees)
    if all(t.num_nodes == n for t in trees):  # no filler: the rows' own tensors, stacked
        return (
            torch.stack([t.parents for t in trees]),
            torch.stack([t.depths for t in trees]),
            torch.stack([t.ancestor_or_self for t in trees]),
            torch.ones(b, n, dtype=torch.bool, device=device),
        )
    parents = torch.full((b, n), -1, dtype=torch.long, device=device)
    depths = torch.zeros(b, n, dtype=torch.long, device=device)
    ancestor_or_self = torch.eye(n, dtype=torch.bool, device=device).repeat(b, 1, 1)
    for row, tree in enumerate(trees):
        k = tree.num_nodes
        parents[row, :k] = tree.parents
        depths[row, :k] = tree.depths
        ancestor_or_self[row, :k, :k] = tree.ancestor_or_self
    is_real = torch.arange(n, device=device)[None] < torch.tensor([t.num_nodes for t in trees], device=device)[:, None]
    return parents, depths, ancestor_or_self, is_real
