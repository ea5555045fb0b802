"""Recorder node: bus messages in, Rerun archetypes out, on the simulated-time timeline."""

from __future__ import annotations

import logging
import shutil
import socket
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import rerun as rr
import rerun.blueprint as rrb
import zenoh

from messages import topics
from messages.types import (
    DeadReckonedPose,
    ExplorationStatus,
    LinkDeleted,
    LinkInferred,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    OccupancyGrid,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePredicted,
    SonarScan,
    TruthPose,
)
from services.recorder.core import POSE_SOURCES, STYLE, RecorderParams, RecorderState, grid_image
from services.runtime import Node, query

log = logging.getLogger("relaxmap.recorder")

APPLICATION_ID = "relaxmap"
SIM_TIME = "sim_time"  # timeline of simulated seconds (each message's stamp)
MAP_VERSION = "map_version"  # timeline of map versions (MapUpdate.version), set from the first update on
FLUSH_TIMEOUT_S = 10.0  # longest wait for the stream to reach the file when closing
DRAIN_S = 1.0  # after the stop, messages already queued are still recorded for at most this long
# A pose's arrows are sent this many at a time, as columns (rr.send_columns): 46 us an arrow instead of
# 140 us for one rr.log each. At the default 0.5 s a pose, that is every 10 simulated seconds.
ARROW_BATCH = 20

# Entity paths. Everything spatial lives under MAP, in metres, world frame.
MAP = "map"
GRID = "map/grid"
CONFIRMED = "map/places/confirmed"
PREDICTED = "map/places/predicted"
TRAVERSED = "map/links/traversed"
INFERRED = "map/links/inferred"
SONAR_RAYS = "map/sonar/rays"
SONAR_ECHOES = "map/sonar/echoes"
BELIEF_ESTIMATE = "map/belief/estimate"
BELIEF_HYPOTHESES = "map/belief/hypotheses"
ENERGY = "plots/energy"
ITERATIONS = "plots/iterations"
MAP_PLACES = "plots/map_size/places"
MAP_LINKS = "plots/map_size/links"
EXPLORED_CONFIRMED = "plots/exploration/confirmed"
EXPLORED_PREDICTED = "plots/exploration/predicted"
BELIEF_PROBABILITY = "plots/belief/probability"
EVENTS = "events"


def pose_path(source: str) -> str:
    """Arrow of a pose source ("truth", "compass", "raw")."""
    return f"map/robot/{source}/pose"


def trail_path(source: str) -> str:
    return f"map/robot/{source}/trail"


def _ui(pt: float) -> float:
    return rr.Radius.ui_points(pt)


def _styles() -> dict[str, rr.AsComponents]:
    """Entity path -> the components that say how it is drawn (logged static, once)."""
    styles: dict[str, rr.AsComponents] = {
        CONFIRMED: rr.Points2D.from_fields(colors=[STYLE.confirmed_color], radii=_ui(STYLE.confirmed_radius_pt),
                                           show_labels=True, draw_order=30.0),
        PREDICTED: rr.Points2D.from_fields(colors=[STYLE.predicted_color], radii=_ui(STYLE.predicted_radius_pt),
                                           show_labels=True, draw_order=29.0),
        TRAVERSED: rr.LineStrips2D.from_fields(colors=[STYLE.traversed_color],
                                               radii=_ui(STYLE.traversed_width_pt / 2), draw_order=20.0),
        INFERRED: rr.LineStrips2D.from_fields(colors=[STYLE.inferred_color],
                                              radii=_ui(STYLE.inferred_width_pt / 2), draw_order=19.0),
        SONAR_RAYS: rr.LineStrips2D.from_fields(radii=_ui(STYLE.ray_width_pt / 2), draw_order=25.0),
        SONAR_ECHOES: rr.Points2D.from_fields(colors=[STYLE.echo_color], radii=_ui(STYLE.echo_radius_pt),
                                              draw_order=26.0),
        BELIEF_ESTIMATE: rr.Ellipses2D.from_fields(colors=[STYLE.belief_color], line_radii=_ui(1.0),
                                                   draw_order=45.0),
        BELIEF_HYPOTHESES: rr.Points2D.from_fields(colors=[(*STYLE.belief_color[:3], 90)], draw_order=28.0),
    }
    for source in POSE_SOURCES:
        styles[pose_path(source)] = rr.Arrows2D.from_fields(colors=[STYLE.pose_color(source)],
                                                            radii=_ui(STYLE.pose_width_pt / 2), draw_order=40.0)
        styles[trail_path(source)] = rr.LineStrips2D.from_fields(colors=[STYLE.pose_color(source)],
                                                                 radii=_ui(STYLE.trail_width_pt / 2), draw_order=35.0)
    return styles


