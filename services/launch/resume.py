"""``run.json``: what a run leaves for ``relaxmap run --resume`` to continue it, written at its end."""

from __future__ import annotations

from pathlib import Path

import msgspec

from services.common.files import atomic_write
from services.launch.monitor import MonitorState

RUN_FILE = "run.json"
STORE_FILE = "map.sqlite"
RUN_FORMAT = 1  # the format of run.json this relaxmap writes and reads


class ResumeError(ValueError):
    """The directory holds no run that can be continued; the message says why."""


class RunRecord(msgspec.Struct, frozen=True, kw_only=True):
    """The content of ``run.json``."""

    format: int  # RUN_FORMAT
    world: str  # the world as given on the command line (a built-in name or a file)
    world_ref: str  # the built-in name, or the world file's absolute path
    seed: int
    parts: int  # how many runs made this directory (1, then one more per --resume)
    sim_time_s: float  # simulated time at the end
    wall_time_s: float  # wall time of every part together
    exploration_complete: bool
    places: int  # places of the final map
    recording_id: str  # the Rerun recording id every part's recording file shares
    recordings: list[str]  # the recording files of the parts, in order (names in the directory)
    monitor: MonitorState  # the launcher's counts and where the robot was


_DECODER = msgspec.json.Decoder(RunRecord)


def write_run_record(out: Path, record: RunRecord) -> None:
    """Write ``out/run.json`` atomically (a reader never sees half of it)."""
    atomic_write(out / RUN_FILE, msgspec.json.format(msgspec.json.encode(record), indent=2) + b"\n")


def read_run_record(out: Path) -> RunRecord:
    """The run saved in ``out``, checked to be one that can be continued.

    Raises
    ------
    ResumeError
        When ``out`` is not a directory, has no ``run.json`` or map store, the file is not one
        relaxmap wrote, or the run cannot go on (its exploration is complete, it has no place, or it
        ended before the robot's first move was heard).
    """
    if not out.is_dir():
        raise ResumeError(f"{out} is not a directory")
    path = out / RUN_FILE
    if not path.is_file():
        raise ResumeError(f"{out} holds no saved run ({RUN_FILE} is missing; a run writes it when it ends)")
    try:
        record = _DECODER.decode(path.read_bytes())
    except msgspec.DecodeError as e:
        raise ResumeError(f"{path} is not a run relaxmap saved: {e}") from None
    if record.format != RUN_FORMAT:
        raise ResumeError(f"{path} has format {record.format}; this relaxmap reads format {RUN_FORMAT}")
    if not (out / STORE_FILE).is_file():
        raise ResumeError(f"{out} has no map store ({STORE_FILE})")
    if record.exploration_complete:
        raise ResumeError(f"the run in {out} completed its exploration: there is nothing to continue")
    if record.places == 0:
        raise ResumeError(f"the run in {out} confirmed no place: start a new run instead")
    if record.monitor.robot is None:
        raise ResumeError(f"the run in {out} ended before any dead-reckoned pose was heard: start a new run")
    return record


def recording_name(part: int) -> str:
    """The recording file of a run's ``part`` (1: ``recording.rrd``, then ``recording-2.rrd`` ...)."""
    return "recording.rrd" if part == 1 else f"recording-{part}.rrd"
