"""The robot daemon: one long-lived process tree per robot (`ssp-rehab robot --robot NAME`) that owns
the real-time worker, its heartbeat relay, the HAL, a planning process and the recorder, and decides
and records every run: its rules (`runs`), tables (`models`) and records (`records`). Web processes
attach to it (`link`) to send commands and read state, through the seams in `interfaces`.
See docs/realtime.md."""
