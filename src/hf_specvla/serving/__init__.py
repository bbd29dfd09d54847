"""Serving robots: a policy service that batches requests from many robots into one ``predict_action`` call with
each robot's own drafts (``service``), its HTTP app (``app``, a superset of OpenVLA's ``deploy.py`` ``POST /act``), a
server on one machine (``server``) or a Ray Serve deployment (``ray_deployment``), and a light client (``client``, no
torch). Sits above ``policies``; the engine and the policies know nothing of it."""

from .._lazy import lazy_exports

__all__ = ["ActReply", "ActRequest", "PolicyClient", "PolicyService", "RequestError", "ServeConfig", "ServerError"]

__getattr__, __dir__ = lazy_exports(
    __name__,
    {
        ".protocol": ("ActReply", "ActRequest", "RequestError"),
        ".client": ("PolicyClient", "ServerError"),
        ".service": ("PolicyService",),
        ".config": ("ServeConfig",),
    },
    globals(),
)
