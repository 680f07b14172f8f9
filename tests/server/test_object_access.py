"""Object-level authorisation (issue 20 defect 14, OWASP API1): roles x routes x owners, generated from the
app's route table, so that a route added without a rule fails here (docs/service.md, "Who may see and
change what")."""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Any

import pytest
from fastapi.routing import iter_route_contexts
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from server.app import API_PREFIX
from server.auth.access import PATIENT_OBJECTS, SELF_OBJECTS, UNSCOPED_ROUTES
from server.db import Database
from tests.server.conftest import Seed, book, create_patient, create_prescription, fallen_run

OBJECT_PARAMETERS = set(PATIENT_OBJECTS) | set(SELF_OBJECTS)
# Unscoped routes that name a patient's object in their body: refused like a path id.
BODY_SCOPED = {
    ("POST", "/prescriptions"),
    ("POST", "/prescriptions/previews"),
    ("POST", "/sessions"),
    ("POST", "/viz/replay"),
    ("POST", "/viz/figure"),
}
ADMIN_ONLY = {key for key, rule in UNSCOPED_ROUTES.items() if rule == "admin only"}


def api_routes(app: Any) -> list[tuple[str, str]]:
    """(method, path under /api/v1) of every API route; WebSockets as method WEBSOCKET."""
    found = []
    for route in iter_route_contexts(app.routes):
        if not route.path.startswith(API_PREFIX + "/"):
            continue
        path = route.path.removeprefix(API_PREFIX)
        for method in sorted(route.methods - {"HEAD"}) if route.methods else ["WEBSOCKET"]:
            found.append((method, path))
    return found


def object_parameters(path: str) -> set[str]:
    return set(re.findall(r"\{(\w+)", path)) & OBJECT_PARAMETERS


def test_every_api_route_has_an_access_rule(client: TestClient) -> None:
    routes = api_routes(client.app)
    assert len(routes) >= 60
    missing = [f"{m} {p}" for m, p in routes if not object_parameters(p) and (m, p) not in UNSCOPED_ROUTES]
    assert not missing, f"routes without an access rule (server/auth/access.py UNSCOPED_ROUTES): {missing}"
    stale = sorted(set(UNSCOPED_ROUTES) - set(routes))
    assert not stale, f"rules for routes that do not exist: {stale}"


@dataclass
class Records:
    """One therapist's patient and everything hanging off it."""

    ids: dict[str, int]

    def url(self, path: str) -> str:
        return API_PREFIX + re.sub(r"\{(\w+)(:path)?\}", lambda m: str(self.ids.get(m.group(1), 1)), path)


def owned_records(client: TestClient, database: Database, seed: Seed, owner: str, serial: int) -> Records:
    headers = seed.headers(owner)
    patient_id = create_patient(client, headers, identifier=f"MRN-ACL-{owner}-{serial}")
    prescription_id = create_prescription(client, headers, patient_id)
    response = book(client, headers, patient_id=patient_id, prescription_id=prescription_id, robot=f"acl-{serial}",
                    start=f"2033-0{1 + serial}-03T09:00:00+00:00",
                    recurrence={"frequency": "weekly", "interval": 1, "count": 2})  # fmt: skip
    assert response.status_code == 201, response.text
    booking = response.json()[0]
    owner_id = seed.therapist_id if owner == "therapist" else seed.colleague_id
    return Records(
        {
            "patient_id": patient_id,
            "prescription_id": prescription_id,
            "session_id": booking["id"],
            "series_id": booking["series_id"],
            "run_id": fallen_run(database, booking),
            "therapist_id": owner_id,
            "user_id": seed.admin_id,  # care-team routes add and remove the admin: nobody loses access
            "version": 1,
        }
    )


def _example(document: dict[str, Any], method: str, path: str, records: Records) -> Any:
    operation = document["paths"][API_PREFIX + path][method.lower()]
    body = operation.get("requestBody")
    if body is None:
        return None
    reference = body["content"]["application/json"]["schema"]["$ref"]
    schema = document["components"]["schemas"][reference.rsplit("/", 1)[-1]]
    example = dict(schema["examples"][0])
    # Optional references the example leaves out (a preview's patient) are named too: they must be checked.
    example.update({k: records.ids[k] for k in schema.get("properties", {}) if k in PATIENT_OBJECTS})
    return {k: records.ids.get(k, v) if k.endswith("_id") else v for k, v in example.items()}


def _answer(client: TestClient, method: str, path: str, records: Records, headers: dict[str, str], body: Any) -> int:
    if method == "WEBSOCKET":
        token = headers["Authorization"].removeprefix("Bearer ")
        try:
            with client.websocket_connect(records.url(path) + f"?token={token}") as socket:
                socket.receive_json()  # accepted: this console has no robot, so it says so and closes
                return 200
        except WebSocketDisconnect as refused:
            return 404 if refused.code == 1008 else 200
    return client.request(method, records.url(path), json=body, headers=headers).status_code


def _order(route: tuple[str, str]) -> tuple[int, str]:
    # Creations first (the later routes act on them), removals last (nothing acts on a removed record).
    return ({"POST": 0, "DELETE": 2}.get(route[0], 1), route[1])