def blueprint() -> rrb.Blueprint:
    """The default layout: the map on the left; the grid, energy, iterations and the rest on the right."""
    return rrb.Blueprint(
        rrb.Horizontal(
            rrb.Spatial2DView(name="Map", origin="/", contents=["/map/**"]),
            rrb.Vertical(
                rrb.Spatial2DView(name="Occupancy grid", origin="/",
                                  contents=[f"/{GRID}", f"/{CONFIRMED}", f"/{pose_path('truth')}",
                                            f"/{trail_path('truth')}", "/map/sonar/**"]),
                rrb.TimeSeriesView(name="Energy", origin=f"/{ENERGY}"),
                rrb.TimeSeriesView(name="Iterations", origin=f"/{ITERATIONS}"),
                rrb.Tabs(
                    rrb.TimeSeriesView(name="Exploration", origin="/plots/exploration"),
                    rrb.TimeSeriesView(name="Map size", origin="/plots/map_size"),
                    rrb.TimeSeriesView(name="Localization", origin="/plots/belief"),
                    rrb.TextLogView(name="Events", origin=f"/{EVENTS}"),
                ),
                row_shares=[3, 2, 2, 2],
            ),
            column_shares=[3, 2],
        ),
        rrb.TimePanel(timeline=SIM_TIME),
        collapse_panels=False,
    )


def open_recording(rrd_path: Path, params: RecorderParams, *, viewer: bool = False, viewer_port: int = 9876,
                   recording_id: str | None = None) -> rr.RecordingStream:
    """A stream to ``rrd_path`` (parents created) and, with ``viewer``, to a spawned viewer as well.

    A viewer that cannot be started is logged and left out; the file is written either way.
    """
    rrd_path.parent.mkdir(parents=True, exist_ok=True)
    batching = rr.ChunkBatcherConfig(flush_tick=params.viewer_flush_period_s if viewer else params.flush_period_s,
                                     flush_num_bytes=params.flush_bytes)
    rec = rr.RecordingStream(APPLICATION_ID, recording_id=recording_id, batcher_config=batching)
    sinks: list = [rr.FileSink(str(rrd_path))]
    if viewer:
        # The CLI installed with this SDK first (same version), else whichever is on PATH.
        exe = shutil.which("rerun", path=str(Path(sys.executable).parent)) or shutil.which("rerun") or "rerun"
        try:
            rr.spawn(port=viewer_port, connect=False, executable_path=exe, recording=rec)
            # A viewer that could not open a window (no display) exits; then nobody listens.
            with socket.create_connection(("127.0.0.1", viewer_port), timeout=1.0):
                pass
            sinks.append(rr.GrpcSink(f"rerun+http://127.0.0.1:{viewer_port}/proxy"))
        except Exception as e:  # no display, no binary: the file still gets everything
            log.warning("recorder: no viewer on port %d (%s); writing %s only", viewer_port, e, rrd_path)
    rec.set_sinks(*sinks)
    rec.send_blueprint(blueprint(), make_active=True, make_default=True)
    return rec


def close_recording(rec: rr.RecordingStream) -> None:
    """Flush and close every sink, so the file ends with its footer (and stays valid)."""
    try:
        rec.flush(timeout_sec=FLUSH_TIMEOUT_S)
    except Exception:
        log.exception("recorder: flushing the recording failed")
    rec.disconnect()


