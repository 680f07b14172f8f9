"""The seam to the real-time worker (server/realtime, see its issue): what run control needs from it,
and starting it with the service. With no worker the service keeps working; run control answers 503."""

from __future__ import annotations

import importlib
import logging
from typing import Any, Protocol

import numpy as np

from server.settings import Settings

logger = logging.getLogger(__name__)

# Where the worker package may expose WorkerClient; the first that has it wins.
WORKER_CLIENT_MODULES = (
    "server.realtime",
    "server.realtime.client",
    "server.realtime.worker_client",
    "server.realtime.worker",
)


class WorkerControl(Protocol):
    """The agreed WorkerClient interface (only the part the service uses)."""

    def start(self) -> None: ...
    def shutdown(self) -> None: ...
    def load_prescription(self, prescription: dict[str, Any], patient: dict[str, Any] | None) -> Any: ...
    def start_motion(self) -> Any: ...
    def pause(self) -> Any: ...
    def resume(self) -> Any: ...
    def stop(self) -> Any: ...
    def emergency_stop(self) -> Any: ...
    def reset(self) -> Any: ...
    def latest_state(self) -> dict[str, Any]: ...
    def drain_telemetry(self) -> np.ndarray: ...
    def drain_events(self) -> list[dict[str, Any]]: ...


def worker_client_class() -> type | None:
    for module_name in WORKER_CLIENT_MODULES:
        try:
            module = importlib.import_module(module_name)
        except ImportError:
            continue
        client = getattr(module, "WorkerClient", None)
        if client is not None:
            return client
    return None


def start_worker(settings: Settings) -> WorkerControl | None:
    """Spawn the real-time worker for `settings.backend`; None (logged) when it cannot run."""
    client_class = worker_client_class()
    if client_class is None:
        logger.warning("no real-time worker is installed (server.realtime): running without a robot")
        return None
    try:
        hal_options = (
            {
                "interface": settings.can_interface,
                "channel": settings.can_channel,
                "simulate": settings.can_simulated_drives,
            }
            if settings.backend == "canopen"
            else {}
        )
        worker: WorkerControl = client_class(
            str(settings.robot_file) if settings.robot_file else None,
            settings.backend,
            settings.control_rate_hz,
            hal_options=hal_options,
        )
        worker.start()
    except Exception:
        logger.exception("the real-time worker (backend %s) did not start: running without a robot", settings.backend)
        return None
    logger.info("real-time worker started: backend %s at %d Hz", settings.backend, settings.control_rate_hz)
    return worker
