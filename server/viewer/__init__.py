"""The participant's 3D view: a loopback viser server per session, relayed through FastAPI.

- ``server.viewer.scene``: the scene of one session (primitives, poses, camera presets).
- ``server.viewer.manager``: servers per session, the DB poll, the hub's frames.
- ``server.routes.viewer``: ``GET /viewer/{token}/`` (viser's client), ``WS /viewer/{token}``
  (relay), ``POST /api/p/{token}/camera``.
"""

from server.viewer.manager import ViewerManager, ViewerSession
from server.viewer.scene import VIEWS, SceneView

__all__ = ["VIEWS", "SceneView", "ViewerManager", "ViewerSession"]
