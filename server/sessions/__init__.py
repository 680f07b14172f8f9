"""The web side of runs: run control and the robot's state as routes (to the robot daemon, through
server.robotd.link), runs and events read back, session logs and exports, balance measures, and the
telemetry WebSocket's fan-out. The runs themselves are the robot daemon's (server.robotd.runs)."""
