"""Every message of the relaxmap process graph, as frozen, tagged msgspec structs."""

from __future__ import annotations

from typing import Literal

import msgspec

# Schema evolution rule: a message type is never changed incompatibly. A new field is added only with
# a default, at the end; a field is never removed, renamed or retyped. Decoders therefore accept
# messages from older publishers (missing fields take their defaults) and from newer ones (unknown
# fields are ignored by msgspec).


class Message(msgspec.Struct, frozen=True, tag=True, kw_only=True):
    """Base of every bus message.

    Attributes
    ----------
    stamp : float
        Simulated time of the event, seconds since the start of the run.
    seq : int
        Sequence number per publisher, starting at 0 and increasing by one per message.
    """

    stamp: float
    seq: int


class Pose2(msgspec.Struct, frozen=True, kw_only=True):
    """A planar pose: position in metres, heading in radians (counter-clockwise from +x)."""

    x_m: float
    y_m: float
    heading_rad: float


# --- sensors ---------------------------------------------------------------------------------------


class OdometryStep(Message, frozen=True, kw_only=True):
    """Wheel odometry increments over one simulation step, in the robot frame."""

    distance_m: float  # signed distance travelled by the wheels in this step
    rotation_rad: float  # heading change measured by the wheels in this step
    dt_s: float  # duration of the step
    sonar_seq: int = -1  # seq of the latest sonar scan of this tick or earlier (-1: none yet); the simulator
    # publishes a tick's scan before its step, so a receiver of the step knows whether the tick has a scan


class CompassReading(Message, frozen=True, kw_only=True):
    """Absolute heading from the magnetic compass, radians in (-pi, pi]."""

    heading_rad: float


class SonarScan(Message, frozen=True, kw_only=True):
    """One reading of the sonar ring. Ranges equal to ``max_range_m`` mean no echo."""

    angles_rad: list[float]  # bearing of each transducer relative to the robot heading
    ranges_m: list[float]  # measured range of each transducer
    beam_width_rad: float  # full opening angle of each beam cone
    min_range_m: float
    max_range_m: float


class TruthPose(Message, frozen=True, kw_only=True):
    """Ground-truth pose of the simulated robot (evaluation only; never used for mapping)."""

    pose: Pose2


# --- dead reckoning --------------------------------------------------------------------------------


class DeadReckonedPose(Message, frozen=True, kw_only=True):
    """Compass-based and raw odometry poses side by side, with the step record.

    The step record (``steps``, ``path_length_m``) counts odometry steps and the distance they covered
    since the start; a link measurement between two marks takes ``T = steps_b - steps_a`` and the mean
    step length ``(path_length_b - path_length_a) / T``.
    """

    compass: Pose2  # heading from the compass, distance from the wheels
    raw: Pose2  # wheels only: drifts in rotation
    steps: int  # odometry steps integrated since the start
    path_length_m: float  # distance integrated since the start (absolute values of the steps)
    gaps: int = 0  # sensor messages missed so far (detected through seq)


# --- places and links ------------------------------------------------------------------------------


class Hypothesis(msgspec.Struct, frozen=True, kw_only=True):
    """One place hypothesis of the localization belief."""

    place_id: int
    probability: float


class LocalizationBelief(Message, frozen=True, kw_only=True):
    """The place recognizer's belief over places. ``place_id`` is -1 when between places."""

    place_id: int
    probability: float
    offset_x_m: float  # filtered offset of the robot from the place centre, world frame
    offset_y_m: float
    offset_var_m2: float  # variance of the offset estimate (per axis)
    hypotheses: list[Hypothesis] = []  # the best few, most probable first
    pose: Pose2 | None = None  # the compass dead-reckoned pose of the scan (same stamp) the belief took in
    link_seq: int = -1  # seq of the latest link the recognizer published up to this belief's scan (-1: none):
    # a commander following the relaxed map waits for the map update that holds it


class RecognizerProgress(Message, frozen=True, kw_only=True):
    """The place recognizer has done the work of one simulator tick: the explorer's place events of the
    tick before and the tick's sonar scan (whichever of them there were). ``link_seq`` is the latest link
    it had published then (-1: none). A lockstep commander following the relaxed map waits for it, and
    for the map update that holds that link, before it answers the tick (as the in-process loop steps
    the explorer after the recognizer)."""

    tick: int
    link_seq: int = -1


class PlacePredicted(Message, frozen=True, kw_only=True):
    """A place the explorer expects but has not visited; position in the dead-reckoning frame."""

    place_id: int
    x_m: float
    y_m: float
    parent_id: int  # the confirmed place it was predicted from


