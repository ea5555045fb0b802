"""The dead-reckoned poses the recognizer keeps to pair with scans and place confirmations."""

from __future__ import annotations

import bisect
import itertools
from collections import deque
from collections.abc import Iterable

from messages.types import DeadReckonedPose

POSE_HISTORY = 512  # poses kept by default: scans come at least once a simulated second, ten ticks


class PoseHistory:
    """The latest ``maxlen`` dead-reckoned poses, one a stamp, in stamp order.

    The recognizer's node and the in-process loop keep them by this one rule, so that both hand the
    recognizer the same poses: a pose of the newest stamp replaces it (the later of two of one tick),
    an older stamp is dropped (dead reckoning repeats only its first pose).

    >>> from messages.types import Pose2
    >>> h = PoseHistory(3)
    >>> for stamp, x in ((0.0, 0.0), (0.1, 1.0), (0.1, 2.0), (0.0, 9.0), (0.2, 3.0), (0.3, 4.0)):
    ...     at = Pose2(x_m=x, y_m=0.0, heading_rad=0.0)
    ...     kept = h.add(DeadReckonedPose(stamp=stamp, seq=0, compass=at, raw=at, steps=0, path_length_m=0.0))
    ...     if not kept:
    ...         print(f"dropped {stamp}")
    dropped 0.0
    >>> [(p.stamp, p.compass.x_m) for p in h.poses]
    [(0.1, 2.0), (0.2, 3.0), (0.3, 4.0)]
    >>> [p.stamp for p in h.between(0.1, 0.3)], h.at(0.25).stamp, h.at(0.05)
    ([0.2], 0.2, None)
    """

    def __init__(self, maxlen: int, poses: Iterable[DeadReckonedPose] = ()) -> None:
        self._poses: deque[DeadReckonedPose] = deque(maxlen=maxlen)
        self._stamps: deque[float] = deque(maxlen=maxlen)
        for pose in poses:
            self.add(pose)

    def add(self, pose: DeadReckonedPose) -> bool:
        """Keep ``pose``; False when it is older than the newest kept, and dropped."""
        if self._stamps and pose.stamp <= self._stamps[-1]:
            if pose.stamp < self._stamps[-1]:
                return False
            self._poses[-1] = pose
            return True
        self._stamps.append(pose.stamp)
        self._poses.append(pose)
        return True

    def __len__(self) -> int:
        return len(self._poses)

    @property
    def poses(self) -> list[DeadReckonedPose]:
        return list(self._poses)

    @property
    def first(self) -> DeadReckonedPose | None:
        return self._poses[0] if self._poses else None

    def reaches(self, stamp: float) -> bool:
        """Whether a pose of ``stamp`` or later is kept."""
        return bool(self._stamps) and self._stamps[-1] >= stamp - 1e-9

    def at(self, stamp: float) -> DeadReckonedPose | None:
        """The pose of the same stamp, else the latest before it; None when all kept are later."""
        i = bisect.bisect_right(self._stamps, stamp + 1e-9)
        return self._poses[i - 1] if i > 0 else None

    def between(self, after: float | None, before: float) -> list[DeadReckonedPose]:
        """The poses stamped strictly between ``after`` and ``before`` (none when ``after`` is None)."""
        if after is None:
            return []
        i = bisect.bisect_right(self._stamps, after + 1e-9)
        j = bisect.bisect_left(self._stamps, before - 1e-9)
        return list(itertools.islice(self._poses, i, max(i, j)))
