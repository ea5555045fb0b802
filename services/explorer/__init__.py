"""Explorer: predicted and confirmed places, link confidence, loop closing and the local controller."""

from services.explorer.controller import Command, clear_towards, open_directions, velocity_command
from services.explorer.core import (
    NO_PLACE,
    Explorer,
    ExplorerOutput,
    ExplorerParams,
    ExplorerStatus,
    LinkConfidenceEvent,
    LinkDeletedEvent,
    LinkInferredEvent,
    PlaceConfirmedEvent,
    PlaceDeletedEvent,
    PlaceFix,
    PlacePredictedEvent,
    confidence_after_failure,
    confidence_after_traversal,
)

__all__ = [
    "NO_PLACE", "Command", "Explorer", "ExplorerOutput", "ExplorerParams", "ExplorerStatus",
    "LinkConfidenceEvent", "LinkDeletedEvent", "LinkInferredEvent", "PlaceConfirmedEvent",
    "PlaceDeletedEvent", "PlaceFix", "PlacePredictedEvent", "clear_towards", "confidence_after_failure",
    "confidence_after_traversal", "open_directions", "velocity_command",
]
