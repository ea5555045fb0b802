"""Place recognizer: local occupancy histograms, a belief over places, link measurements (Section 4.3)."""

from services.place_recognizer.core import (
    NO_PLACE,
    LinkAccumulator,
    LinkEstimate,
    Localization,
    PlaceRecognizer,
    PlaceRecognizerParams,
    RecognizerOutput,
)

__all__ = [
    "NO_PLACE", "LinkAccumulator", "LinkEstimate", "Localization", "PlaceRecognizer", "PlaceRecognizerParams",
    "RecognizerOutput",
]