class PlaceConfirmed(Message, frozen=True, kw_only=True):
    """A visited place; initial coordinates from dead reckoning relative to the last place."""

    place_id: int
    x_m: float
    y_m: float


class PlaceDeleted(Message, frozen=True, kw_only=True):
    """A place removed from the map (predicted but unreachable, or no longer reached by any path)."""

    place_id: int
    reason: str


class LinkMeasured(Message, frozen=True, kw_only=True):
    """A traversed link with its measurement (Eqs. 24-27): displacement from ``from_id`` to ``to_id``."""

    from_id: int
    to_id: int
    d_m: float  # measured distance
    theta_rad: float  # absolute (compass) angle of the displacement
    steps: int  # odometry steps along the traversal (T_ji)
    mean_step_m: float  # mean step length along the traversal (delta_bar_ji)
    variance_m2: float | None = None  # set: circular noise model (Appendix A) for this link
    traversals: int = 1  # how many traversals were fused into this measurement


class LinkInferred(Message, frozen=True, kw_only=True):
    """A link the explorer believes exists but was never traversed (path planning only)."""

    from_id: int
    to_id: int
    d_m: float


class LinkConfidence(Message, frozen=True, kw_only=True):
    """The explorer's confidence in a link (Eqs. 17-18)."""

    from_id: int
    to_id: int
    confidence: float


class LinkDeleted(Message, frozen=True, kw_only=True):
    """A link removed from the map (confidence fell below the threshold)."""

    from_id: int
    to_id: int
    reason: str


# --- control and exploration -----------------------------------------------------------------------


class VelocityCommand(Message, frozen=True, kw_only=True):
    """Velocity command for the robot. ``tick`` is the simulation tick it answers (lockstep clock).

    ``confirmed_seq``, ``deleted_seq`` and ``links_deleted_seq`` are the seqs of the latest
    ``PlaceConfirmed``, ``PlaceDeleted`` and ``LinkDeleted`` the explorer published before this command
    (-1: none), so that a receiver knows which events it must have heard: zenoh keeps the order of one
    key's messages, not across keys. The relaxer applies the events a command names together.
    ``relocalisations`` counts the explorer's requests to the place recognizer to relocalise, up to
    this command (its legs keep failing from where the belief puts the robot): the recognizer acts on
    a rise of the count before its next scan. ``final`` marks the last command of a run (the explorer's
    at the tick its exploration became complete): the simulator computes no tick after it.
    """

    v_mps: float
    omega_radps: float
    tick: int
    confirmed_seq: int = -1
    deleted_seq: int = -1
    relocalisations: int = 0
    links_deleted_seq: int = -1
    final: bool = False


class ExplorationStatus(Message, frozen=True, kw_only=True):
    """Progress of the explorer; ``complete`` once no predicted place is left."""

    complete: bool
    confirmed: int
    predicted: int
    target_id: int  # -1 when none


# --- the map ---------------------------------------------------------------------------------------


class PlacePosition(msgspec.Struct, frozen=True, kw_only=True):
    """Relaxed coordinates of one place, metres."""

    place_id: int
    x_m: float
    y_m: float


class NoiseParams(msgspec.Struct, frozen=True, kw_only=True):
    """The three global noise parameters of Eq. 5: per-step variances and covariance."""

    s_dd: float  # distance variance per step, m^2
    s_aa: float  # heading variance per step, rad^2
    s_da: float  # covariance of distance and heading per step, m rad


class MapUpdate(Message, frozen=True, kw_only=True):
    """The relaxer's map after one relaxation cycle: the places that moved, energy and noise."""

    version: int  # increases by one per update
    changed: list[PlacePosition]  # places whose coordinates changed (all of them on a full update)
    full: bool  # True when ``changed`` holds every place
    places: int
    links: int
    energy: float  # Eq. 7 at the new coordinates
    iterations: int  # relaxation sweeps or solver iterations in this cycle
    method: str  # what ran this cycle: "sweep", "exact", "multilevel", ...
    noise: NoiseParams
    link_seq: int = -1  # the highest seq of a measured link the relaxer had taken in (held or waiting for its
    # places) when it made this update; -1: none
    confirmed_seq: int = -1  # ... and of a place confirmation applied
    deleted_seq: int = -1  # ... of a place deletion applied
    links_deleted_seq: int = -1  # ... of a link deletion applied


# --- system ----------------------------------------------------------------------------------------


