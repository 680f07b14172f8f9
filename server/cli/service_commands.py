"""`ssp-rehab serve` (the console service), `ssp-rehab robot` (a robot's daemon, which `serve` starts
when none runs) and `ssp-rehab create-user` (clinician accounts)."""

from __future__ import annotations

import datetime as dt
import logging
import os
import signal
import sys
from pathlib import Path
from typing import TYPE_CHECKING, Any

import typer

if TYPE_CHECKING:
    from pydantic import ValidationError


from core.errors import InvalidValueError
from server.cli.output import console, emit, error_console, fail
from server.cli.robot_option import ROBOT_OPTION

ROLES = ("admin", "therapist")
DATA_DIR_HELP = "Holds the SQLite database and the token key (default ./data, or SSP_REHAB_DATA_DIR)."


MAX_WEB_WORKERS = 16


def _prepare_web_processes(settings: Any, options: dict[str, Any]) -> str:
    """What `serve --workers N` (N > 1) does once, before the web processes start: it puts the given
    options into the environment the processes inherit (their app factory reads Settings from it), and
    does the one-time set-up they would otherwise race on: the schema upgrade and the token-signing key
    (two processes generating it at once would sign with different keys). Returns the factory's import
    string. The robot daemon is not started here: each process attaches, and its lock admits one daemon."""
    import os

    from core.robot import load_twin
    from server.db import create_database_engine, upgrade_database

    for name, value in options.items():
        if value is None:
            continue
        if isinstance(value, Path):
            value = value.resolve()
        elif isinstance(value, bool):
            value = "true" if value else "false"
        os.environ[f"SSP_REHAB_{name.upper()}"] = str(value)
    if settings.robot_file:
        load_twin(settings.robot_file)  # a bad description fails here, once, not in every process
    settings.resolved_secret_key()
    engine = create_database_engine(settings.resolved_database_url())
    try:
        upgrade_database(engine)
    finally:
        engine.dispose()
    return "server.app:app_from_environment"


def _console_identity() -> str:
    """This `serve`'s console id, in the environment its web processes (and the robot daemon they start)
    inherit: its processes share the session-control lease (server.robotd.link.console_id), and the
    daemon names it as its starter, so that this console, and only it, stops it on exit."""
    import uuid

    from server.robotd.link import CONSOLE_ID_ENVIRONMENT

    return os.environ.setdefault(CONSOLE_ID_ENVIRONMENT, f"serve-{os.getpid()}-{uuid.uuid4().hex[:8]}")


def _end_robot(settings: Any, console_identity: str, keep_robot: bool, began: dt.datetime) -> None:
    """On `serve`'s exit: stop the robot daemon this console started (a controlled stop of a run in
    motion, records flushed) unless `--keep-robot`; a daemon that ran without it is left alone. Says which."""
    from server.robotd.link import DAEMON_STOP_TIMEOUT_S, running_daemon, stop_daemon
    from server.robotd.status import RobotPaths

    paths = RobotPaths(settings.data_dir.resolve(), settings.robot)
    robot = settings.robot
    daemon = running_daemon(paths)
    if daemon is None:
        return
    how_to_stop = f"stop it with `kill -TERM {daemon.pid}` (its pid file: {paths.pid})"
    if daemon.started_by != console_identity:
        console.print(
            f"the robot daemon {robot} (pid {daemon.pid}) keeps running: this console did not start it "
            "(a service, `ssp-rehab robot`, or another console)",
            soft_wrap=True,
        )
        return
    if keep_robot:
        console.print(f"left the robot daemon {robot} running (--keep-robot): {how_to_stop}", soft_wrap=True)
        return
    console.print(f"stopping the robot daemon {robot} (pid {daemon.pid}) that this console started …", soft_wrap=True)
    end = stop_daemon(paths, daemon)
    if not end.ended:
        error_console.print(
            f"[bold red]the robot daemon {robot} (pid {daemon.pid}) has not ended within "
            f"{DAEMON_STOP_TIMEOUT_S:g} s[/]: {how_to_stop}; its log: {paths.log}",
            soft_wrap=True,
        )
        return
    if not end.clean:
        error_console.print(
            f"[bold red]the robot daemon {robot} (pid {daemon.pid}) ended without its own shutdown[/]: the next "
            f"daemon closes a run it left open as interrupted; its log: {paths.log}",
            soft_wrap=True,
        )
        return
    runs = _runs_interrupted_by_the_exit(settings, began)
    what = "".join(f"run {run_id} interrupted with a controlled stop; " for run_id in runs) or "no run in motion; "
    console.print(f"stopped the robot daemon {robot} that this console started ({what}records flushed)", soft_wrap=True)


