"""The participant's 3D view: viser's web client, fed by trustlab's own websocket in viser's wire format.

- ``server.viewer.scene``: the scene of one session (primitives) as viser's messages.
- ``server.viewer.live``: what moves in it (poses, marks, follow cameras), built on the event loop and written
  by the viewer sockets to the browsers.
- ``server.viewer.wire``: viser 1.1.1's wire format.
- ``server.viewer.cameras``: the camera presets.
- ``server.viewer.manager``: the views of the sessions, the DB poll, the hub's ticks.
- ``server.viewer.targets``: what a session's view should show (its trial's scene and stage), from the database.
- ``server.viewer.remote``, ``server.viewer.process``, ``server.viewer.link``: all of the above in a view process of
  its own when serving with uvicorn (the default), the server handing it the viewer sockets and telling it what
  only the server knows (attempts played back, teleoperations' worlds, trials started, camera presets).
- ``server.routes.viewer``: ``GET /viewer/{token}/`` (viser's client), ``WS /viewer/{token}``
  (the scene and what moves), ``POST /api/p/{token}/camera``.
"""

from server.viewer.cameras import VIEWS
from server.viewer.manager import ViewerManager, ViewerSession
from server.viewer.scene import SceneView

__all__ = ["VIEWS", "SceneView", "ViewerManager", "ViewerSession"]
