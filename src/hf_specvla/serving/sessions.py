"""Each robot's state on the server ([`Sessions`]): its previous actions (token ids, as
``VLAPolicy.previous_action_ids``), which are its drafts. No policy here.

A robot names itself with ``session``; its previous actions are kept per session (least recently used first out past
``max_sessions``) and returned in every reply as ``draft_state``, which the robot may echo: then its drafts do not
depend on which replica answers. A robot whose state is lost gets its action without prior drafts (one step of
greedy's speed); ``reset`` starts a new episode.
"""

from __future__ import annotations

from collections import OrderedDict

from .protocol import ActRequest


class Sessions:
    """The previous actions of at most ``max_sessions`` robots, least recently used first out."""

    def __init__(self, max_sessions: int):
        self.max_sessions = max_sessions
        self._histories: OrderedDict[str, list[list[int]]] = OrderedDict()

    def __len__(self) -> int:
        return len(self._histories)

    def __contains__(self, session: str) -> bool:
        return session in self._histories

    def history(self, request: ActRequest) -> list[list[int]]:
        """The robot's previous actions (its drafts; a new list): none at a reset (the session's are forgotten) or
        without a session, the echoed ``draft_state`` if any, else the session's."""
        if request.reset or request.session is None:
            if request.session is not None:
                self.forget(request.session)
            return []
        if request.draft_state is not None:
            return [list(a) for a in request.draft_state]
        return [list(a) for a in self._histories.get(request.session, [])]

    def remember(self, session: str, history: list[list[int]]) -> None:
        """The robot's previous actions after its latest one (the most recently used)."""
        self._histories[session] = history
        self._histories.move_to_end(session)
        while len(self._histories) > self.max_sessions:
            self._histories.popitem(last=False)

    def forget(self, session: str) -> None:
        self._histories.pop(session, None)
