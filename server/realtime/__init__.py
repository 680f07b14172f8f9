"""The real-time worker: fixed-rate loop, safety supervisor, per-tick pipeline and its shared-memory interface."""
