"""The harness: simulated participants and the clients that drive a running trustlab, for tests, benchmarks and
``trustlab bots``. It sits on top of the server (nothing in ``server/`` but the CLI imports it); the models of the
people themselves are pure and live in ``experiment.participants``.

- ``client``, ``bots``, ``bot_teleop``, ``crowd``: a bot is one participant over HTTP and the teleoperation
  websocket (errors, measurements and sockets; the session walk; its teleoperation; many bots at once).
- ``live``: the app served by uvicorn in a thread, or ``trustlab serve`` in a subprocess.
- ``teleop_client``: a teleoperation socket that checks every message against the published JSON Schema.
- ``viewer_client``: a headless client of a participant's 3D view (viser's wire format).
- ``browser``: Debian's Chromium through Playwright (``browser_session``); ``driver``: the participant page driven
  as a person would, teleoperation with held keys.
"""