def _runs_interrupted_by_the_exit(settings: Any, since: dt.datetime) -> list[int]:
    """The runs of this console's robot that its exit interrupted (its link ended, or its daemon was stopped,
    with the run in motion: a controlled stop either way), as recorded."""
    from sqlalchemy import select

    from server.db import Database, create_database_engine
    from server.robotd.consoles import CONSOLE_LOST
    from server.robotd.daemon import DAEMON_STOPPED
    from server.robotd.models import RunOutcome, SessionEvent, SessionRun

    engine = create_database_engine(settings.resolved_database_url())
    try:
        with Database(engine).session() as session:
            rows = session.execute(
                select(SessionRun.id, SessionEvent.details)
                .join(SessionEvent, SessionEvent.run_id == SessionRun.id)
                .where(
                    SessionRun.robot == settings.robot,
                    SessionRun.outcome == RunOutcome.INTERRUPTED.value,
                    SessionRun.ended_at >= since,
                    SessionEvent.kind == "run_ended",
                )
                .order_by(SessionRun.id)
            ).all()
    finally:
        engine.dispose()
    reasons = (CONSOLE_LOST, DAEMON_STOPPED)
    return [run_id for run_id, details in rows if str((details or {}).get("reason", "")).startswith(reasons)]


def _settings(**overrides: Any) -> Any:
    """Settings from the environment, with the command-line options that were given taking precedence."""
    from server.settings import Settings

    return Settings(**{name: value for name, value in overrides.items() if value is not None})


def _validation_message(error: ValidationError) -> str:
    """The first refusal, naming the field, the value (never a secret's: `server.security`) and the rule."""
    from server.security import shown_value

    first = error.errors()[0]
    field = ".".join(str(part) for part in first["loc"])
    return f"{field} = {shown_value(field, first.get('input'))}: {first['msg']}"


def _interactive() -> bool:
    """A person at a terminal, who can be asked again (not a script piping its input)."""
    import sys

    return sys.stdin.isatty()


def _password_refusal(password: str) -> str | None:
    """Why an account's password is refused (never the password itself), or None."""
    from pydantic import TypeAdapter, ValidationError

    from server.api_types import Password

    try:
        TypeAdapter(Password).validate_python(password)
    except ValidationError as error:
        return f"password = (not shown): {error.errors()[0]['msg']}"
    return None


