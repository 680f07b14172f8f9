"""Speed, latency and scale measurements. Each `bench_<name>.py` has `run(*, quick: bool) -> dict`.

Run with `ssp-rehab bench <name> [--json] [--write-results]`; dated figures go to RESULTS.md.
Timing targets live here, not in unit tests, and compare against a baseline measured in the same run.
"""
