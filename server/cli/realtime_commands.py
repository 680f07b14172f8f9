"""`ssp-rehab realtime check` (the offline prescription check) and `ssp-rehab realtime run` (play a
prescription on a spawned worker and report its timing)."""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any

import typer

from core.errors import InvalidValueError
from server.cli.output import console, emit, fail, print_violations_by_reason, progress_bar
from server.cli.robot_option import ROBOT_OPTION, twin_from_option

# The default is core.plan.config.DEFAULT_CONTROL_RATE_HZ, read when a command runs (that module loads numba).
RATE_HELP = "Control rate, 250–2000 Hz (default 1000 Hz, the worker's)."
realtime_app = typer.Typer(help="The real-time worker: prescription checks and worker runs.", no_args_is_help=True)


def _read_json(path: Path | None, what: str, as_json: bool) -> Any:
    if path is None:
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as error:
        raise fail(f"{what} = {str(path)!r}: not a readable JSON file ({error})", as_json=as_json) from None


def _human_report(data: dict[str, Any]) -> None:
    if "rejected" in data:
        rejected = data["rejected"]
        console.print(f"[bold red]refused[/]: {rejected['message']}")
        # Every kinematic limit the segment breaks, not only the first (issue 13).
        print_violations_by_reason(rejected.get("violations_by_reason", {}))
        return
    console.print(f"[bold green]accepted[/]: {data['samples']} samples, {data['duration_s']:.3f} s with transitions")
    for name, use in sorted(data["peak_use"].items()):
        console.print(f"  {name:22s} peak {100 * use:6.1f} % of its limit")


