"""Console-service settings (pydantic-settings): environment variables `SSP_REHAB_*` and a `.env` file.

The embedded default needs no setup: a SQLite file in the data directory and the simulator backend.
A clinic that shares records between consoles points `SSP_REHAB_DATABASE_URL` at PostgreSQL (psycopg 3).
"""

from __future__ import annotations

import ipaddress
import secrets
from pathlib import Path
from typing import Literal
from zoneinfo import ZoneInfo

from pydantic import Field, SecretStr, field_validator
from pydantic_settings import BaseSettings, SettingsConfigDict

from server.file_modes import OWNER_ONLY_FILE, private_directory, private_file, tighten
from server.realtime.scheduling import parse_cpu_request
from server.scheduling.clinic_time import is_zone_name, machine_zone_name

Backend = Literal["sim", "kinematic", "canopen"]
SECRET_KEY_FILE = "secret_key"


class Settings(BaseSettings):
    model_config = SettingsConfigDict(env_prefix="SSP_REHAB_", env_file=".env", extra="ignore")

    data_dir: Path = Field(default=Path("data"), description="Holds the SQLite file and the token-signing key.")
    database_url: str | None = Field(default=None, description="SQLAlchemy URL; default: SQLite file in data_dir.")
    backend: Backend = Field(default="sim", description="HAL backend the real-time worker drives.")
    robot_file: Path | None = Field(default=None, description="Robot description TOML; default: the paper's twin.")
    control_rate_hz: int = Field(default=1000, ge=250, le=2000, description="Real-time loop rate (Hz).")
    plan_store_max_mb: int = Field(
        default=4096,
        ge=100,
        le=1_000_000,
        description="Stored plans beyond this size (MB) go, least recently used first (a 20-minute plan is "
        "about 90 MB); a plan that goes is made again when it is needed.",
    )
    can_interface: str = Field(default="socketcan", description="python-can interface for --backend canopen.")
    can_channel: str = Field(default="can0", description="CAN channel for --backend canopen.")
    can_simulated_drives: int = Field(
        default=0, ge=0, le=12, description="Simulated CiA 402 drives on the same bus (commissioning without a robot)."
    )
    start_worker: bool = Field(
        default=True, description="Attach to the robot daemon (and start it when none runs) with the service."
    )
    robot: str = Field(
        default="twin-1",
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
        description="The robot this console controls: its daemon runs motion for bookings on this robot.",
    )
    drive_communication_timeout_s: float | None = Field(
        default=None,
        gt=0,
        le=5.0,
        description="Simulated drives' (sim, kinematic) communication-loss stop; default: the HAL's own (50 ms).",
    )

    secret_key: SecretStr | None = Field(
        default=None, description="Signs access tokens; default: generated in data_dir."
    )
    token_lifetime_s: int = Field(default=12 * 3600, ge=60, le=7 * 24 * 3600)
    cookie_name: str = "ssp_rehab_session"
    # The embedded default listens on loopback over plain HTTP, where a Secure cookie would never be sent back.
    cookie_secure: bool = Field(default=False, description="Set the Secure flag; turn on whenever served over HTTPS.")
    cors_origins: list[str] = Field(default_factory=list, description="Allowed browser origins; empty: CORS closed.")
    allowed_origins: list[str] = Field(
        default_factory=list,
        description="Browser origins (scheme://host[:port]) allowed to send cookie-authenticated changes, besides "
        "the origin the console is served from (and cors_origins). Set it when a proxy rewrites the Host header.",
    )
    trusted_proxies: list[str] = Field(
        default_factory=list,
        description="Addresses or networks (CIDR) of reverse proxies whose X-Forwarded-For and X-Forwarded-Proto "
        "are believed; empty: the headers are ignored and the connecting address is the client.",
    )
    max_request_body_bytes: int = Field(
        default=4 * 1024 * 1024,
        ge=1024,
        description="Largest request body accepted (bytes); larger ones get 413 before they are parsed.",
    )

    login_max_failures: int = Field(
        default=5,
        ge=1,
        description="Failed logins from one client address before it backs off (429), and on one account before "
        "each attempt on it is delayed (never refused).",
    )
    login_window_s: float = Field(
        default=300.0,
        gt=0,
        le=86_400,
        description="Window in which an address's failures count, and its first back-off's length; repeated "
        "back-offs grow (twice the failures within four times the window, and so on). An account's failures "
        "count for four windows.",
    )
    login_delay_max_s: float = Field(
        default=10.0,
        ge=0,
        le=60,
        description="Longest delay before an attempt on an account with many recent failures is checked (s).",
    )

    timezone: str = Field(
        default_factory=machine_zone_name,
        description="The clinic's IANA time zone (e.g. Europe/Berlin): bookings keep their wall-clock time in it;"
        " default: the machine's zone.",
    )
    metrics_token: SecretStr | None = Field(
        default=None, description="Bearer token that opens GET /metrics (Prometheus); unset: /metrics is closed."
    )
    audit_drain_interval_s: float = Field(
        default=0.25, gt=0, le=3600, description="How often journaled audit reads are moved into the database (s)."
    )
    log_format: Literal["json", "console"] = Field(
        default="json", description="Service logs: JSON lines (structlog) or human-readable console lines."
    )

    telemetry_rate_hz: float = Field(default=30.0, gt=0, le=120, description="WebSocket telemetry frame rate.")
    log_flush_interval_s: float = Field(default=1.0, gt=0, le=60, description="How often telemetry chunks are written.")
    viz_enabled: bool = Field(default=True, description="Serve the live 3D view (viser) on its own port.")
    viz_host: str = Field(
        default="127.0.0.1",
        description="Loopback interface the 3D view listens on; browsers reach it only through the console's login.",
    )
    viz_port: int = Field(default=8081, ge=1, le=65535, description="Port of the 3D view (embedded by the web app).")
    viz_rate_hz: float = Field(default=30.0, ge=30.0, le=120.0, description="3D view update rate.")
    estop_host: str = Field(
        default="127.0.0.1",
        description="Interface of the emergency-stop listener (a process beside the robot daemon); `serve` sets "
        "it to its own --host.",
    )
    estop_port: int = Field(
        default=0,
        ge=0,
        le=65535,
        description="Port of the emergency-stop listener; 0: a free port, kept across daemon restarts when it is "
        "still free (set one when a reverse proxy forwards to it).",
    )
    estop_public_url: str | None = Field(
        default=None,
        description="Where browsers reach the emergency-stop listener behind a reverse proxy (e.g. /estop); default: "
        "the console's host name with estop_port.",
    )
    console_port: int | None = Field(
        default=None,
        ge=1,
        le=65535,
        description="The console's own port (`serve` sets it): the stop listener answers pages from that origin.",
    )
    frontend_dir: Path | None = Field(
        default=None, description="Static clinician app; default: frontend_static/ if present."
    )
    realtime_cpu: str = Field(
        default="auto",
        description="The real-time worker's CPU: auto (a free one, claimed machine-wide, highest first), none, or a "
        "CPU number (docs/realtime.md).",
    )
    web_healthcheck_timeout_s: int = Field(
        default=300,
        ge=5,
        le=3600,
        description="`serve --workers N`: how long uvicorn waits for a web process to answer its health check "
        "before it kills it (uvicorn's 5 s, and 60 s, killed starting ones at load 14-23 on 2 cores).",
    )

    @field_validator("realtime_cpu")
    @classmethod
    def _realtime_cpu(cls, value: str) -> str:
        return str(parse_cpu_request(value))

    @field_validator("viz_host")
    @classmethod
    def _viz_on_loopback(cls, value: str) -> str:
        # viser has no login of its own: the console relays it (server/viz/proxy.py) to logged-in users only.
        try:
            loopback = value == "localhost" or ipaddress.ip_address(value).is_loopback
        except ValueError:
            loopback = False
        if not loopback:
            raise ValueError(f"viz_host = {value!r}: must be a loopback address (127.0.0.0/8, ::1 or localhost)")
        return value

    @field_validator("timezone")
    @classmethod
    def _known_zone(cls, value: str) -> str:
        if not is_zone_name(value):
            raise ValueError(f"timezone = {value!r}: not an IANA time-zone name (such as Europe/Berlin)")
        return value

    def clinic_zone(self) -> ZoneInfo:
        return ZoneInfo(self.timezone)

    def resolved_database_url(self) -> str:
        if self.database_url:
            return self.database_url
        return f"sqlite:///{(self.data_dir / 'ssp-rehab.sqlite3').resolve()}"

    def resolved_secret_key(self) -> bytes:
        """The configured key, else one generated once and kept (mode 0600) in the data directory."""
        if self.secret_key is not None:
            return self.secret_key.get_secret_value().encode()
        path = self.data_dir / SECRET_KEY_FILE
        if not path.exists():
            private_directory(self.data_dir)
            private_file(path).write_text(secrets.token_urlsafe(48))
        tighten(path, OWNER_ONLY_FILE)
        return path.read_text().strip().encode()

    def resolved_frontend_dir(self) -> Path | None:
        if self.frontend_dir is not None:
            return self.frontend_dir
        bundled = Path(__file__).resolve().parent.parent / "frontend_static"
        return bundled if (bundled / "index.html").exists() else None
