"""The recorder's pure core: map coordinates, links, trails, sonar rays, belief and the grid image."""

from __future__ import annotations

import math

import numpy as np
import pytest

from messages.types import (
    Hypothesis,
    LinkDeleted,
    LinkInferred,
    LinkMeasured,
    LocalizationBelief,
    MapUpdate,
    NoiseParams,
    OccupancyGrid,
    PlaceConfirmed,
    PlaceDeleted,
    PlacePosition,
    PlacePredicted,
    Pose2,
    SonarScan,
)
from services.recorder.core import RecorderParams, RecorderState, grid_image

NOISE = NoiseParams(s_dd=0.01, s_aa=0.001, s_da=0.0)


def confirmed(pid: int, x: float, y: float) -> PlaceConfirmed:
    return PlaceConfirmed(stamp=1.0, seq=pid, place_id=pid, x_m=x, y_m=y)


def update(version: int, moved: dict[int, tuple[float, float]], *, full: bool = False) -> MapUpdate:
    return MapUpdate(stamp=float(version), seq=version, version=version,
                     changed=[PlacePosition(place_id=p, x_m=x, y_m=y) for p, (x, y) in moved.items()],
                     full=full, places=len(moved), links=0, energy=1.5, iterations=3, method="sweep", noise=NOISE)


def measured(a: int, b: int) -> LinkMeasured:
    return LinkMeasured(stamp=2.0, seq=0, from_id=a, to_id=b, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)


def inferred(a: int, b: int) -> LinkInferred:
    return LinkInferred(stamp=2.0, seq=0, from_id=a, to_id=b, d_m=1.0)


def state_with_places(**params) -> RecorderState:
    st = RecorderState(params=RecorderParams(**params))
    for pid, (x, y) in {0: (0.0, 0.0), 1: (2.0, 0.0), 2: (2.0, 2.0)}.items():
        st.place_confirmed(confirmed(pid, x, y))
    return st


def test_confirmed_coordinates_until_relaxed_ones_replace_them():
    st = state_with_places()
    v = st.places()
    assert v.confirmed_ids.tolist() == [0, 1, 2]
    np.testing.assert_allclose(v.confirmed_xy, [[0, 0], [2, 0], [2, 2]])
    st.map_update(update(1, {1: (2.1, -0.1)}))
    v = st.places()
    np.testing.assert_allclose(v.confirmed_xy, [[0, 0], [2.1, -0.1], [2, 2]])
    # a later update of another place leaves the relaxed coordinates of place 1 in place
    st.map_update(update(2, {2: (1.9, 2.05)}))
    np.testing.assert_allclose(st.places().confirmed_xy, [[0, 0], [2.1, -0.1], [1.9, 2.05]])
    assert st.version == 2
    # links follow the relaxed coordinates
    st.link_measured(measured(1, 2))
    np.testing.assert_allclose(st.links().traversed, [[[2.1, -0.1], [1.9, 2.05]]])


def test_map_update_of_an_unseen_place_adds_it_as_confirmed():
    st = RecorderState()
    st.map_update(update(1, {7: (3.0, 4.0)}, full=True))
    v = st.places()
    assert v.confirmed_ids.tolist() == [7]
    np.testing.assert_allclose(v.confirmed_xy, [[3.0, 4.0]])


def test_deleted_places_disappear_with_their_links():
    st = state_with_places()
    st.place_predicted(PlacePredicted(stamp=1.0, seq=0, place_id=5, x_m=4.0, y_m=0.0, parent_id=1))
    st.link_measured(measured(0, 1))
    st.link_measured(measured(1, 2))
    st.link_inferred(inferred(1, 5))
    st.map_update(update(1, {1: (2.0, 0.1)}))
    st.place_deleted(PlaceDeleted(stamp=3.0, seq=0, place_id=1, reason="test"))
    v = st.places()
    assert v.confirmed_ids.tolist() == [0, 2]
    assert 1 not in st.relaxed and 1 not in st.initial
    links = st.links()
    assert links.traversed_ids.shape == (0, 2) and links.inferred_ids.shape == (0, 2)
    st.place_deleted(PlaceDeleted(stamp=3.0, seq=1, place_id=5, reason="unreachable"))
    assert st.places().predicted_ids.tolist() == []


