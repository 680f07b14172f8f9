"""Observability of the console service: Prometheus metrics at /metrics and structured JSON logs."""
