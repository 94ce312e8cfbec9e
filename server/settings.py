"""The one settings object. Nothing else in trustlab reads the environment."""

from __future__ import annotations

from pydantic import Field
from pydantic_settings import BaseSettings, SettingsConfigDict


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="TRUSTLAB_", env_file=".env", extra="ignore")

    database_url: str = "sqlite:///trustlab.db"
    host: str = "127.0.0.1"
    port: int = Field(8000, ge=0, le=65535)
    #: The address participants reach (behind a proxy: its https URL); default http://host:port.
    public_url: str | None = None
    #: Seconds between abandonment sweeps.
    sweep_interval_s: float = Field(30.0, gt=0)
    #: Largest request body accepted, in bytes.
    max_body_bytes: int = Field(256 * 1024, ge=1024)
    #: Teleoperation messages accepted per second per session (more are refused); a page sends one per input
    #: change and a keep-alive every few hundred milliseconds.
    teleop_rate_limit_hz: float = Field(60.0, gt=0)
    #: World messages per second at most that the teleoperation socket pushes while the arm moves.
    teleop_world_hz: float = Field(15.0, gt=0, le=60)
    #: Messages per second a 3D view's client may send on average (its camera, while the participant drags the
    #: view: one per animation frame, about 60 a second), with twice that in a burst; a client that sends more
    #: is closed (1008). Its messages are read and dropped, but each costs the server.
    viewer_message_rate_hz: float = Field(120.0, gt=0)
    #: Pages of other origins allowed to open the websockets, besides this server's own (as the browser reached it)
    #: and the public URL: e.g. '["https://lab.example.org"]' (a page of the lab's that embeds the study).
    allowed_origins: list[str] = Field(default_factory=list)
    #: Addresses of the reverse proxies whose X-Forwarded-For names the client (the join rate limits count it),
    #: e.g. '["127.0.0.1"]' behind nginx on this machine. Default none: the connection's own address counts, as a
    #: header from anyone else could be forged. ``serve --workers`` sets its own nginx's (server.workers).
    forwarded_allow_ips: list[str] = Field(default_factory=list)
    #: Seconds a connection may take to send a request's line and headers before it is closed (uvicorn bounds only
    #: the idle wait between requests: ``server.launch.bounded_h11``).
    request_head_timeout_s: float = Field(10.0, gt=0, le=300)
    #: Serve the API's interactive docs (Swagger UI, vendored) at /docs; the schema stays at /openapi.json.
    api_docs: bool = True
    #: Joins accepted per minute from one client address (a lab behind one NAT stays far below it); more get 429.
    join_rate_limit_per_ip: int = Field(30, ge=1)
    #: Joins accepted per minute per study (about ten a second: a recruitment platform's rush stays below it).
    join_rate_limit_per_study: int = Field(600, ge=1)
    #: Tick rate of the world loop that advances active sessions.
    world_hz: float = Field(30.0, gt=0, le=240)
    #: Run the world loop (tests that step the world by hand turn it off).
    world_loop: bool = True
    #: Helper processes that plan the robot's autonomous attempts ahead of time (0: plan in a thread of the
    #: server; see ``server.world.attempts.Attempts.prepare``): planning is CPU the event loop's process then
    #: does not spend (docs/architecture.md, "Processes").
    planner_processes: int = Field(1, ge=0, le=8)
    #: Move the teleoperated arms in a helper process when moving one world-loop tick's arms here would take at
    #: least ``physics_helper_min_ms`` (the arms that move times the measured time an arm's move takes): the
    #: physics then runs on another core instead of holding the interpreter lock that every request waits for
    #: (``server.world.physics``). Below that the round trip to the helper costs more CPU than it saves, and they move
    #: in the server.
    physics_helper: bool = True
    physics_helper_min_ms: float = Field(2.0, ge=0)
    #: Serve the participants' 3D views in a process of their own (``server.viewer.remote``) when serving with
    #: uvicorn (``trustlab serve``): the server's event loop then carries requests, decisions and teleoperation
    #: only. Off: the views are served in the server's process, as an app without uvicorn (tests) always does.
    view_process: bool = True
    #: This process's index in a group started by ``trustlab serve --workers N`` (None: the only process).
    #: Worker 0 is the primary: it alone gets the admin API and joins, and runs the background jobs (the
    #: abandonment sweep, fits); see ``server.workers``.
    worker_index: int | None = Field(None, ge=0)
    #: The client event log's budget per participant session (``POST /api/p/{token}/events``): events stored in all,
    #: and bytes of their payloads (as stored JSON). Past either, more events are refused with 413 (code
    #: event_budget_spent); the study goes on. A real page writes far less in a whole study: at most ~150 events a
    #: trial (presses, keys while teleoperating, camera, focus), ~70 bytes each, so ~30,000 events and ~2 MB for the
    #: longest study (200 trials); these defaults leave more than 3x and 10x that.
    event_budget_events: int = Field(100_000, ge=1)
    event_budget_bytes: int = Field(32 * 1024 * 1024, ge=1024)
    #: Event requests per second one session may send on average, ``event_rate_burst`` at once (a page sends a
    #: batch of up to 50 every 2 s or more, and catches up after being offline); more get 429 with Retry-After,
    #: which the page's client retries after.
    event_rate_per_s: float = Field(4.0, gt=0)
    event_rate_burst: int = Field(30, ge=1)
    #: Under a study's cap (``recruitment.max_active_participants``), seconds a session that has not consented holds
    #: its place after its latest request. The page sends a heartbeat every 10 s (a background tab's timers may
    #: slow to one a minute), so a person reading the consent form keeps it; a bare join holds one this long, not
    #: for the idle timeout. A consented session holds its place until it ends.
    unconsented_place_hold_s: float = Field(120.0, ge=10, le=3600)
    #: Under a study's cap, unconsented sessions one client address may hold at once (more joins: 429). Consented
    #: ones do not count: a lab behind one NAT runs any number of participants and needs only this many reading
    #: the consent form at the same moment.
    max_unconsented_per_address: int = Field(20, ge=1)

    @property
    def primary(self) -> bool:
        """Whether this process runs the background jobs (the only process, or worker 0 of a group)."""
        return self.worker_index in (None, 0)

    def base_url(self) -> str:
        return (self.public_url or f"http://{self.host}:{self.port}").rstrip("/")