def test_link_kinds_are_kept_apart():
    st = state_with_places()
    st.link_measured(measured(0, 1))
    st.link_inferred(inferred(1, 2))
    st.link_inferred(inferred(0, 2))
    links = st.links()
    assert links.traversed_ids.tolist() == [[0, 1]]
    assert links.inferred_ids.tolist() == [[0, 2], [1, 2]]
    np.testing.assert_allclose(links.traversed, [[[0, 0], [2, 0]]])
    # traversing an inferred link (in the other direction) makes it a traversed one
    st.link_measured(measured(2, 1))
    links = st.links()
    assert links.traversed_ids.tolist() == [[0, 1], [1, 2]]
    assert links.inferred_ids.tolist() == [[0, 2]]
    # an inferred link never hides a traversed one
    st.link_inferred(inferred(1, 0))
    assert st.links().inferred_ids.tolist() == [[0, 2]]
    st.link_deleted(LinkDeleted(stamp=4.0, seq=0, from_id=2, to_id=0, reason="low confidence"))
    st.link_deleted(LinkDeleted(stamp=4.0, seq=1, from_id=1, to_id=0, reason="low confidence"))
    links = st.links()
    assert links.traversed_ids.tolist() == [[1, 2]] and links.inferred_ids.shape == (0, 2)


def test_a_deletion_older_than_the_links_latest_measurement_leaves_it_drawn():
    st = state_with_places()
    st.link_measured(measured(0, 1))  # at 2 s
    st.link_deleted(LinkDeleted(stamp=1.5, seq=0, from_id=1, to_id=0, reason="low confidence"))
    assert st.links().traversed_ids.tolist() == [[0, 1]]
    st.link_deleted(LinkDeleted(stamp=2.5, seq=1, from_id=1, to_id=0, reason="low confidence"))
    assert st.links().traversed_ids.tolist() == []


def test_links_wait_for_their_places():
    st = RecorderState()
    st.link_measured(measured(3, 4))
    assert st.links().traversed.shape == (0, 2, 2)
    st.place_confirmed(confirmed(3, 0.0, 0.0))
    st.place_confirmed(confirmed(4, 1.0, 1.0))
    np.testing.assert_allclose(st.links().traversed, [[[0, 0], [1, 1]]])


def test_predicted_places_follow_their_parent_and_give_way_to_confirmation():
    st = state_with_places()
    st.place_predicted(PlacePredicted(stamp=1.0, seq=0, place_id=9, x_m=4.0, y_m=0.0, parent_id=1))
    st.place_predicted(PlacePredicted(stamp=1.0, seq=1, place_id=2, x_m=9.0, y_m=9.0, parent_id=1))  # confirmed
    v = st.places()
    assert v.predicted_ids.tolist() == [9]
    np.testing.assert_allclose(v.predicted_xy, [[4.0, 0.0]])
    st.map_update(update(1, {1: (2.5, 0.5)}))
    np.testing.assert_allclose(st.places().predicted_xy, [[4.5, 0.5]])
    st.place_confirmed(confirmed(9, 4.4, 0.4))
    v = st.places()
    assert v.predicted_ids.tolist() == [] and v.confirmed_ids.tolist() == [0, 1, 2, 9]


def test_trails_are_bounded_and_spaced():
    st = RecorderState(params=RecorderParams(trail_points=5, trail_spacing_m=0.25))
    for i in range(100):
        st.pose("compass", Pose2(x_m=0.125 * i, y_m=0.0, heading_rad=0.0))
    trail = st.trail("compass")
    assert trail.shape == (5, 2)
    # one point every 0.25 m (every second pose), the newest last
    np.testing.assert_allclose(trail[:, 0], [11.25, 11.5, 11.75, 12.0, 12.25])
    assert st.trail("raw").shape == (0, 2)
    with pytest.raises(ValueError):
        st.pose("gps", Pose2(x_m=0.0, y_m=0.0, heading_rad=0.0))


def test_rate_limits_on_simulated_time():
    st = RecorderState(params=RecorderParams(trail_period_s=1.0, live_period_s=0.1))
    assert not st.trail_due("truth", 0.0)  # no trail yet
    st.pose("truth", Pose2(x_m=0.0, y_m=0.0, heading_rad=0.0))
    assert st.trail_due("truth", 0.0)
    assert not st.trail_due("truth", 0.5)
    assert st.trail_due("truth", 1.0)
    assert st.live_due("sonar", 0.0) and not st.live_due("sonar", 0.05) and st.live_due("sonar", 0.1)
    assert st.live_due("sonar", 0.0)  # the clock went back: a new run