class Recorder:
    """Turns bus messages into Rerun logs; every callback runs in the node's event loop."""

    def __init__(self, node: Node, rec: rr.RecordingStream, params: RecorderParams, *,
                 stop: threading.Event, max_sim_time_s: float | None = None) -> None:
        self.node = node
        self.rec = rec
        self.params = params
        self.state = RecorderState(params=params)
        self.stop = stop
        self.max_sim_time_s = max_sim_time_s
        self.complete = False
        self._grid_thread: threading.Thread | None = None
        self._grid_in_flight = False  # a query's thread runs, or its result waits in the event queue
        self._grid_pending: float | None = None  # stamp of a request made while another was in flight
        self._stamp: float | None = None  # simulated time of the message being handled
        self._map_dirty: float | None = None  # when they last changed without being logged (map_period_s)
        self._arrows: dict[str, list[tuple[float, np.ndarray, np.ndarray]]] = {}  # pose source -> arrows to send
        self._labelled: dict[str, np.ndarray] = {}  # places entity -> the ids its labels were last logged for
        # Every key is present from the start: health copies this dict from another thread.
        node.detail.update({"handled": 0, "map_updates": 0, "map_version": -1, "grid_queries": 0, "grid_failures": 0,
                            "grids_logged": 0, "grid_skipped": 0, "places": 0, "predicted": 0,
                            "links_traversed": 0, "links_inferred": 0, "sonar_scans": 0})
        self._log_static()

    # -- helpers ------------------------------------------------------------------------------------
    def _log_static(self) -> None:
        rec = self.rec
        # 2-D views draw +y downwards; this flip shows the map with +y up. Data below stay in metres.
        rec.log(MAP, rr.Transform3D(scale=[1.0, -1.0, 1.0]), static=True)
        rec.log(ENERGY, rr.SeriesLines(names="energy (Eq. 7)", colors=[STYLE.confirmed_color]), static=True)
        rec.log(ITERATIONS, rr.SeriesLines(names="iterations per cycle", colors=[STYLE.pose_color("compass")]),
                static=True)
        rec.log(MAP_PLACES, rr.SeriesLines(names="places", colors=[STYLE.confirmed_color]), static=True)
        rec.log(MAP_LINKS, rr.SeriesLines(names="links", colors=[STYLE.traversed_color]), static=True)
        rec.log(EXPLORED_CONFIRMED, rr.SeriesLines(names="confirmed", colors=[STYLE.confirmed_color]), static=True)
        rec.log(EXPLORED_PREDICTED, rr.SeriesLines(names="predicted", colors=[STYLE.predicted_color]), static=True)
        rec.log(BELIEF_PROBABILITY, rr.SeriesLines(names="P(best place)", colors=[STYLE.belief_color]), static=True)
        # How each entity is drawn, once for the whole recording: the logs over time carry only the data.
        # Each style component costs the SDK as much to convert as the data (a pose's arrow: 360 us whole,
        # 140 us without its colour, radius and draw order).
        for path, style in _styles().items():
            rec.log(path, style, static=True)

    def _at(self, stamp: float) -> bool:
        """Set the simulated time; False (and stop) for a message beyond --max-sim-time."""
        if self.max_sim_time_s is not None and stamp > self.max_sim_time_s:
            if not self.stop.is_set():
                log.info("recorder: simulated time %.3f s is beyond %.3f s: stopping", stamp, self.max_sim_time_s)
                self.stop.set()
            return False
        if self._map_dirty is not None and self.state.map_due(stamp):
            self.flush_map()
        self._stamp = stamp
        self.rec.set_time(SIM_TIME, duration=stamp)
        return True

    def flush_map(self) -> None:
        """Log the places and links changed since they were last logged, at the time of the change."""
        if self._map_dirty is None:
            return
        self.rec.set_time(SIM_TIME, duration=self._map_dirty)
        self._log_map()
        if self._stamp is not None:
            self.rec.set_time(SIM_TIME, duration=self._stamp)

    def _map_changed(self) -> None:
        """The places or links changed by an event other than a map update: log them now, or at the
        latest change of this ``map_period_s`` (logging the whole map on every inferred link and predicted
        place cost more than the map updates themselves)."""
        if self.state.map_due(self._stamp):
            self._log_map()
        else:
            self._map_dirty = self._stamp
            self._count()

    def _event(self, text: str, level: rr.TextLogLevel = rr.TextLogLevel.INFO) -> None:
        self.rec.log(EVENTS, rr.TextLog(text, level=level))

    def _log_map(self) -> None:
        """The places and the links, whole, at the current time."""
        st, rec = self.state, self.rec
        places = st.places()
        for path, ids, xy in ((CONFIRMED, places.confirmed_ids, places.confirmed_xy),
                              (PREDICTED, places.predicted_ids, places.predicted_xy)):
            # the ids as labels only when they changed: the viewer keeps the latest labels of the entity
            labels = None if np.array_equal(ids, self._labelled.get(path)) else ids.astype(str)
            rec.log(path, rr.Points2D.from_fields(positions=xy, labels=labels))
            self._labelled[path] = ids
        links = st.links(places)
        rec.log(TRAVERSED, rr.LineStrips2D.from_fields(strips=links.traversed))
        rec.log(INFERRED, rr.LineStrips2D.from_fields(strips=links.inferred))
        st.map_logged = self._map_dirty if self._map_dirty is not None else self._stamp
        self._map_dirty = None
        self._count()

    def _count(self) -> None:
        st, d = self.state, self.node.detail
        d["places"], d["predicted"] = len(st.initial), len(st.predicted)  # the relaxed ones are among the initial
        d["links_traversed"], d["links_inferred"] = len(st.traversed), len(st.inferred)

    # -- places and links ---------------------------------------------------------------------------
    def on_place_confirmed(self, msg: PlaceConfirmed) -> None:
        if self._at(msg.stamp):
            self.state.place_confirmed(msg)
            self._map_changed()
            self._event(f"place {msg.place_id} confirmed at ({msg.x_m:.2f}, {msg.y_m:.2f})")

    def on_place_predicted(self, msg: PlacePredicted) -> None:
        if self._at(msg.stamp):
            self.state.place_predicted(msg)
            self._map_changed()

    def on_place_deleted(self, msg: PlaceDeleted) -> None:
        if self._at(msg.stamp):
            self.state.place_deleted(msg)
            self._map_changed()
            self._event(f"place {msg.place_id} deleted: {msg.reason}", rr.TextLogLevel.WARN)

    def on_link_measured(self, msg: LinkMeasured) -> None:
        if self._at(msg.stamp):
            self.state.link_measured(msg)
            self._map_changed()
            self._event(f"link {msg.from_id}-{msg.to_id} measured: d={msg.d_m:.2f} m, "
                        f"theta={np.degrees(msg.theta_rad):.1f} deg, {msg.traversals} traversal(s)")

    def on_link_inferred(self, msg: LinkInferred) -> None:
        if self._at(msg.stamp):
            self.state.link_inferred(msg)
            self._map_changed()

    def on_link_deleted(self, msg: LinkDeleted) -> None:
        if self._at(msg.stamp):
            self.state.link_deleted(msg)
            self._map_changed()
            self._event(f"link {msg.from_id}-{msg.to_id} deleted: {msg.reason}", rr.TextLogLevel.WARN)

    def on_map_update(self, msg: MapUpdate) -> None:
        if not self._at(msg.stamp):
            return
        self.flush_map()
        self.rec.set_time(MAP_VERSION, sequence=msg.version)
        self.state.map_update(msg)
        self._log_map()
        rec = self.rec
        rec.log(ENERGY, rr.Scalars(msg.energy))
        rec.log(ITERATIONS, rr.Scalars(float(msg.iterations)))
        rec.log(MAP_PLACES, rr.Scalars(float(msg.places)))
        rec.log(MAP_LINKS, rr.Scalars(float(msg.links)))
        self.node.detail["map_updates"] += 1
        self.node.detail["map_version"] = self.state.version
        if self.state.grid_due(msg.version, msg.stamp):
            self._ask_grid(msg.stamp)

    # -- robot --------------------------------------------------------------------------------------
    def _pose(self, source: str, stamp: float) -> None:
        st, rec = self.state, self.rec
        if st.live_due(source, stamp):
            origin, vector = st.arrow(source)
            arrows = self._arrows.setdefault(source, [])
            arrows.append((stamp, origin, vector))
            if len(arrows) >= ARROW_BATCH:
                self._send_arrows(source)
        if st.trail_due(source, stamp):
            rec.log(trail_path(source), rr.LineStrips2D.from_fields(strips=[st.trail(source)]))

    def _send_arrows(self, source: str) -> None:
        """The arrows of ``source`` kept since the last send, as one column per component."""
        arrows = self._arrows.pop(source, [])
        if arrows:
            stamps, origins, vectors = zip(*arrows)
            self.rec.send_columns(pose_path(source), indexes=[rr.TimeColumn(SIM_TIME, duration=stamps)],
                                  columns=rr.Arrows2D.columns(origins=np.array(origins), vectors=np.array(vectors)))

    def flush_poses(self) -> None:
        """Send every arrow still kept (at the end of the recording)."""
        for source in list(self._arrows):
            self._send_arrows(source)

    def on_truth(self, msg: TruthPose) -> None:
        if self._at(msg.stamp):
            self.state.pose("truth", msg.pose)
            self._pose("truth", msg.stamp)

    def on_dead_reckoning(self, msg: DeadReckonedPose) -> None:
        if self._at(msg.stamp):
            for source, pose in (("compass", msg.compass), ("raw", msg.raw)):
                self.state.pose(source, pose)
                self._pose(source, msg.stamp)

    def on_sonar(self, msg: SonarScan) -> None:
        if not self._at(msg.stamp):
            return
        self.node.detail["sonar_scans"] += 1
        if not self.state.live_due("sonar", msg.stamp):
            return
        rays = self.state.sonar_rays(msg)
        if rays is None:
            return
        colors = np.where(rays.echo[:, None], STYLE.echo_color, STYLE.no_echo_color).astype(np.uint8)
        self.rec.log(SONAR_RAYS, rr.LineStrips2D.from_fields(strips=rays.segments, colors=colors))
        self.rec.log(SONAR_ECHOES, rr.Points2D.from_fields(positions=rays.ends[rays.echo]))

    def on_belief(self, msg: LocalizationBelief) -> None:
        if not self._at(msg.stamp) or not self.state.live_due("belief", msg.stamp):
            return
        view = self.state.belief(msg)
        rec = self.rec
        rec.log(BELIEF_PROBABILITY, rr.Scalars(view.probability))
        if view.estimate_xy is None:
            rec.log(BELIEF_ESTIMATE, rr.Ellipses2D.from_fields(centers=np.zeros((0, 2)), half_sizes=np.zeros((0, 2)),
                                                               labels=[]))
        else:
            rec.log(BELIEF_ESTIMATE, rr.Ellipses2D.from_fields(
                centers=[view.estimate_xy], half_sizes=[[max(view.sigma_m, 0.02)] * 2],
                labels=[f"{view.place_id} p={view.probability:.2f}"]))
        radii = [_ui(STYLE.belief_radius_pt * float(np.sqrt(p))) for p in view.hypothesis_p]
        rec.log(BELIEF_HYPOTHESES, rr.Points2D.from_fields(positions=view.hypothesis_xy, radii=radii,
                                                           labels=[f"p={p:.2f}" for p in view.hypothesis_p]))

    def on_status(self, msg: ExplorationStatus) -> None:
        if not self._at(msg.stamp):
            return
        self.rec.log(EXPLORED_CONFIRMED, rr.Scalars(float(msg.confirmed)))
        self.rec.log(EXPLORED_PREDICTED, rr.Scalars(float(msg.predicted)))
        if msg.complete and not self.complete:
            self._event(f"exploration complete: {msg.confirmed} places confirmed")
        self.complete = msg.complete

    # -- the occupancy grid -------------------------------------------------------------------------
    def _ask_grid(self, stamp: float) -> None:
        """Ask map/grid in a worker thread; the reply is logged from the event loop."""
        if self._grid_in_flight:
            # One query at a time; the latest request waits for the one in flight to end.
            if self._grid_pending is not None:
                self.node.detail["grid_skipped"] += 1
            self._grid_pending = stamp
            return
        self.node.detail["grid_queries"] += 1
        p = self.params
        params = {"resolution": f"{p.grid_resolution_m:g}"} if p.grid_resolution_m > 0 else None
        key = topics.map_grid(self.node.robot)
        session, call_soon = self.node.session, self.node.call_soon

        def ask() -> None:
            try:
                grid = query(session, key, params, type_=OccupancyGrid, timeout_s=p.grid_timeout_s)
            except Exception as e:  # no relaxer, an error reply, a closing session: counted, not fatal
                call_soon(self._on_grid_failed, e)
                return
            call_soon(self._on_grid, grid, stamp)

        self._grid_in_flight = True
        self._grid_thread = threading.Thread(target=ask, name="recorder-grid", daemon=True)
        self._grid_thread.start()

    def _grid_done(self) -> None:
        """The query in flight ended: ask again for a request that came meanwhile."""
        self._grid_in_flight = False
        if self._grid_pending is not None and not self.stop.is_set():
            stamp, self._grid_pending = self._grid_pending, None
            self._ask_grid(stamp)

    def _on_grid_failed(self, error: Exception) -> None:
        self.node.detail["grid_failures"] += 1
        log.debug("recorder: no occupancy grid: %s", error)
        self._grid_done()

    def _on_grid(self, grid: OccupancyGrid, stamp: float) -> None:
        try:
            image = grid_image(grid)
        except ValueError as e:
            self._on_grid_failed(e)
            return
        self._grid_done()
        if self._at(stamp):
            self.rec.set_time(MAP_VERSION, sequence=grid.version)
            # Row r, column c of the image covers x = ox + c res, y = oy + r res (the grid's own layout).
            self.rec.log(GRID, rr.Transform3D(translation=[*image.origin_xy, 0.0],
                                              scale=[image.resolution_m, image.resolution_m, 1.0]))
            self.rec.log(GRID, rr.Image(image.grey, color_model="L", draw_order=-10.0))
            self.rec.set_time(MAP_VERSION, sequence=max(self.state.version, grid.version))
            self.node.detail["grids_logged"] += 1

    def close(self, timeout_s: float = 0.5) -> None:
        """Give a grid query in flight a moment to end (it ends by its own timeout anyway)."""
        if self._grid_thread is not None:
            self._grid_thread.join(timeout_s)