def register(app: typer.Typer) -> None:
    @app.command()
    def serve(
        host: str = typer.Option("127.0.0.1", "--host", help="Interface to listen on."),
        port: int = typer.Option(8000, "--port", min=1, max=65535),
        data_dir: Path | None = typer.Option(None, "--data-dir", help=DATA_DIR_HELP),
        backend: str | None = typer.Option(None, "--backend", help="Robot backend: sim (default), kinematic, canopen."),
        robot_file: Path | None = ROBOT_OPTION,
        robot_name: str | None = typer.Option(
            None, "--robot-name", help="The robot this console controls, as bookings name it (default twin-1)."
        ),
        no_robot: bool = typer.Option(False, "--no-robot", help="Do not attach to (or start) a robot daemon."),
        can_interface: str | None = typer.Option(None, "--can-interface", help="python-can interface (canopen)."),
        can_channel: str | None = typer.Option(None, "--can-channel", help="CAN channel (canopen), e.g. can0."),
        can_simulate: int | None = typer.Option(
            None, "--can-simulate", help="Simulated CiA 402 drives on that bus (canopen, commissioning)."
        ),
        workers: int = typer.Option(
            1,
            "--workers",
            help="Web processes behind the one port, all attached to the one robot daemon.",
        ),
        keep_robot: bool = typer.Option(
            False,
            "--keep-robot",
            help="Leave the robot daemon running on exit (by default a daemon this console started is stopped).",
        ),
    ) -> None:
        """Run the therapist console: REST API, telemetry WebSocket, web app at / and OpenAPI at /docs."""
        import uvicorn
        from pydantic import ValidationError

        from server.app import create_app
        from server.hal.backends import BACKENDS

        if backend is not None and backend not in BACKENDS:
            raise fail(f"--backend = {backend!r}: must be one of {', '.join(BACKENDS)}")
        if not 1 <= workers <= MAX_WEB_WORKERS:
            raise fail(f"--workers = {workers}: must be from 1 to {MAX_WEB_WORKERS} web processes")
        options = {
            "data_dir": data_dir,
            "backend": backend,
            "robot": robot_name,
            "robot_file": robot_file,
            "start_worker": False if no_robot else None,
            "can_interface": can_interface,
            "can_channel": can_channel,
            "can_simulated_drives": can_simulate,
            "console_port": port,
            # The stop listener serves the browsers this console serves, unless configured apart.
            "estop_host": None if "SSP_REHAB_ESTOP_HOST" in os.environ else host,
        }
        application: Any  # the app, or the import string of its factory
        console_identity = _console_identity()
        try:
            settings = _settings(**options)
            # One process runs the app object; several each build it from the environment (a factory).
            application = create_app(settings) if workers == 1 else _prepare_web_processes(settings, options)
        except ValidationError as error:
            raise fail(_validation_message(error)) from error
        except InvalidValueError as error:
            raise fail(str(error)) from error
        from server.observability.logs import configure_logging

        configure_logging(settings.log_format)
        if host not in ("127.0.0.1", "localhost", "::1") and not settings.cookie_secure:
            logging.getLogger(__name__).warning(
                "listening on %s without SSP_REHAB_COOKIE_SECURE=true: put the service behind HTTPS", host
            )
        console.print(
            f"ssp-rehab console on http://{host}:{port}/  (API docs: /docs)\n"
            f"  data: {settings.data_dir.resolve()}   backend: {settings.backend}   web processes: {workers}"
        )
        began = dt.datetime.now(dt.UTC)
        # uvicorn re-sends the signal that stopped it once it has shut down; SIGTERM's default action would
        # end this process before the robot daemon is seen to.
        signal.signal(signal.SIGTERM, lambda signum, _: sys.exit(128 + signum))
        try:
            # X-Forwarded-For is believed only from SSP_REHAB_TRUSTED_PROXIES, by the app itself (server.security);
            # uvicorn's own default would trust it from loopback. log_config=None keeps the structured (JSON)
            # logging configured above for uvicorn's loggers too.
            uvicorn.run(
                application,
                host=host,
                port=port,
                log_level="info",
                proxy_headers=False,
                log_config=None,
                workers=workers,
                factory=workers > 1,
                # uvicorn's default (5 s) killed web processes that started on a loaded machine (issue 20).
                timeout_worker_healthcheck=settings.web_healthcheck_timeout_s,
            )
        finally:
            if settings.start_worker:  # once, here: the web processes (and their links) have all ended
                _end_robot(settings, console_identity, keep_robot, began)

    @app.command("warm-up")
    def warm_up(
        robot_file: Path | None = ROBOT_OPTION,
        as_json: bool = typer.Option(False, "--json", help="Print the outcome as JSON."),
    ) -> None:
        """Compile the real-time kernels into numba's cache (set-up; `scripts/console.sh` runs it), so that
        the robot daemon's first start loads them instead of compiling for minutes."""
        import time

        from pydantic import ValidationError

        from core.robot import default_twin, load_twin
        from server.cli.output import progress_bar
        from server.realtime.pipeline import compile_tick_path
        from server.realtime.supervisor import SupervisorConfig

        try:
            settings = _settings(robot_file=robot_file)
            twin = load_twin(settings.robot_file) if settings.robot_file else default_twin()
        except ValidationError as error:
            raise fail(_validation_message(error), as_json=as_json) from error
        except InvalidValueError as error:
            raise fail(str(error), as_json=as_json) from error
        began = time.perf_counter()
        # The tick path is the same on every backend (it runs on an ideal HAL), as the worker compiles it.
        description = "compiling the real-time kernels into numba's cache (minutes on a fresh install)"
        with progress_bar(description, 1, enabled=not as_json) as advance:
            compile_tick_path(twin, settings.control_rate_hz, SupervisorConfig())
            advance(1)
        emit(
            {"control_rate_hz": settings.control_rate_hz, "elapsed_s": round(time.perf_counter() - began, 1)},
            as_json=as_json,
            human=lambda r: console.print(
                f"real-time kernels ready in numba's cache ({r['elapsed_s']} s, {r['control_rate_hz']} Hz)"
            ),
        )

    @app.command("robot")
    def robot_daemon(
        robot: str | None = typer.Option(
            None, "--robot", help="The robot's name, as bookings name it (default: SSP_REHAB_ROBOT or twin-1)."
        ),
        data_dir: Path | None = typer.Option(None, "--data-dir", help=DATA_DIR_HELP),
        backend: str | None = typer.Option(None, "--backend", help="Robot backend: sim (default), kinematic, canopen."),
        robot_file: Path | None = typer.Option(
            None, "--robot-file", help="Robot description TOML (default: SSP_REHAB_ROBOT_FILE or the paper's robot)."
        ),
        as_json: bool = typer.Option(False, "--json", help="Print the outcome as JSON."),
        started_by: str | None = typer.Option(
            None, "--started-by", hidden=True, help="The console (`serve`) that started it, and stops it on exit."
        ),
    ) -> None:
        """Run the robot daemon: the real-time worker, heartbeat relay, HAL, planning process and recorder
        of one robot. It owns and records every run; `serve` starts it when none runs."""
        from pydantic import ValidationError

        from server.hal.backends import BACKENDS
        from server.robotd.process import AlreadyRunning, run_robot_daemon

        if backend is not None and backend not in BACKENDS:
            raise fail(f"--backend = {backend!r}: must be one of {', '.join(BACKENDS)}", as_json=as_json)
        try:
            settings = _settings(data_dir=data_dir, backend=backend, robot=robot, robot_file=robot_file)
        except ValidationError as error:
            raise fail(_validation_message(error), as_json=as_json) from error
        logging.basicConfig(level=logging.INFO, format="%(asctime)s robotd %(levelname)s [%(name)s] %(message)s")
        try:
            code = run_robot_daemon(settings, settings.robot, started_by)
        except AlreadyRunning as error:
            raise fail(str(error), as_json=as_json) from error
        emit(
            {"robot": settings.robot, "exit_code": code},
            as_json=as_json,
            human=lambda r: console.print(f"robot daemon {r['robot']} ended"),
        )
        raise typer.Exit(code)

    @app.command("create-user")
    def create_user(
        username: str = typer.Option(..., "--username"),
        password: str = typer.Option(..., "--password", prompt=True, hide_input=True, confirmation_prompt=True),
        role: str = typer.Option(..., "--role", help="admin or therapist"),
        full_name: str = typer.Option("", "--full-name"),
        data_dir: Path | None = typer.Option(None, "--data-dir", help=DATA_DIR_HELP),
        as_json: bool = typer.Option(False, "--json"),
    ) -> None:
        """Create a clinician account (the first admin, typically). Upgrades the database first."""
        from pydantic import ValidationError

        from server.db import Database, create_database_engine, upgrade_database
        from server.errors import ConflictError, InvalidFieldError
        from server.users.schemas import UserCreate
        from server.users.service import create_user as create

        while (refusal := _password_refusal(password)) is not None:
            if not _interactive():
                raise fail(refusal, as_json=as_json)
            error_console.print(f"[bold red]refused:[/] {refusal}; choose another")
            password = typer.prompt("Password", hide_input=True, confirmation_prompt=True)
        try:
            data = UserCreate(username=username, password=password, role=role, full_name=full_name)  # type: ignore[arg-type]
        except ValidationError as error:
            raise fail(_validation_message(error), as_json=as_json) from error
        settings = _settings(data_dir=data_dir)
        engine = create_database_engine(settings.resolved_database_url())
        try:
            upgrade_database(engine)
            with Database(engine).session() as session:
                user = create(session=session, data=data, actor_id=None)
                result = {"id": user.id, "username": user.username, "role": user.role}
        except (ConflictError, InvalidFieldError) as error:
            raise fail(str(error), as_json=as_json) from error
        finally:
            engine.dispose()
        emit(
            result,
            as_json=as_json,
            human=lambda r: console.print(f"created {r['role']} account [bold]{r['username']}[/] (id {r['id']})"),
        )

    @app.command("unlock-login")
    def unlock_login(
        username: str | None = typer.Option(None, "--username", help="Forget this account's failed logins."),
        address: str | None = typer.Option(None, "--address", help="Lift this client address's back-off."),
        data_dir: Path | None = typer.Option(None, "--data-dir", help=DATA_DIR_HELP),
        as_json: bool = typer.Option(False, "--json"),
    ) -> None:
        """Lift a login back-off (an admin's unlock, docs/service.md): a client address, an account, or both."""
        from pydantic import ValidationError

        from server.auth.schemas import LoginUnlock
        from server.auth.service import unlock_login as unlock
        from server.auth.throttle import LoginThrottle
        from server.db import Database, create_database_engine, upgrade_database
        from server.errors import NotFoundError

        try:
            request = LoginUnlock(username=username, address=address)  # type: ignore[arg-type]
        except ValidationError as error:
            raise fail(_validation_message(error), as_json=as_json) from error
        settings = _settings(data_dir=data_dir)
        throttle = LoginThrottle(settings.login_max_failures, settings.login_window_s)
        engine = create_database_engine(settings.resolved_database_url())
        try:
            upgrade_database(engine)
            with Database(engine).session() as session:
                lifted = unlock(session=session, throttle=throttle, username=request.username,
                                address=str(request.address) if request.address else None, actor_id=None)  # fmt: skip
        except NotFoundError as error:
            raise fail(str(error), as_json=as_json) from error
        finally:
            engine.dispose()
        emit(
            {"unlocked": lifted},
            as_json=as_json,
            human=lambda r: console.print("unlocked: " + ", ".join(r["unlocked"])),
        )
