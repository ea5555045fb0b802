"""The run monitor over a real session: which measured links count as lost."""

from __future__ import annotations

import zenoh

from messages import topics
from messages.codec import codec
from messages.types import LinkDeleted, LinkMeasured
from services.launch.monitor import RunMonitor
from services.runtime import loopback_config
from tests.conftest import wait_until

ROBOT = "robot0"


def test_a_link_measured_again_after_its_deletion_counts_as_lost_until_the_map_holds_it(hub):
    session, endpoint = hub
    monitor = RunMonitor(session, ROBOT)
    client = zenoh.open(loopback_config(connect=[endpoint]))
    try:
        def measured(stamp: float) -> None:
            client.put(topics.links_measured(ROBOT), codec(LinkMeasured).encode(LinkMeasured(
                stamp=stamp, seq=0, from_id=1, to_id=0, d_m=1.0, theta_rad=0.0, steps=10, mean_step_m=0.1)))

        def deleted(stamp: float, pair: tuple[int, int] = (0, 1)) -> None:
            client.put(topics.links_deleted(ROBOT), codec(LinkDeleted).encode(LinkDeleted(
                stamp=stamp, seq=0, from_id=pair[0], to_id=pair[1], reason="confidence")))

        measured(10.0)
        assert wait_until(lambda: monitor.links_lost(set()) == {(0, 1)}, 10)
        deleted(30.0)
        assert wait_until(lambda: monitor.links_lost(set()) == set(), 10)  # deleted on purpose
        measured(40.0)
        assert wait_until(lambda: monitor.links_lost(set()) == {(0, 1)}, 10)  # alive again: the map must hold it
        deleted(30.0)  # the first deletion heard again (a publisher's history)
        deleted(50.0, (2, 3))  # a later deletion on the same key: once it is heard, so is the one before
        assert wait_until(lambda: (2, 3) in monitor.deleted_links, 10)
        assert monitor.links_lost(set()) == {(0, 1)}
        assert monitor.links_lost({(0, 1)}) == set()
    finally:
        client.close()
        monitor.close()