@pytest.mark.parametrize("owner", ["therapist", "colleague"])
@pytest.mark.parametrize("caller", ["admin", "owner", "stranger"])
def test_roles_routes_owners(client: TestClient, database: Database, seed: Seed, owner: str, caller: str) -> None:
    """Every route that names a patient's object, for records of either therapist: the admin and the owner
    get past the check (anything but 403/404), the other therapist gets 404 (403 for another's calendar)."""
    stranger = "colleague" if owner == "therapist" else "therapist"
    caller_role = {"admin": "admin", "owner": owner, "stranger": stranger}[caller]
    headers = seed.headers(caller_role)
    serial = ["admin", "owner", "stranger"].index(caller) + (3 if owner == "colleague" else 0)
    records = owned_records(client, database, seed, owner, serial=serial)
    document = client.get("/openapi.json").json()
    refused_wrongly: list[str] = []
    checked = 0
    for method, path in sorted(api_routes(client.app), key=_order):
        scoped = bool(object_parameters(path)) and (method, path) not in UNSCOPED_ROUTES
        in_body = (method, path) in BODY_SCOPED
        admin_only = (method, path) in ADMIN_ONLY
        if not (scoped or in_body or admin_only) or (admin_only and caller_role == "admin"):
            continue  # the admin's own routes are tested in test_api_users (these would end its login)
        body = _example(document, method, path, records) if method != "WEBSOCKET" else None
        status = _answer(client, method, path, records, headers, body)
        checked += 1
        if admin_only:
            expected_refusal = caller_role != "admin"
            refused = status == 403
        else:
            expected_refusal = caller == "stranger"
            self_object = "therapist_id" in object_parameters(path)
            refused = status == (403 if self_object else 404)
            if not expected_refusal:
                refused = status in (403, 404)
        if refused != expected_refusal:
            refused_wrongly.append(f"{method} {path} -> {status}")
    assert checked >= 35
    assert not refused_wrongly, f"{caller} ({caller_role}) on {owner}'s records: {refused_wrongly}"


def test_stop_and_pause_are_never_refused_by_care(robot_client: TestClient, seed: Seed) -> None:
    """A stop is never refused: another therapist's stop reaches the robot (409 here: nothing runs)."""
    patient_id = create_patient(robot_client, seed.headers())
    prescription_id = create_prescription(robot_client, seed.headers(), patient_id)
    booking = book(robot_client, seed.headers(), patient_id=patient_id, prescription_id=prescription_id).json()[0]
    for command in ("stop", "pause"):
        answer = robot_client.post(f"/api/v1/sessions/{booking['id']}/{command}", headers=seed.headers("colleague"))
        assert answer.status_code == 409, answer.text
    start = robot_client.post(f"/api/v1/sessions/{booking['id']}/start", headers=seed.headers("colleague"))
    assert start.status_code == 404, start.text


def test_lists_show_only_the_callers_care(client: TestClient, database: Database, seed: Seed) -> None:
    mine = owned_records(client, database, seed, "therapist", serial=1)
    theirs = owned_records(client, database, seed, "colleague", serial=2)
    headers = seed.headers("therapist")

    def ids(url: str) -> set[int]:
        response = client.get(url, headers=headers)
        assert response.status_code == 200, response.text
        return {row["id"] for row in response.json()}

    assert mine.ids["patient_id"] in ids("/api/v1/patients")
    assert theirs.ids["patient_id"] not in ids("/api/v1/patients")
    assert ids("/api/v1/prescriptions") & {mine.ids["prescription_id"], theirs.ids["prescription_id"]} == {
        mine.ids["prescription_id"]
    }
    assert ids(f"/api/v1/sessions?therapist_id={seed.colleague_id}") == set()
    assert theirs.ids["session_id"] in {
        row["id"] for row in client.get("/api/v1/sessions", headers=seed.headers("admin")).json()
    }
    week = client.get("/api/v1/schedule/week?day=2033-02-03", headers=headers).json()["bookings"]
    week += client.get("/api/v1/schedule/week?day=2033-03-03", headers=headers).json()["bookings"]
    shown = {b["id"]: b for b in week}
    assert shown[theirs.ids["session_id"]]["in_care"] is False  # busy, but no name
    assert shown[theirs.ids["session_id"]]["patient_name"] == ""
    assert shown[mine.ids["session_id"]]["patient_name"] == "Greta Testperson"
    pending = client.get("/api/v1/reviews/pending?robot=acl-2", headers=headers).json()
    assert pending["run_id"] == theirs.ids["run_id"] and pending["needs_acknowledgement"]


def test_a_booking_hands_the_patient_over(client: TestClient, seed: Seed) -> None:
    """Cover and handover: a member books a colleague, who joins the care team (audited); the colleague
    could not see the patient before."""
    headers = seed.headers("therapist")
    patient_id = create_patient(client, headers)
    assert client.get(f"/api/v1/patients/{patient_id}", headers=seed.headers("colleague")).status_code == 404
    prescription_id = create_prescription(client, headers, patient_id)
    answer = book(
        client, headers, patient_id=patient_id, prescription_id=prescription_id, therapist_id=seed.colleague_id
    )
    assert answer.status_code == 201, answer.text
    assert client.get(f"/api/v1/patients/{patient_id}", headers=seed.headers("colleague")).status_code == 200
    team = client.get(f"/api/v1/patients/{patient_id}/care-team", headers=headers).json()
    assert {m["username"] for m in team} == {"therapist", "colleague"}
    removed = client.delete(f"/api/v1/patients/{patient_id}/care-team/{seed.colleague_id}", headers=headers)
    assert removed.status_code == 204
    refused = client.get(f"/api/v1/patients/{patient_id}", headers=seed.headers("colleague"))
    assert refused.status_code == 404 and "not in the care of your account" in refused.json()["detail"]