class Health(Message, frozen=True, kw_only=True):
    """A service's health, served on ``relaxmap/<robot>/health/<service>``; stamp is wall seconds."""

    service: str
    pid: int
    uptime_s: float
    messages_in: int
    messages_out: int
    decode_errors: int
    query_errors: int
    detail: dict[str, float] = {}  # service-specific counters


# --- query replies (relaxer's query API) ------------------------------------------------------------


class MapPlace(msgspec.Struct, frozen=True, kw_only=True):
    """A confirmed place of the map with its relaxed coordinates, metres."""

    place_id: int
    x_m: float
    y_m: float


class MapLink(msgspec.Struct, frozen=True, kw_only=True):
    """A traversed link of the map and its (fused) measurement, as in ``LinkMeasured``."""

    from_id: int
    to_id: int
    d_m: float
    theta_rad: float
    steps: int
    mean_step_m: float
    variance_m2: float | None = None
    traversals: int = 1


class MapGraph(msgspec.Struct, frozen=True, kw_only=True):
    """The whole map (reply of ``map/graph``)."""

    version: int
    places: list[MapPlace]
    links: list[MapLink]
    energy: float
    noise: NoiseParams
    pinned: int  # id of the place held fixed (gauge); -1 for an empty map
    deleted: list[int] = []  # ids of the places deleted for good (an id is never used again)


class PlaceReply(msgspec.Struct, frozen=True, kw_only=True):
    """One place with its links (reply of ``map/place/<id>``)."""

    place: MapPlace
    links: list[MapLink]


class PathReply(msgspec.Struct, frozen=True, kw_only=True):
    """Shortest path over traversed links (reply of ``map/path``)."""

    from_id: int
    to_id: int
    places: list[int]  # from_id first, to_id last
    length_m: float  # sum of the measured link distances along the path


class OccupancyGrid(msgspec.Struct, frozen=True, kw_only=True):
    """A global occupancy grid (reply of ``map/grid``), row-major from the origin corner.

    ``cells`` holds one byte per cell: 0-100 occupancy probability in percent, 255 unknown (as ROS's
    -1). Row ``r``, column ``c`` covers ``x = origin_x_m + c * resolution_m`` and
    ``y = origin_y_m + r * resolution_m``.
    """

    resolution_m: float
    origin_x_m: float
    origin_y_m: float
    width: int
    height: int
    cells: bytes
    version: int  # map version the grid was built from


class MapStats(msgspec.Struct, frozen=True, kw_only=True):
    """Counts, energy, iterations and timings of the relaxer (reply of ``map/stats``)."""

    version: int
    places: int
    links: int
    energy: float
    updates: int  # relaxation cycles run
    iterations: int  # sweeps or solver iterations over all cycles
    cycle_ms_mean: float
    cycle_ms_p99: float
    methods: dict[str, int]  # cycles per method ("sweep", "exact", ...)
    noise: NoiseParams


class PlaceScan(msgspec.Struct, frozen=True, kw_only=True):
    """A sonar scan the relaxer keeps for the grid: the place it was taken at and where the robot was."""

    stamp: float  # simulated time of the scan
    place_id: int  # the place the scan belongs to
    offset_x_m: float  # robot minus place centre when the scan was taken, world frame
    offset_y_m: float
    dr_x_m: float  # the robot's compass dead-reckoned position then
    dr_y_m: float
    heading_rad: float  # compass heading then
    angles_rad: list[float]  # bearing of each transducer relative to the heading
    ranges_m: list[float]
    beam_width_rad: float
    max_range_m: float


class ScanSet(msgspec.Struct, frozen=True, kw_only=True):
    """Stored sonar scans, oldest first (reply of ``map/scans``)."""

    version: int  # map version when the reply was made
    scans: list[PlaceScan]


class ErrorReply(msgspec.Struct, frozen=True, kw_only=True):
    """Payload of an error reply to a query: what was wrong."""

    error: str
    key: str


ALL_REPLIES: tuple[type, ...] = (MapGraph, PlaceReply, PathReply, OccupancyGrid, MapStats, ScanSet, ErrorReply)

ALL_MESSAGES: tuple[type[Message], ...] = (
    OdometryStep,
    CompassReading,
    SonarScan,
    TruthPose,
    DeadReckonedPose,
    LocalizationBelief,
    RecognizerProgress,
    PlacePredicted,
    PlaceConfirmed,
    PlaceDeleted,
    LinkMeasured,
    LinkInferred,
    LinkConfidence,
    LinkDeleted,
    VelocityCommand,
    ExplorationStatus,
    MapUpdate,
    Health,
)
