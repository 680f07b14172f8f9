"""A bounded loopback load generator for `ssp-rehab bench faults` (wrk is not installed): in a process of its
own, so that its threads never share the measuring process's interpreter lock, it keeps a console busy for
a fixed time with large exports built by the web process, repeated ~4 MiB CSV cue uploads and many
concurrent HTTP clients, and prints what it did as JSON.

    python -m benchmarks.loopback_load --url http://127.0.0.1:PORT/api/v1 --token T --seconds 60 \
        --export-session 3 --exporters 2 --uploaders 1 --clients 50 --patient 1

Loopback only: it refuses any other host.
"""

from __future__ import annotations

import argparse
import collections
import ipaddress
import json
import threading
import time
from collections.abc import Callable
from typing import Any
from urllib.parse import urlsplit

import httpx

UPLOAD_BYTES = 3_900_000  # the JSON body (each newline escaped: one more byte a row) just under the 4 MiB limit
CSV_HEADER = "time_s,specific_force_x_m_s2,specific_force_y_m_s2,specific_force_z_m_s2\n"


def upload_body(patient_id: int) -> dict[str, Any]:
    """A csv_replay prescription whose JSON body is just under 4 MiB (a 60 s segment of a longer recording)."""
    rows, size, index = [], len(CSV_HEADER), 0
    while size < UPLOAD_BYTES - 1024:
        row = f"{index * 0.001:.3f},0.10,0.20,0.00\n"
        rows.append(row)
        size += len(row)
        index += 1
    return {
        "patient_id": patient_id,
        "name": "load replay",
        "segments": [{"cue": {"kind": "csv_replay", "csv": CSV_HEADER + "".join(rows)}, "duration_s": 60.0}],
    }


def _loop(until: float, counts: collections.Counter[str], name: str, call: Callable[[], httpx.Response]) -> None:
    while time.monotonic() < until:
        try:
            response = call()
            counts[f"{name}_{response.status_code}"] += 1
            counts[f"{name}_bytes"] += len(response.content)
        except httpx.HTTPError as error:
            counts[f"{name}_{type(error).__name__}"] += 1


def main() -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("--url", required=True)
    parser.add_argument("--token", required=True)
    parser.add_argument("--seconds", type=float, required=True)
    parser.add_argument("--export-session", type=int, default=None)
    parser.add_argument("--exporters", type=int, default=2)
    parser.add_argument("--uploaders", type=int, default=1)
    parser.add_argument("--clients", type=int, default=50)
    parser.add_argument("--patient", type=int, default=None)
    arguments = parser.parse_args()
    host = urlsplit(arguments.url).hostname or ""
    if host != "localhost" and not ipaddress.ip_address(host).is_loopback:
        raise SystemExit(f"--url host = {host!r}: the load generator stays on loopback")
    headers = {"Authorization": f"Bearer {arguments.token}"}
    until = time.monotonic() + arguments.seconds
    counts: collections.Counter[str] = collections.Counter()
    workers: list[threading.Thread] = []

    def start(name: str, call_factory: Callable[[httpx.Client], Callable[[], httpx.Response]]) -> None:
        def target() -> None:
            with httpx.Client(base_url=arguments.url, headers=headers, timeout=120.0) as client:
                _loop(until, counts, name, call_factory(client))

        thread = threading.Thread(target=target, daemon=True)
        workers.append(thread)
        thread.start()

    if arguments.export_session is not None:
        for index in range(arguments.exporters):
            export_format = "json" if index % 2 == 0 else "csv"
            path = f"/sessions/{arguments.export_session}/export?format={export_format}"
            start("export", lambda client, path=path: lambda: client.get(path))
    if arguments.patient is not None:
        body = json.dumps(upload_body(arguments.patient)).encode()
        upload_headers = {"Content-Type": "application/json"}
        for _ in range(arguments.uploaders):
            start(
                "upload",
                lambda client: lambda: client.post("/prescriptions", content=body, headers=upload_headers),
            )
    for index in range(arguments.clients):
        path = "/health" if index % 2 == 0 else "/patients?limit=50"
        start("client", lambda client, path=path: lambda: client.get(path))
    for thread in workers:
        thread.join(arguments.seconds + 180.0)
    print(json.dumps(dict(counts)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