@realtime_app.command("check")
def check(
    prescription_file: Path = typer.Argument(..., help="Prescription JSON: {'segments': [...]}"),
    patient_file: Path | None = typer.Option(None, "--patient", help="Patient JSON: body_mass_kg, height_m, preset."),
    control_rate_hz: int | None = typer.Option(None, "--rate", help=RATE_HELP),
    robot_file: Path | None = ROBOT_OPTION,
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Run a prescription offline through the batch pipeline; refuse it if any limit would be exceeded."""
    from core.plan.build import check_prescription
    from core.plan.config import DEFAULT_CONTROL_RATE_HZ
    from core.plan.prescription import PrescriptionError
    from core.plan.rejection import PrescriptionRejected
    from server.realtime.loop import LoopConfigError, validate_control_rate

    prescription = _read_json(prescription_file, "prescription_file", as_json)
    patient = _read_json(patient_file, "patient_file", as_json)
    try:
        rate_hz = validate_control_rate(
            DEFAULT_CONTROL_RATE_HZ if control_rate_hz is None else control_rate_hz
        )  # the worker's range, not only what a plan allows
        report = check_prescription(
            prescription, twin_from_option(robot_file), control_rate_hz=rate_hz, patient=patient
        )
    except PrescriptionRejected as rejected:
        emit({"rejected": rejected.to_dict()}, as_json=as_json, human=_human_report)
        raise typer.Exit(1) from None
    except (PrescriptionError, LoopConfigError, InvalidValueError) as error:
        raise fail(str(error), as_json=as_json) from None
    emit(report.to_dict(), as_json=as_json, human=_human_report)


@realtime_app.command("run")
def run(
    prescription_file: Path = typer.Argument(..., help="Prescription JSON to play."),
    patient_file: Path | None = typer.Option(None, "--patient", help="Patient JSON: body_mass_kg, height_m, preset."),
    seconds: float = typer.Option(10.0, "--seconds", min=0.5, max=3600.0, help="How long to let it play."),
    backend: str = typer.Option("kinematic", "--backend", help="HAL backend: kinematic or sim."),
    control_rate_hz: int | None = typer.Option(None, "--rate", help=RATE_HELP),
    robot_file: Path | None = ROBOT_OPTION,
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Spawn a worker, play the prescription, stop it, and report tick timing and events."""
    import numpy as np

    from core.plan.config import DEFAULT_CONTROL_RATE_HZ
    from core.plan.prescription import PrescriptionError
    from core.plan.rejection import PrescriptionRejected
    from server.messages import CommandRefused
    from server.realtime.client import WorkerClient, WorkerError
    from server.realtime.loop import LoopConfigError
    from server.robotd.playback import plan_and_load

    prescription = _read_json(prescription_file, "prescription_file", as_json)
    patient = _read_json(patient_file, "patient_file", as_json)
    rate_hz = DEFAULT_CONTROL_RATE_HZ if control_rate_hz is None else control_rate_hz
    try:
        client = WorkerClient(str(robot_file) if robot_file else None, backend, rate_hz)
    except (ValueError, LoopConfigError) as error:
        raise fail(str(error), as_json=as_json) from None
    records, events = [], []
    try:
        client.start()
        playback, _ = plan_and_load(client, prescription, patient)
        playback.start(client)
        with progress_bar("playing", round(seconds * 10), enabled=not as_json) as advance:
            for _ in range(round(seconds * 10)):
                time.sleep(0.1)
                records.append(client.drain_telemetry())
                advance(1)
        client.stop()
        deadline = time.monotonic() + 60.0
        while client.latest_state()["state"] not in ("stopped", "idle") and time.monotonic() < deadline:
            time.sleep(0.05)
        records.append(client.drain_telemetry())
        events = client.drain_events()
    except (PrescriptionRejected, PrescriptionError, CommandRefused, WorkerError) as error:
        raise fail(str(error), as_json=as_json) from None
    finally:
        client.shutdown()
    telemetry = np.concatenate(records)
    compute, lateness = telemetry["tick_compute_us"].astype(float), telemetry["lateness_us"].astype(float)
    summary = {
        "ticks": len(telemetry),
        "tick_compute_us": {"p50": float(np.percentile(compute, 50)), "p99": float(np.percentile(compute, 99))},
        "lateness_us": {
            "p50": float(np.percentile(lateness, 50)),
            "p99": float(np.percentile(lateness, 99)),
            "max": float(lateness.max()),
        },
        "deadline_misses": int(telemetry["deadline_misses"][-1]),
        "events": [{"kind": e["kind"], "tick": e["tick"], **e["details"]} for e in events],
    }
    emit(summary, as_json=as_json, human=lambda data: console.print_json(json.dumps(data, default=str)))


def plan(
    prescription_file: Path = typer.Argument(..., help="Prescription JSON: {'segments': [...]}"),
    cueing: str | None = typer.Option(None, "--cueing", help="classical or optimal (default: the file's)."),
    patient_file: Path | None = typer.Option(None, "--patient", help="Patient JSON: body_mass_kg, height_m, preset."),
    control_rate_hz: int | None = typer.Option(None, "--rate", help=RATE_HELP),
    robot_file: Path | None = ROBOT_OPTION,
    data_dir: Path | None = typer.Option(None, "--data-dir", help="Store the plan here for the robot daemon."),
    as_json: bool = typer.Option(False, "--json"),
) -> None:
    """Plan and check a prescription as the robot daemon does (every sample it would play), with progress;
    print its plan id (the key Start finds it by), duration, planning time and check report. With
    --data-dir the checked plan is stored where that console's robot daemon plays it from."""
    import resource

    from core.plan.config import DEFAULT_CONTROL_RATE_HZ
    from core.plan.prescription import PrescriptionError
    from core.plan.rejection import PrescriptionRejected
    from core.robot import twin_digest
    from server.realtime.loop import LoopConfigError, validate_control_rate
    from server.realtime.supervisor import SupervisorConfig
    from server.robotd.plan_store import PlanStore, plan_key
    from server.robotd.planner import checked_plan

    prescription = _read_json(prescription_file, "prescription_file", as_json)
    patient = _read_json(patient_file, "patient_file", as_json)
    if cueing is not None:
        if cueing not in ("classical", "optimal"):
            raise fail(f"--cueing = {cueing!r}: must be classical or optimal", as_json=as_json)
        prescription = {**prescription, "cueing": cueing}
    config = SupervisorConfig()
    began_wall, began_cpu = time.perf_counter(), resource.getrusage(resource.RUSAGE_SELF)
    try:
        rate_hz = validate_control_rate(DEFAULT_CONTROL_RATE_HZ if control_rate_hz is None else control_rate_hz)
        twin = twin_from_option(robot_file)
        with progress_bar("planning and checking", 1000, enabled=not as_json) as advance:
            done = [0]

            def progress(fraction: float) -> None:
                step = round(fraction * 1000) - done[0]
                if step > 0:
                    done[0] += step
                    advance(step)

            plan, report = checked_plan(twin, rate_hz, config, prescription, patient, progress)
        feasible, refusal = True, None
    except PrescriptionRejected as rejected:
        feasible, refusal, plan, report = False, rejected.to_dict(), None, {}
    except (PrescriptionError, LoopConfigError, InvalidValueError) as error:
        raise fail(str(error), as_json=as_json) from None
    ended = resource.getrusage(resource.RUSAGE_SELF)
    key = plan_key(
        prescription, patient, robot_digest=twin_digest(twin), config=config.to_dict(), control_rate_hz=rate_hz
    )
    if plan is not None and data_dir is not None:
        PlanStore(data_dir.resolve() / "plans").save(key, plan, report)
    result = {
        "plan_id": key,
        "feasible": feasible,
        "duration_s": report.get("duration_s"),
        "planning_wall_s": round(time.perf_counter() - began_wall, 3),
        "planning_cpu_s": round(
            ended.ru_utime + ended.ru_stime - began_cpu.ru_utime - began_cpu.ru_stime, 3
        ),  # this process: the check's batch kernels may use both cores
        "report": report if feasible else None,
        "rejected": refusal,
        "stored": str(data_dir.resolve() / "plans" / key) if plan is not None and data_dir is not None else None,
    }

    def human(data: dict[str, Any]) -> None:
        _human_report(data["report"] if data["feasible"] else {"rejected": data["rejected"]})
        console.print(
            f"plan {data['plan_id']}: planned in {data['planning_wall_s']} s "
            f"({data['planning_cpu_s']} s of CPU)" + (f"; stored in {data['stored']}" if data["stored"] else "")
        )

    emit(result, as_json=as_json, human=human)
    if not feasible:
        raise typer.Exit(1)


def register(app: typer.Typer) -> None:
    app.add_typer(realtime_app, name="realtime")
    app.command("plan")(plan)
