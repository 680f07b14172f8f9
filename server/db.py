"""Database plumbing: engine, sessions, the declarative base and running the Alembic migrations.

Alembic (migrations/) is the only thing that creates or changes the schema. SQLite is the embedded
default; PostgreSQL (psycopg 3) is selected by URL. Service functions take the ORM session explicitly
and commit once, so a request either writes everything or nothing.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import functools
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Annotated, Any, ParamSpec, TypeVar

from fastapi import Depends, Request
from sqlalchemy import DateTime, Engine, MetaData, create_engine, event, text
from sqlalchemy.engine import Connection, Dialect, make_url
from sqlalchemy.exc import DBAPIError, InternalError, OperationalError
from sqlalchemy.orm import DeclarativeBase, Session, sessionmaker
from sqlalchemy.types import TypeDecorator

from server.file_modes import OWNER_ONLY_FILE, private_directory, private_file, tighten

P = ParamSpec("P")
R = TypeVar("R")
MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"

# Stable constraint names so that migrations can refer to them on every backend.
NAMING_CONVENTION = {
    "ix": "ix_%(column_0_label)s",
    "uq": "uq_%(table_name)s_%(column_0_name)s",
    "ck": "ck_%(table_name)s_%(constraint_name)s",
    "fk": "fk_%(table_name)s_%(column_0_name)s_%(referred_table_name)s",
    "pk": "pk_%(table_name)s",
}


class Base(DeclarativeBase):
    metadata = MetaData(naming_convention=NAMING_CONVENTION)


class UTCDateTime(TypeDecorator[dt.datetime]):
    """Stored as naive UTC on every backend; always handed back timezone-aware (UTC)."""

    impl = DateTime
    cache_ok = True

    def process_bind_param(self, value: dt.datetime | None, dialect: Dialect) -> dt.datetime | None:
        if value is None:
            return None
        if value.tzinfo is None:
            raise ValueError("naive datetime given to a UTC column")
        return value.astimezone(dt.UTC).replace(tzinfo=None)

    def process_result_value(self, value: dt.datetime | None, dialect: Dialect) -> dt.datetime | None:
        return None if value is None else value.replace(tzinfo=dt.UTC)


def utc_now() -> dt.datetime:
    return dt.datetime.now(dt.UTC)


def is_sqlite(url: str) -> bool:
    return make_url(url).get_backend_name() == "sqlite"


def create_database_engine(url: str, **engine_options: Any) -> Engine:
    """An engine with the settings this service relies on (SQLite: foreign keys, WAL, serialised writers)."""
    if not is_sqlite(url):
        return create_engine(
            url, pool_pre_ping=True, pool_size=10, max_overflow=30, hide_parameters=True, **engine_options
        )
    database = make_url(url).database
    if database and database != ":memory:" and not database.startswith("file:"):
        # Password hashes and patient data: owner-only (SQLite gives its -wal and -shm files the same mode).
        path = Path(database)
        if not path.parent.exists():
            private_directory(path.parent)
        private_file(path)
        for companion in ("-wal", "-shm", "-journal"):
            tighten(path.with_name(path.name + companion), OWNER_ONLY_FILE)
    engine = create_engine(
        url,
        connect_args={"check_same_thread": False, "timeout": 30},
        hide_parameters=True,
        pool_size=20,
        max_overflow=30,
        **engine_options,
    )

    @event.listens_for(engine, "connect")
    def _configure(dbapi_connection: Any, _record: Any) -> None:
        # Take over transaction control from pysqlite so that SAVEPOINT and BEGIN IMMEDIATE work (SQLAlchemy docs).
        dbapi_connection.isolation_level = None
        dbapi_connection.execute("PRAGMA foreign_keys = ON")
        dbapi_connection.execute("PRAGMA journal_mode = WAL")
        dbapi_connection.execute("PRAGMA synchronous = NORMAL")

    @event.listens_for(engine, "begin")
    def _begin(connection: Connection) -> None:
        # A writing transaction takes the write lock up front (see write_transaction); readers stay deferred,
        # and in WAL mode they never block the writer.
        writing = connection.get_execution_options().get(WRITE_LOCK_OPTION, False)
        connection.exec_driver_sql("BEGIN IMMEDIATE" if writing else "BEGIN")

    return engine


WRITE_LOCK_OPTION = "ssp_rehab_write_lock"
SQLITE_WRITER_LOCK = "sqlite_writer_lock"


@contextmanager
def write_transaction(session: Session) -> Iterator[Session]:
    """One writing transaction, committed on success and rolled back before any error leaves.

    On SQLite it starts with BEGIN IMMEDIATE, so a read-then-write (audit on read, booking conflict checks)
    waits its turn instead of failing on a stale snapshot, and the write lock never outlives this call: a
    lock held across an await would stall every other request thread until the busy timeout. A read
    transaction still open in `session` (the authentication check) is ended first; it wrote nothing.
    """
    if session.in_transaction():
        session.commit()
    # One SQLite writer at a time within this process, queued here rather than in SQLite's busy handler,
    # whose sleep-and-retry backoff gives some writers multi-second waits under load.
    process_lock: threading.Lock | None = session.info.get(SQLITE_WRITER_LOCK)
    with process_lock or contextlib.nullcontext():
        session.connection(execution_options={WRITE_LOCK_OPTION: True})
        try:
            yield session
            session.commit()
        except BaseException:
            session.rollback()
            raise


def writes(function: Callable[P, R]) -> Callable[P, R]:
    """Run a keyword-only service function taking `session=` inside one `write_transaction`."""

    @functools.wraps(function)
    def in_write_transaction(*args: P.args, **kwargs: P.kwargs) -> R:
        session = kwargs["session"]
        assert isinstance(session, Session)
        with write_transaction(session):
            return function(*args, **kwargs)

    return in_write_transaction


def alembic_config(connection: Connection | None = None, url: str | None = None) -> Any:
    from alembic.config import Config

    config = Config(str(MIGRATIONS_DIR / "alembic.ini"))
    config.set_main_option("script_location", str(MIGRATIONS_DIR))
    if url is not None:
        config.set_main_option("sqlalchemy.url", url.replace("%", "%%"))
    config.attributes["connection"] = connection
    return config


class DatabaseReadOnlyError(RuntimeError):
    """The database refuses writes (a read-only file or mount, a read-only PostgreSQL transaction or standby)."""


READ_ONLY_MESSAGES = ("readonly database", "read-only", "read only")
PG_READ_ONLY_TRANSACTION = "25006"


def database_label(engine: Engine) -> str:
    """How messages name the database: its file for SQLite, its URL (without password) otherwise."""
    url = engine.url
    if url.get_backend_name() == "sqlite":
        name = (url.database or ":memory:").removeprefix("file:").split("?", 1)[0]
        return f"database file {Path(name).resolve() if name != ':memory:' else name}"
    return f"database {url.render_as_string(hide_password=True)}"


def refused_write_reason(error: DBAPIError, engine: Engine | None) -> str | None:
    """'database … is read-only' when `error` is the database refusing a write as read-only; else None."""
    original = error.orig
    read_only = getattr(original, "sqlstate", None) == PG_READ_ONLY_TRANSACTION or any(
        marker in str(original).lower() for marker in READ_ONLY_MESSAGES
    )
    if not read_only:
        return None
    return f"{database_label(engine) if engine is not None else 'the database'} is read-only"


def read_only_reason(engine: Engine) -> str | None:
    """Why this database would refuse writes, found without writing anything; None when it accepts them."""
    try:
        with engine.connect() as connection:
            if engine.dialect.name == "postgresql":
                standby = connection.exec_driver_sql("SELECT pg_is_in_recovery()").scalar()
                read_only = connection.exec_driver_sql("SHOW transaction_read_only").scalar() == "on"
                return f"{database_label(engine)} is read-only" if standby or read_only else None
            if engine.dialect.name == "sqlite":
                # A write rolled back: SQLite tells a read-only file (chmod, chattr +i, ro mount) only on a write.
                transaction = connection.begin()
                try:
                    connection.exec_driver_sql("CREATE TABLE ssp_rehab_write_probe (probe INTEGER)")
                finally:
                    transaction.rollback()
    except (OperationalError, InternalError) as error:
        reason = refused_write_reason(error, engine)
        if reason is None:
            raise
        return reason
    return None


def require_writable(engine: Engine) -> None:
    reason = read_only_reason(engine)
    if reason is not None:
        raise DatabaseReadOnlyError(f"{reason}: the console cannot record sessions; make it writable and start again")


def upgrade_database(engine: Engine, revision: str = "head") -> None:
    """Check that the database accepts writes, then migrate it (Alembic) to `revision`."""
    from alembic import command

    require_writable(engine)
    with engine.begin() as connection:
        command.upgrade(alembic_config(connection), revision)


def downgrade_database(engine: Engine, revision: str = "base") -> None:
    from alembic import command

    with engine.begin() as connection:
        command.downgrade(alembic_config(connection), revision)


def current_revision(engine: Engine) -> str | None:
    with engine.connect() as connection:
        try:
            return connection.execute(text("SELECT version_num FROM alembic_version")).scalar()
        except Exception:
            return None


class Database:
    """Hands out ORM sessions. Bound to one connection (tests: a transaction rolled back afterwards),
    access is serialised, because the request threads and the session recorder would otherwise share it."""

    def __init__(self, engine: Engine, *, connection: Connection | None = None) -> None:
        self.engine = engine
        self.dialect_name = engine.dialect.name
        self._single_connection_lock = threading.RLock() if connection is not None else None
        writer_lock = threading.Lock() if self.dialect_name == "sqlite" and connection is None else None
        self._factory = sessionmaker(
            bind=connection if connection is not None else engine,
            expire_on_commit=False,
            join_transaction_mode="create_savepoint",
            info={SQLITE_WRITER_LOCK: writer_lock},
        )

    @contextmanager
    def exclusive(self) -> Iterator[None]:
        """Hold the one connection (tests) across several sessions; a no-op on a pooled engine. A thread that
        takes its own lock before opening sessions takes this first, so it never waits on the connection while
        holding a lock that a request thread (which holds the connection) waits for."""
        if self._single_connection_lock is None:
            yield
            return
        with self._single_connection_lock:
            yield

    @contextmanager
    def session(self) -> Iterator[Session]:
        if self._single_connection_lock is None:
            with self._factory() as session:
                yield session
            return
        with self._single_connection_lock, self._factory() as session:
            yield session


def get_session(request: Request) -> Iterator[Session]:
    database: Database = request.app.state.database
    with database.session() as session:
        yield session


SessionDep = Annotated[Session, Depends(get_session)]


def load_models() -> MetaData:
    """Import every domain's models so that `Base.metadata` is complete (Alembic, schema checks).

    Plain imports, inside the function because each models module imports `Base` from here (a cycle at
    module level); an ImportError propagates instead of leaving a table silently missing."""
    import server.audit.models
    import server.auth.models
    import server.patients.models
    import server.prescriptions.models
    import server.reviews.models
    import server.robotd.models
    import server.scheduling.models
    import server.users.models  # noqa: F401  (imported for their tables)

    return Base.metadata
