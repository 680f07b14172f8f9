"""The robot daemon: one long-lived process tree per robot (`ssp-rehab robot --robot NAME`) that owns
the real-time worker, its heartbeat relay, the HAL, a planning process and the recorder, and decides
and records every run. Web processes attach to it (server.robotd.link) to send commands and read state.
See docs/realtime.md."""