def subscribe_all(node: Node, recorder: Recorder, robot: str) -> None:
    """Every topic the recorder draws, to its callback; ``handled`` in health counts the messages done."""
    table = (
        (topics.truth_pose(robot), TruthPose, recorder.on_truth),
        (topics.dr_pose(robot), DeadReckonedPose, recorder.on_dead_reckoning),
        (topics.sonar(robot), SonarScan, recorder.on_sonar),
        (topics.localization(robot), LocalizationBelief, recorder.on_belief),
        (topics.places_confirmed(robot), PlaceConfirmed, recorder.on_place_confirmed),
        (topics.places_predicted(robot), PlacePredicted, recorder.on_place_predicted),
        (topics.places_deleted(robot), PlaceDeleted, recorder.on_place_deleted),
        (topics.links_measured(robot), LinkMeasured, recorder.on_link_measured),
        (topics.links_inferred(robot), LinkInferred, recorder.on_link_inferred),
        (topics.links_deleted(robot), LinkDeleted, recorder.on_link_deleted),
        (topics.map_update(robot), MapUpdate, recorder.on_map_update),
        (topics.exploration_status(robot), ExplorationStatus, recorder.on_status),
    )
    for key, type_, callback in table:
        node.subscribe(key, type_, _counted(node, callback))


