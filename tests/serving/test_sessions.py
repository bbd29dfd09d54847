"""Each robot's drafts on the server, alone: no policy."""

from __future__ import annotations

import numpy as np

from hf_specvla.serving.protocol import ActRequest
from hf_specvla.serving.sessions import Sessions

IMAGE = np.zeros((4, 4, 3), np.uint8)


def _request(session=None, reset=False, draft_state=None) -> ActRequest:
    return ActRequest(IMAGE, "reach", None, session, reset=reset, draft_state=draft_state)


def test_a_robot_gets_its_own_previous_actions_back_as_new_lists():
    sessions = Sessions(max_sessions=4)
    sessions.remember("a", [[1, 2], [3, 4]])
    sessions.remember("b", [[5, 6]])
    history = sessions.history(_request("a"))
    assert history == [[1, 2], [3, 4]] and sessions.history(_request("b")) == [[5, 6]]
    history[0].append(99)  # the caller's copy: the session's own is untouched
    assert sessions.history(_request("a")) == [[1, 2], [3, 4]]


def test_an_echoed_draft_state_wins_over_the_kept_one():
    sessions = Sessions(max_sessions=4)
    sessions.remember("a", [[1, 2]])
    assert sessions.history(_request("a", draft_state=[[7, 8]])) == [[7, 8]]


def test_a_reset_forgets_and_no_session_has_no_drafts():
    sessions = Sessions(max_sessions=4)
    sessions.remember("a", [[1, 2]])
    assert sessions.history(_request("a", reset=True, draft_state=[[7, 8]])) == []
    assert "a" not in sessions and len(sessions) == 0
    assert sessions.history(_request(None, draft_state=[[7, 8]])) == []
    assert sessions.history(_request("never-seen")) == []


def test_the_least_recently_used_robot_leaves_first():
    sessions = Sessions(max_sessions=2)
    sessions.remember("a", [[1]])
    sessions.remember("b", [[2]])
    sessions.remember("a", [[3]])  # a is the most recent now
    sessions.remember("c", [[4]])
    assert "b" not in sessions and sessions.history(_request("a")) == [[3]] and len(sessions) == 2
