"""Where the history tests get their databases: a SQLite file, or a fresh schema on the PostgreSQL
server NORTHFINDER_TEST_PG_URL names (.ci/postgres starts a throw-away one). Without a server the
PostgreSQL cases skip with the reason; with NORTHFINDER_TEST_PG_REQUIRED=1 (CI), or CI set and the
URL given, a skip is an error."""

from __future__ import annotations

import os
import socket
import threading
import uuid
from urllib.parse import parse_qs, quote, urlsplit

import pytest

PG_URL_ENV = "NORTHFINDER_TEST_PG_URL"
BACKENDS = ("sqlite", "postgresql")


def pg_required() -> bool:
    return os.environ.get("NORTHFINDER_TEST_PG_REQUIRED") == "1" or bool(
        os.environ.get("CI") and os.environ.get(PG_URL_ENV)
    )


def pg_url_or_skip() -> str:
    """The test server's URL after one real connection, else skip (or fail where required)."""
    url = os.environ.get(PG_URL_ENV)
    reason = None
    if not url:
        reason = f"no PostgreSQL server for the history tests: set {PG_URL_ENV} (.ci/postgres starts one)"
    else:
        import psycopg

        try:
            psycopg.connect(url, connect_timeout=10).close()
        except psycopg.Error as exc:
            reason = f"PostgreSQL server {url} not reachable: {str(exc).strip().splitlines()[0]}"
    if reason:
        if pg_required():
            pytest.fail(f"{reason} — PostgreSQL tests are required here (CI)")
        pytest.skip(reason)
    return url


def with_search_path(url: str, schema: str) -> str:
    """The URL with every session's search_path set to `schema` (libpq's `options`)."""
    sep = "&" if "?" in url else "?"
    return f"{url}{sep}options={quote(f'-csearch_path={schema}')}"


class PgSchema:
    """A fresh schema on the test server: `url` opens sessions in it; `drop()` removes it."""

    def __init__(self, base_url: str):
        import psycopg

        self.base_url, self.name = base_url, f"nf_test_{uuid.uuid4().hex[:12]}"
        with psycopg.connect(base_url, autocommit=True) as conn:
            conn.execute(f"CREATE SCHEMA {self.name}")
        self.url = with_search_path(base_url, self.name)

    def drop(self) -> None:
        import psycopg

        with psycopg.connect(self.base_url, autocommit=True) as conn:
            conn.execute(f"DROP SCHEMA {self.name} CASCADE")


@pytest.fixture
def pg_schema():
    schema = PgSchema(pg_url_or_skip())
    yield schema
    schema.drop()


@pytest.fixture(params=BACKENDS)
def target(request, tmp_path):
    """A history database on each back end: a SQLite path, or a postgresql:// URL of a new schema."""
    if request.param == "sqlite":
        yield tmp_path / "history.sqlite"
        return
    schema = PgSchema(pg_url_or_skip())
    yield schema.url
    schema.drop()


class TcpRelay:
    """127.0.0.1:port relayed to the test server's Unix socket: `stop()` is the network going down
    (connections refused, open ones cut), `start()` it coming back on the same port."""

    def __init__(self, base_url: str):
        parts = urlsplit(base_url)
        host = parse_qs(parts.query).get("host", [parts.hostname or ""])[0]
        port = parts.port or 5432
        self.upstream: tuple[str, ...] | str = (
            os.path.join(host, f".s.PGSQL.{port}") if host.startswith("/") else (host, port)
        )
        self.dbname = parts.path.lstrip("/")
        self.user = parts.username or "postgres"
        probe = socket.socket()
        probe.bind(("127.0.0.1", 0))
        self.port = probe.getsockname()[1]
        probe.close()
        self.listener: socket.socket | None = None
        self.links: list[socket.socket] = []

    def url(self, schema: str) -> str:
        return with_search_path(f"postgresql://{self.user}@127.0.0.1:{self.port}/{self.dbname}", schema)

    def start(self) -> None:
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind(("127.0.0.1", self.port))
        self.listener.listen(8)
        threading.Thread(target=self._accept, args=(self.listener,), daemon=True).start()

    def stop(self) -> None:
        if self.listener is not None:
            try:
                self.listener.shutdown(socket.SHUT_RDWR)  # wakes the accept() blocked in its thread
            except OSError:
                pass
            self.listener.close()
            self.listener = None
        for s in self.links:
            try:
                s.close()
            except OSError:
                pass
        self.links.clear()

    def _accept(self, listener: socket.socket) -> None:
        while True:
            try:
                client, _ = listener.accept()
            except OSError:
                return
            family = socket.AF_UNIX if isinstance(self.upstream, str) else socket.AF_INET
            server = socket.socket(family)
            server.connect(self.upstream)
            self.links += [client, server]
            for a, b in ((client, server), (server, client)):
                threading.Thread(target=self._pump, args=(a, b), daemon=True).start()

    @staticmethod
    def _pump(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