def _counted(node: Node, callback: Callable[[Any], None]) -> Callable[[Any], None]:
    def on_message(msg: Any) -> None:
        try:
            callback(msg)
        finally:
            node.detail["handled"] += 1

    on_message.__name__ = callback.__name__
    return on_message


def _drain(node: Node, timeout_s: float) -> int:
    """Handle the messages that arrived before the stop (for at most ``timeout_s``); how many."""
    deadline = time.monotonic() + timeout_s
    n = 0
    while time.monotonic() < deadline and node.spin_once(0.0):
        n += 1
    return n


def run(session: zenoh.Session, params: RecorderParams, *, rrd_path: Path, robot: str = topics.DEFAULT_ROBOT,
        stop: threading.Event | None = None, viewer: bool = False, viewer_port: int = 9876,
        recording_id: str | None = None, duration_s: float | None = None,
        max_sim_time_s: float | None = None) -> None:
    """Record until ``stop`` is set (or ``duration_s`` wall seconds, or ``max_sim_time_s``).

    The recording is flushed and closed on every way out, exceptions included, so that the file
    always ends with its footer.
    """
    stop = stop if stop is not None else threading.Event()
    deadline = None if duration_s is None else time.monotonic() + duration_s

    def tick() -> None:
        if deadline is not None and time.monotonic() >= deadline:
            log.info("recorder: --duration-s reached: stopping")
            stop.set()

    rec = open_recording(rrd_path, params, viewer=viewer, viewer_port=viewer_port, recording_id=recording_id)
    recorder = None
    try:
        with Node(session, "recorder", robot=robot) as node:
            recorder = Recorder(node, rec, params, stop=stop, max_sim_time_s=max_sim_time_s)
            subscribe_all(node, recorder, robot)
            log.info("recorder: writing %s", rrd_path)
            node.spin(stop, tick=tick, period_s=0.1)
            drained = _drain(node, DRAIN_S)
            if drained:
                log.info("recorder: %d queued messages recorded after the stop", drained)
    finally:
        if recorder is not None:
            try:
                recorder.flush_map()
                recorder.flush_poses()
            except Exception:
                log.exception("recorder: the last change of the map or the last poses could not be logged")
        close_recording(rec)
        if recorder is not None:
            recorder.close()
        log.info("recorder: %s closed", rrd_path)