def test_sonar_rays_in_the_world_frame():
    st = RecorderState(params=RecorderParams(sonar_pose="truth"))
    scan = SonarScan(stamp=1.0, seq=0, angles_rad=[0.0, math.pi / 2, math.pi], ranges_m=[1.0, 2.0, 5.0],
                     beam_width_rad=0.4, min_range_m=0.1, max_range_m=5.0)
    assert st.sonar_rays(scan) is None  # no pose yet
    st.pose("compass", Pose2(x_m=9.0, y_m=9.0, heading_rad=0.0))  # not the pose the rays use
    st.pose("truth", Pose2(x_m=1.0, y_m=2.0, heading_rad=math.pi / 2))
    rays = st.sonar_rays(scan)
    np.testing.assert_allclose(rays.origin, [1.0, 2.0])
    # heading +y: the forward ray goes up, the left one to -x, the backward one down (no echo)
    np.testing.assert_allclose(rays.ends, [[1.0, 3.0], [-1.0, 2.0], [1.0, -3.0]], atol=1e-12)
    assert rays.echo.tolist() == [True, True, False]
    segs = rays.segments
    assert segs.shape == (3, 2, 2)
    np.testing.assert_allclose(segs[:, 0], [[1.0, 2.0]] * 3)
    bad = SonarScan(stamp=1.0, seq=1, angles_rad=[0.0], ranges_m=[1.0, 2.0], beam_width_rad=0.4,
                    min_range_m=0.1, max_range_m=5.0)
    with pytest.raises(ValueError):
        st.sonar_rays(bad)


def test_arrow_points_along_the_heading():
    st = RecorderState(params=RecorderParams(arrow_length_m=0.5))
    assert st.arrow("raw") is None
    st.pose("raw", Pose2(x_m=1.0, y_m=1.0, heading_rad=math.pi))
    origin, vector = st.arrow("raw")
    np.testing.assert_allclose(origin, [1.0, 1.0])
    np.testing.assert_allclose(vector, [-0.5, 0.0], atol=1e-12)


def test_belief_on_the_map():
    st = state_with_places()
    st.map_update(update(1, {1: (2.0, 0.5)}))
    hyps = [Hypothesis(place_id=p, probability=q) for p, q in ((1, 0.8), (-1, 0.1), (2, 0.05), (42, 0.05))]
    msg = LocalizationBelief(stamp=5.0, seq=0, place_id=1, probability=0.8, offset_x_m=0.1, offset_y_m=-0.2,
                             offset_var_m2=0.04, hypotheses=hyps)
    view = st.belief(msg)
    np.testing.assert_allclose(view.estimate_xy, [2.1, 0.3])
    assert view.sigma_m == pytest.approx(0.2)
    assert view.hypothesis_ids.tolist() == [1, 2]  # "no place" and unknown places are not drawn
    np.testing.assert_allclose(view.hypothesis_xy, [[2.0, 0.5], [2.0, 2.0]])
    np.testing.assert_allclose(view.hypothesis_p, [0.8, 0.05])
    between = st.belief(LocalizationBelief(stamp=6.0, seq=1, place_id=-1, probability=0.3, offset_x_m=0.0,
                                           offset_y_m=0.0, offset_var_m2=1.0))
    assert between.estimate_xy is None and between.sigma_m is None and between.hypothesis_xy.shape == (0, 2)


def test_grid_requests_every_n_versions_or_period():
    st = RecorderState(params=RecorderParams(grid_every_versions=3, grid_period_s=10.0))
    asked = [v for v in range(1, 11) if st.grid_due(v, stamp=0.1 * v)]
    assert asked == [1, 4, 7, 10]
    assert st.grid_due(11, stamp=20.0)  # the period passed
    assert not st.grid_due(12, stamp=20.5)
    assert st.grid_due(1, stamp=0.0)  # a new run


def test_grid_image_grey_levels_and_layout():
    cells = bytes([0, 100, 255, 40, 0, 0])  # 3 wide, 2 high, row 0 first
    grid = OccupancyGrid(resolution_m=0.5, origin_x_m=-1.0, origin_y_m=2.0, width=3, height=2, cells=cells,
                         version=4)
    image = grid_image(grid)
    assert image.grey.dtype == np.uint8 and image.grey.shape == (2, 3)
    assert image.grey.tolist() == [[255, 0, 128], [153, 255, 255]]
    assert image.origin_xy == (-1.0, 2.0) and image.resolution_m == 0.5 and image.version == 4
    with pytest.raises(ValueError):
        grid_image(OccupancyGrid(resolution_m=0.5, origin_x_m=0.0, origin_y_m=0.0, width=3, height=3,
                                 cells=cells, version=0))


def test_params_are_checked():
    with pytest.raises(ValueError):
        RecorderParams(sonar_pose="lidar")
    with pytest.raises(ValueError):
        RecorderParams(trail_points=1)
    with pytest.raises(ValueError):
        RecorderParams(grid_timeout_s=0.0)
    with pytest.raises(ValueError):
        RecorderParams(flush_period_s=0.0)
    with pytest.raises(ValueError):
        RecorderParams(viewer_flush_period_s=-1.0)
    with pytest.raises(ValueError):
        RecorderParams(flush_bytes=0)
    assert RecorderParams().grid_every_versions == 10
