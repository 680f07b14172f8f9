"""Session runs: run control through the real-time worker, events, the telemetry WebSocket, the durable
session log (telemetry chunks + events) and its export."""
